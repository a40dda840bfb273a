"""The world agents live in: :class:`Terrain` (a height field or mesh to walk on), :class:`Obstacles`
(spheres and meshes to steer around) and :class:`FoodSources` (points that attract and feed)."""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from ..core import checks
from ..kernels import agents as K


def as_points(value, what, width=3):
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be an array of shape (n, {width}) [m]") from None
    if a.ndim == 1 and a.size == width:
        a = a[None]
    if a.ndim != 2 or a.shape[1] != width:
        raise ValueError(f"{what} must have shape (n, {width}), got {a.shape}")
    bad = np.flatnonzero(~np.isfinite(a).all(axis=1))
    if len(bad):
        raise ValueError(f"{what}[{bad[0]}] is not finite: {a[bad[0]]}; give finite values")
    return a


def _mesh_arrays(points, faces, what):
    pts = as_points(points, f"{what} points")
    tri = checks.index_array(faces, f"{what} faces")  # 2.5 is refused, never truncated
    try:
        tri = tri.reshape(-1, 3)
    except ValueError:
        raise ValueError(f"{what} faces must be triangles: an int array of shape (m, 3)") from None
    if len(tri) == 0:
        raise ValueError(f"{what} has no triangles")
    if tri.min() < 0 or tri.max() >= len(pts):
        bad = int(np.flatnonzero((tri < 0).any(axis=1) | (tri >= len(pts)).any(axis=1))[0])
        raise ValueError(f"{what} triangle {bad} indexes a vertex outside [0, {len(pts)}): {tri[bad].tolist()}")
    return pts, tri


