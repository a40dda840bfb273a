"""The preview renderer: uploads a :class:`~warpsim.render.geometry.FrameGeometry`, builds its
``wp.Mesh`` and ``wp.Bvh`` and casts one ray per pixel with ``warpsim.kernels.render``.

    r = Renderer(480, 360, device="cpu")
    rgb = r.render(geometry, camera)        # (360, 480, 3) uint8, sRGB
"""
from __future__ import annotations

import math

import numpy as np
import warp as wp

from ..kernels import render as K

MAX_SIZE = 8192


def check_size(width, height):
    """ValueError unless 1 <= width, height <= MAX_SIZE (integers)."""
    for name, v in (("width", width), ("height", height)):
        if int(v) != v or not 1 <= v <= MAX_SIZE:
            raise ValueError(f"image {name} {v!r} must be an integer in [1, {MAX_SIZE}], e.g. --size 480x360")
    return int(width), int(height)


def nice_step(length):
    """A round checker size [m] about a tenth of ``length``."""
    raw = max(float(length) / 10.0, 1e-6)
    e = 10.0 ** math.floor(math.log10(raw))
    return min((m * e for m in (1.0, 2.0, 5.0, 10.0)), key=lambda s: abs(s - raw))


class Renderer:
    """Casts ``width`` x ``height`` rays on ``device``; see the module docstring.

    Args:
        light: direction towards the light (normalised here), +Y up.
        ambient: share of light that reaches surfaces in shadow, in [0, 1].
        background: (horizon, zenith) colours of the sky.
        smoke_extinction: extinction per unit density [1/m] of the volume.
    """

    def __init__(self, width, height, device=None, light=(-0.35, 1.0, 0.45), ambient=0.35,
                 background=((0.92, 0.94, 0.97), (0.62, 0.72, 0.86)), smoke_extinction=30.0):
        self.width, self.height = check_size(width, height)
        self.device = wp.get_device(device)
        light = np.asarray(light, np.float64)
        self.light = light / np.linalg.norm(light)
        self.ambient = float(ambient)
        self.background = background
        self.smoke_extinction = float(smoke_extinction)
        self._dummy_density = wp.zeros((1, 1, 1), dtype=float, device=self.device)
        self.last_seconds = None
        self._buffers = {}  # name -> device array reused while the shape stays (pictures of one scene)
        self._meshes = {}  # name -> (triangles, wp.Mesh): refitted while the triangles stay

    def _array(self, a, dtype, name=None):
        """``a`` on the device: a new array, or (``name`` given) a view of the first entries of that name's
        buffer, refilled in one copy (the buffer only grows: the next pictures' views start where these did,
        so meshes and BVHs over them are refitted, not rebuilt)."""
        a = np.ascontiguousarray(a)
        if name is None:
            return wp.array(a, dtype=dtype, device=self.device)
        view = self._grown(name, a.size // wp.types.type_size(dtype), dtype)
        if view.shape[0]:
            view.assign(a)
        return view

    def _grown(self, name, count, dtype):
        """A view of the first ``count`` ``dtype`` of the buffer ``name`` (allocated again only to grow)."""
        buf = self._buffers.get(name)
        if buf is None or buf.dtype != dtype or buf.shape[0] < count:
            buf = self._buffers[name] = wp.empty(max(count, 1), dtype=dtype, device=self.device)
        return _part(buf, 0, count)

    def _output(self, name, count, dtype):
        """The buffer ``name`` of ``count`` ``dtype`` the kernels write (kept while the count stays)."""
        buf = self._buffers.get(name)
        if buf is None or buf.shape[0] != count:
            buf = self._buffers[name] = wp.empty(count, dtype=dtype, device=self.device)
        return buf

    def _mesh(self, points, triangles, name):
        """(0/1, id) of a ``wp.Mesh`` of the triangles over ``points`` (a device array: a view of the
        pictures' joined vertices; id 0 when there are none); the last picture's mesh of ``name`` is
        refitted when its triangles and its points' place are the same (sweep thumbnails, frames of one
        cache: no BVH built per picture)."""
        if not len(triangles):
            return 0, 0
        cached = self._meshes.get(name)
        if cached is not None and cached[0].shape == triangles.shape and np.array_equal(cached[0], triangles) \
                and (cached[1].points.ptr, cached[1].points.shape) == (points.ptr, points.shape):
            cached[1].refit()
            return 1, cached[1].id
        mesh = wp.Mesh(points, self._array(triangles.reshape(-1), wp.int32))
        self._meshes[name] = (np.array(triangles, copy=True), mesh)
        return 1, mesh.id

    def _caps(self, lowers, uppers, name):
        """(0/1, id) of a ``wp.Bvh`` over capsule boxes ``lowers``, ``uppers`` (device views of the pictures'
        joined boxes, ``kernels.render.capsule_boxes``; id 0 when there are none), refitted when the last
        picture's BVH of ``name`` was over the same place."""
        if not lowers.shape[0]:
            return 0, 0
        bvh = self._meshes.get(name)
        if bvh is not None and (bvh.lowers.ptr, bvh.lowers.shape, bvh.uppers.ptr) == (lowers.ptr, lowers.shape,
                                                                                     uppers.ptr):
            bvh.refit()
        else:
            bvh = self._meshes[name] = wp.Bvh(lowers, uppers)
        return 1, bvh.id

    def _camera(self, camera):
        vec3 = wp.vec3
        f, r_, u = camera.basis()
        tx, ty = camera.tangents(self.width, self.height)
        cam = K.Camera()
        cam.eye, cam.forward, cam.right, cam.up = vec3(*camera.eye), vec3(*f), vec3(*r_), vec3(*u)
        cam.tan_x, cam.tan_y = float(tx), float(ty)
        return cam

    def _lighting(self, geom, camera, ground_y):
        """The :class:`Lighting` of one picture: light, sky, and the ground (at ``ground_y``, see
        :meth:`render`) with its checker and fade sized by ``geom``'s bounds."""
        vec3 = wp.vec3
        bounds = geom.bounds()
        lit = K.Lighting()
        lit.light = vec3(*self.light)
        lit.ambient = self.ambient
        lit.sky_low, lit.sky_high = vec3(*self.background[0]), vec3(*self.background[1])
        if ground_y is None:
            ground_y = None if bounds is None else float(bounds[0][1])
        lit.ground = 0 if ground_y is None or ground_y is False or bounds is None else 1  # nothing drawn: sky only
        lit.ground_y = 0.0 if not lit.ground else float(ground_y)
        extent = 1.0 if bounds is None else float(np.max(bounds[1] - bounds[0]))
        lit.checker = nice_step(extent)
        lit.fade = 3.0 * extent + float(np.linalg.norm(camera.eye - camera.target))
        return lit

    def _no_volume(self):
        vol = K.Volume()
        vol.density = self._dummy_density
        vol.origin, vol.dx, vol.color, vol.active = wp.vec3(0.0, 0.0, 0.0), 1.0, wp.vec3(0.0, 0.0, 0.0), 0
        vol.extinction = self.smoke_extinction
        return vol

    def render(self, geom, camera, ground_y=None, linear=False):
        """(height, width, 3) uint8 sRGB image of ``geom`` seen by ``camera`` (float linear RGB
        with ``linear=True``). ``ground_y``: height of the ground plane [m] (None: the bottom of
        the geometry's bounds; ``False``: no ground; an empty frame has none)."""
        vol = self._no_volume()
        if geom.volume is not None and geom.volume["density"].size:
            v = geom.volume
            vol.density = wp.array(v["density"], dtype=float, device=self.device)
            vol.origin, vol.dx = wp.vec3(*v["origin"]), float(v["dx"])
            vol.color = wp.vec3(*v["color"])
            vol.active = 1
        return self._draw([(geom, ground_y)], camera, vol, linear)[0].copy()  # (a view on the CPU)

    def render_many(self, items, camera):
        """[(height, width, 3) uint8 sRGB image] of each ``(geom, ground_y)`` of ``items`` seen by
        ``camera``, as :meth:`render` draws it (the same kernels), in one launch for all of them (a
        sweep's thumbnails: one picture is too few pixels to fill a GPU). Picture ``k`` keeps its own
        mesh, glass and capsule BVH (refitted for the next call's picture ``k`` when its triangles or
        count are the same; a BVH built from other points may settle a ray's tie between two faces
        otherwise: on the H200 some pictures differed from ``render``'s, on the CPU none did). A
        geometry with a density volume is drawn by :meth:`render`."""
        items = list(items)
        if any(g.volume is not None and g.volume["density"].size for g, _ in items):
            return [self.render(g, camera, ground_y=ground) for g, ground in items]
        if not items:
            return []
        return list(self._draw(items, camera, self._no_volume()).copy())  # (copied: the buffer is reused)

    def _draw(self, items, camera, vol, linear=False):
        """(pictures, height, width, 3) uint8 sRGB (float linear RGB with ``linear``) of ``items``
        (``(geom, ground_y)``) and the volume ``vol``: one launch of ``render_pictures`` and, for sRGB,
        one of ``encode_srgb8`` on the device (the array is a view of the device's output on the CPU)."""
        vec3 = wp.vec3

        def joined(field, dtype):
            parts = [getattr(g, field) for g, _ in items]
            return self._array(np.concatenate(parts) if len(parts) > 1 else parts[0], dtype, field)

        def starts(field):
            return np.cumsum([0] + [len(getattr(g, field)) for g, _ in items[:-1]]).astype(np.int32)

        def bases(field):
            return self._array(starts(field), wp.int32, field + "_base")

        # every picture's vertices and capsules in one copy each; a picture's mesh and BVH are views of them
        points, glass_points = joined("points", vec3), joined("glass_points", vec3)
        cap_a, cap_b, cap_r = joined("cap_a", vec3), joined("cap_b", vec3), joined("cap_r", float)
        lowers, uppers = self._grown("cap_lowers", cap_r.shape[0], vec3), self._grown("cap_uppers", cap_r.shape[0], vec3)
        if cap_r.shape[0]:
            wp.launch(K.capsule_boxes, dim=cap_r.shape[0], inputs=[cap_a, cap_b, cap_r], outputs=[lowers, uppers],
                      device=self.device)
        meshes = np.zeros(len(items), np.uint64)
        glasses, bvhs = meshes.copy(), meshes.copy()
        lights = []
        point_at, glass_at, cap_at = starts("points"), starts("glass_points"), starts("cap_r")
        for k, (g, ground) in enumerate(items):
            p, gp, c = int(point_at[k]), int(glass_at[k]), int(cap_at[k])
            meshes[k] = self._mesh(_part(points, p, len(g.points)), g.triangles, ("opaque", k))[1]
            glasses[k] = self._mesh(_part(glass_points, gp, len(g.glass_points)), g.glass_triangles, ("glass", k))[1]
            bvhs[k] = self._caps(_part(lowers, c, len(g.cap_r)), _part(uppers, c, len(g.cap_r)), ("caps", k))[1]
            lights.append(self._lighting(g, camera, ground))

        pixels = self.width * self.height
        image = self._output("pictures", len(items) * pixels, vec3)
        wp.launch(K.render_pictures, dim=(len(items), pixels), device=self.device, inputs=[
            self._camera(camera), wp.array(lights, dtype=K.Lighting, device=self.device), self.width, self.height,
            self._array(meshes, wp.uint64, "meshes"), bases("triangles"), joined("face_colors", vec3),
            joined("corner_normals", vec3), self._array(glasses, wp.uint64, "glasses"), bases("glass_triangles"),
            joined("glass_colors", vec3), joined("glass_alpha", float), self._array(bvhs, wp.uint64, "bvhs"),
            bases("cap_r"), cap_a, cap_b, cap_r, joined("cap_colors", vec3), vol,
        ], outputs=[image])
        if linear:
            return image.numpy().reshape(len(items), self.height, self.width, 3)
        codes = self._output("srgb8", 3 * image.shape[0], wp.uint8)
        wp.launch(K.encode_srgb8, dim=image.shape[0], inputs=[image], outputs=[codes], device=self.device)
        return codes.numpy().reshape(len(items), self.height, self.width, 3)


def _part(buf, start, count):
    """``buf[start:start + count]`` (a view), or an empty array when ``count`` is 0 (Warp slices no empty range)."""
    if count == 0:
        return wp.empty(0, dtype=buf.dtype, device=buf.device)
    return buf[start:start + count]


def to_srgb8(linear):
    """uint8 sRGB from linear RGB in [0, 1] (clipped), in NumPy (the renderer encodes its pictures on
    the device, ``kernels.render.encode_srgb8``: the same curve, within one code)."""
    c = np.clip(linear, 0.0, 1.0)
    s = np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.power(c, 1.0 / 2.4) - 0.055)
    return (s * 255.0 + 0.5).astype(np.uint8)
