"""Pictures of warpsim caches without leaving warpsim: a preview renderer written as Warp kernels.

Renders the prims of a USD cache (meshes, points as spheres, curves as thin tubes, instanced
agents, colliders, smoke density as a ray-marched volume) with Lambert shading, a ground plane
with shadows and a camera that frames the scene's bounds, and writes PNG, GIF or MP4 files.

Drives ``warpsim.kernels.render``. Entry points: Renderer, Camera, frame_bounds, GeometryBuilder,
render_cache (also ``warpsim render CACHE`` and ``warpsim plot CACHE``). The README's previews:
``python -m warpsim.render.gallery`` (each clip made by ``python -m warpsim run`` in a child process).
"""

from .cache import render_cache
from .camera import Camera, frame_bounds, parse_camera
from .geometry import FrameGeometry, GeometryBuilder
from .renderer import Renderer
from .usd_scene import CacheScene

__all__ = ["CacheScene", "Camera", "FrameGeometry", "GeometryBuilder", "Renderer", "frame_bounds", "parse_camera",
           "render_cache"]