class Terrain:
    """Ground for agents: y = h(x, z), flat, a height field or a triangle mesh (followed as a
    height field: the highest surface under the agent; model walls with steep but finite
    faces). Build with :meth:`flat`, :meth:`from_heights`, :meth:`from_function` or
    :meth:`from_mesh`."""

    KINDS = {"flat": 0, "heights": 1, "mesh": 2}
    """Terrain kinds by name; the constructor takes a name or its number."""

    def __init__(self, kind, height=0.0, heights=None, origin=(0.0, 0.0), spacing=1.0, points=None, faces=None):
        """Validated here, so a bad argument fails now, not at the first step: ``kind`` "flat"
        (0, the plane y = height), "heights" (1, ``heights`` (nx, nz) [m] at ``origin`` + (i, k)
        ``spacing``) or "mesh" (2, ``points`` (v, 3), ``faces`` (m, 3))."""
        fix = "use Terrain.flat(h), Terrain.from_heights(heights, spacing) or Terrain.from_mesh(points, faces)"
        if isinstance(kind, str):
            kind = self.KINDS[checks.choice(kind, "Terrain kind", tuple(self.KINDS), fix)]
        elif isinstance(kind, bool) or kind not in (0, 1, 2):
            raise ValueError(f"Terrain kind {checks.show(kind)} is unknown; use 'flat' (0), 'heights' (1) or "
                             f"'mesh' (2); {fix}")
        self.kind = int(kind)
        self.flat_height = checks.finite(height, "Terrain height", "m")
        self.spacing = checks.positive(spacing, "Terrain spacing", "m", "the height-field sample spacing")
        o = as_points(origin, "Terrain origin (x, z)", width=2)
        if len(o) != 1:
            raise ValueError(f"Terrain origin must be one (x, z) pair [m], got {len(o)}")
        self.origin = (float(o[0, 0]), float(o[0, 1]))
        if self.kind == 1:
            if heights is None:
                raise ValueError(f"Terrain kind 'heights' needs heights= (a 2-D array [m]); {fix}")
            h = np.asarray(heights, dtype=np.float64) if not isinstance(heights, str) else np.zeros(0)
            if h.ndim != 2 or h.shape[0] < 2 or h.shape[1] < 2:
                raise ValueError(f"terrain heights must be a 2-D array of at least 2 x 2 samples, got shape {h.shape}")
            if not np.isfinite(h).all():
                i, k = np.argwhere(~np.isfinite(h))[0]
                raise ValueError(f"terrain heights[{i}, {k}] is not finite")
            heights = h
        if self.kind == 2:
            if points is None or faces is None:
                raise ValueError(f"Terrain kind 'mesh' needs points= and faces=; {fix}")
            points, faces = _mesh_arrays(points, faces, "terrain mesh")
        self.heights = heights
        self.points = points
        self.faces = faces
        self._cache = {}

    @classmethod
    def flat(cls, height=0.0):
        """The plane y = height [m]."""
        return cls(0, height=checks.finite(height, "terrain height", "m"))

    @classmethod
    def from_heights(cls, heights, spacing, origin=(0.0, 0.0)):
        """Height field: ``heights[i, k]`` [m] at x = origin[0] + i spacing, z = origin[1] +
        k spacing; bilinear in between, clamped outside."""
        h = np.asarray(heights, dtype=np.float64)
        if h.ndim != 2 or h.shape[0] < 2 or h.shape[1] < 2:
            raise ValueError(f"terrain heights must be a 2-D array of at least 2 x 2 samples, got shape {h.shape}")
        if not np.isfinite(h).all():
            i, k = np.argwhere(~np.isfinite(h))[0]
            raise ValueError(f"terrain heights[{i}, {k}] is not finite")
        return cls(1, height=float(h.min()), heights=h, origin=origin, spacing=spacing)

    @classmethod
    def from_function(cls, fn, lower, upper, spacing):
        """Height field sampling ``fn(x, z)`` (NumPy, vectorised) on [lower, upper] (x, z pairs) [m]."""
        lo = as_points(lower, "terrain lower (x, z)", width=2)[0]
        hi = as_points(upper, "terrain upper (x, z)", width=2)[0]
        if not (hi > lo).all():
            raise ValueError(f"terrain upper {hi} must exceed lower {lo} in x and z")
        spacing = checks.positive(spacing, "terrain spacing", "m")
        n = np.maximum(np.ceil((hi - lo) / spacing).astype(int) + 1, 2)
        xs = lo[0] + spacing * np.arange(n[0])
        zs = lo[1] + spacing * np.arange(n[1])
        X, Z = np.meshgrid(xs, zs, indexing="ij")
        return cls.from_heights(np.broadcast_to(fn(X, Z), X.shape), spacing, lo)

    @classmethod
    def from_mesh(cls, points, faces):
        """A triangle mesh (points (v, 3) [m], triangles (m, 3)) followed from above."""
        pts, tri = _mesh_arrays(points, faces, "terrain mesh")
        return cls(2, height=float(pts[:, 1].min()), points=pts, faces=tri)

    # ----------------------------------------------------------------------------------
    def bind(self, device):
        """The kernel struct on ``device`` (built once per device)."""
        key = str(device)
        if key in self._cache:
            return self._cache[key][0]
        t = K.TerrainData()
        t.kind = self.kind
        t.height = self.flat_height
        t.origin_x, t.origin_z = self.origin
        t.spacing = self.spacing
        keep = []
        if self.kind == 1:
            t.heights = wp.array(self.heights.astype(np.float32), dtype=float, device=device)
            t.nx, t.nz = self.heights.shape
            keep.append(t.heights)
        else:
            t.heights = wp.zeros((1, 1), dtype=float, device=device)
            t.nx = t.nz = 1
        if self.kind == 2:
            mesh = wp.Mesh(points=wp.array(self.points.astype(np.float32), dtype=wp.vec3, device=device),
                           indices=wp.array(self.faces.reshape(-1).astype(np.int32), dtype=int, device=device))
            t.mesh = mesh.id
            t.top = float(self.points[:, 1].max() + 1.0)
            t.bottom = float(self.points[:, 1].min() - 1.0)
            keep.append(mesh)
        else:
            t.mesh = 0
            t.top = t.bottom = 0.0
        self._cache[key] = (t, keep)
        return t

    def sample(self, points, device=None) -> np.ndarray:
        """(h, dh/dx, dh/dz) at points (n, 3) or (n, 2) (x, z) as a NumPy (n, 3) array."""
        device = wp.get_device(device)
        p = np.asarray(points, dtype=np.float64)
        if p.ndim == 2 and p.shape[1] == 2:
            p = np.stack([p[:, 0], np.zeros(len(p)), p[:, 1]], axis=1)
        p = as_points(p, "terrain sample points")
        out = wp.zeros(len(p), dtype=wp.vec3, device=device)
        wp.launch(K.sample_terrain, len(p), inputs=[self.bind(device), wp.array(p.astype(np.float32), dtype=wp.vec3,
                                                                                 device=device), out], device=device)
        return out.numpy().astype(np.float64)

    def height(self, points, device=None) -> np.ndarray:
        """Ground height h [m] at points (n, 3) or (n, 2)."""
        return self.sample(points, device)[:, 0]

    def bounds(self):
        """((x_min, z_min), (x_max, z_max)) of a height field or mesh, None for a flat plane."""
        if self.kind == 1:
            o = np.array(self.origin)
            return o, o + self.spacing * (np.array(self.heights.shape) - 1)
        if self.kind == 2:
            return self.points[:, [0, 2]].min(axis=0), self.points[:, [0, 2]].max(axis=0)
        return None

    def mesh(self, size=50.0) -> tuple[np.ndarray, np.ndarray]:
        """(points (v, 3), triangles (m, 3)) for drawing; a flat plane is a square of side ``size``."""
        if self.kind == 2:
            return self.points, self.faces
        if self.kind == 1:
            nx, nz = self.heights.shape
            xs = self.origin[0] + self.spacing * np.arange(nx)
            zs = self.origin[1] + self.spacing * np.arange(nz)
            X, Z = np.meshgrid(xs, zs, indexing="ij")
            pts = np.stack([X, self.heights, Z], axis=-1).reshape(-1, 3)
        else:
            h = 0.5 * size
            pts = np.array([[-h, self.flat_height, -h], [h, self.flat_height, -h], [-h, self.flat_height, h], [h, self.flat_height, h]])
            nx = nz = 2
        idx = np.arange(nx * nz).reshape(nx, nz)
        a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[:-1, 1:], idx[1:, 1:]
        # counter-clockwise seen from above (+Y): normals point up
        tri = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)])
        return pts, tri


