"""Meshing: marching cubes written as Warp kernels, welded and watertight with normals
(``marching_cubes``), and moving metaballs whose topology changes every frame (``metaballs``).

Drives ``warpsim.kernels.marching_cubes`` and ``warpsim.kernels.implicit_fields``.
Entry classes: MarchingCubes, marching_cubes, Metaballs.
"""

from .marching_cubes import MarchingCubes, MarchingCubesResult, marching_cubes, topology_changed
from .metaballs import Metaballs

__all__ = ["MarchingCubes", "MarchingCubesResult", "marching_cubes", "topology_changed", "Metaballs"]