class Obstacles:
    """Obstacles agents steer around and never enter.

    spheres: [(center (3,), radius)] [m]; planes: [(normal (3,), offset)] half-spaces n . x >=
    offset are free (normals are normalised); meshes: [(points (v, 3), triangles (m, 3))]
    (closed meshes: the inside is solid)."""

    def __init__(self, spheres=(), planes=(), meshes=()):
        self.spheres = []
        for k, s in enumerate(spheres):
            try:
                c, r = s
            except (TypeError, ValueError):
                raise ValueError(f"obstacle sphere {k} must be (center, radius), got {s!r}") from None
            c = as_points(c, f"obstacle sphere {k} center")[0]
            if not (math.isfinite(float(r)) and float(r) > 0.0):
                raise ValueError(f"obstacle sphere {k} radius must be > 0 [m], got {r}")
            self.spheres.append((c, float(r)))
        self.planes = []
        for k, pl in enumerate(planes):
            try:
                n, off = pl
            except (TypeError, ValueError):
                raise ValueError(f"obstacle plane {k} must be (normal, offset), got {pl!r}") from None
            n = as_points(n, f"obstacle plane {k} normal")[0]
            if np.linalg.norm(n) == 0.0 or not math.isfinite(float(off)):
                raise ValueError(f"obstacle plane {k} needs a non-zero normal and a finite offset, got {pl!r}")
            self.planes.append((n / np.linalg.norm(n), float(off)))
        self.meshes = []
        for k, m in enumerate(meshes):
            try:
                pts, tri = m
            except (TypeError, ValueError):
                raise ValueError(f"obstacle mesh {k} must be (points, triangles), got {type(m).__name__}") from None
            self.meshes.append(_mesh_arrays(pts, tri, f"obstacle mesh {k}"))
        self._cache = {}

    @property
    def count(self):
        return len(self.spheres) + len(self.planes) + len(self.meshes)

    def bind(self, device):
        """The kernel struct on ``device`` (built once per device)."""
        key = str(device)
        if key in self._cache:
            return self._cache[key][0]
        o = K.Obstacles()
        sph = np.array([[*c, r] for c, r in self.spheres] or [[0.0, 0.0, 0.0, 0.0]], dtype=np.float32)
        pln = np.array([[*n, off] for n, off in self.planes] or [[0.0, 1.0, 0.0, 0.0]], dtype=np.float32)
        o.spheres = wp.array(sph, dtype=wp.vec4, device=device)
        o.planes = wp.array(pln, dtype=wp.vec4, device=device)
        keep = [o.spheres, o.planes]
        ids = []
        for pts, tri in self.meshes:
            mesh = wp.Mesh(points=wp.array(pts.astype(np.float32), dtype=wp.vec3, device=device),
                           indices=wp.array(tri.reshape(-1).astype(np.int32), dtype=int, device=device))
            keep.append(mesh)
            ids.append(mesh.id)
        o.meshes = wp.array(ids or [0], dtype=wp.uint64, device=device)
        keep.append(o.meshes)
        o.sphere_count = len(self.spheres)
        o.plane_count = len(self.planes)
        o.count = self.count
        self._cache[key] = (o, keep)
        return o

    def distance(self, points, max_dist=1.0e6, device=None) -> np.ndarray:
        """Smallest signed distance [m] from each point (n, 3) to the obstacles (NumPy (n,))."""
        device = wp.get_device(device)
        p = as_points(points, "obstacle distance points")
        out = wp.zeros(len(p), dtype=float, device=device)
        wp.launch(K.eval_obstacle_distance, len(p), inputs=[self.bind(device), wp.array(
            p.astype(np.float32), dtype=wp.vec3, device=device), float(max_dist), out], device=device)
        return out.numpy().astype(np.float64)


class FoodSources:
    """Food at ``positions`` (n, 3) [m] holding ``amounts`` (n,) bites each (ints >= 0)."""

    def __init__(self, positions, amounts):
        self.positions = as_points(positions, "food positions")
        a = np.asarray(amounts)
        if a.ndim == 0:
            a = np.full(len(self.positions), a)
        if a.shape != (len(self.positions),):
            raise ValueError(f"food amounts must have shape ({len(self.positions)},), got {a.shape}")
        if not np.all(np.equal(np.mod(a, 1), 0)) or (a < 0).any():
            bad = int(np.flatnonzero((np.mod(a, 1) != 0) | (a < 0))[0])
            raise ValueError(f"food source {bad} has amount {a[bad]}; amounts are whole bites >= 0")
        self.initial_amounts = a.astype(np.int64)


def food_struct(food, device):
    f = K.Food()
    if food is None:
        f.positions = wp.zeros(1, dtype=wp.vec3, device=device)
        f.amounts = wp.zeros(1, dtype=int, device=device)
        f.count = 0
    else:
        f.positions = wp.array(food.positions.astype(np.float32), dtype=wp.vec3, device=device)
        f.amounts = wp.array(food.initial_amounts.astype(np.int32), dtype=int, device=device)
        f.count = len(food.positions)
    return f
