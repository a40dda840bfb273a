"""What one frame of the preview renderer is made of, gathered on the host (pure NumPy).

:class:`GeometryBuilder` collects polygon meshes (opaque or translucent), spheres, capsules and a
density volume, and :meth:`GeometryBuilder.build` returns a :class:`FrameGeometry` of flat
arrays the renderer uploads: triangles with a colour per face and a shading normal per face
corner, capsules ``(a, b, r)`` (a sphere is a capsule with ``a == b``) and a dense density grid.
Shapes USD describes analytically (cubes, cones) are tessellated here; spheres and capsules stay
exact. Units are metres; colours linear RGB in [0, 1].
"""
from __future__ import annotations

from typing import Optional
from dataclasses import dataclass, field

import numpy as np

SMOOTH_COS = 0.9  # corners whose vertex normal is within ~25 degrees of the face normal shade smoothly


@dataclass
class FrameGeometry:
    """Flat arrays of one frame (shapes in brackets; F faces, C capsules)."""

    points: np.ndarray  # opaque triangle vertices (V, 3) [m]
    triangles: np.ndarray  # (F, 3) int32 vertex indices
    face_colors: np.ndarray  # (F, 3)
    corner_normals: np.ndarray  # (3 F, 3) unit shading normals
    glass_points: np.ndarray  # translucent triangle vertices (V', 3) [m]
    glass_triangles: np.ndarray  # (F', 3)
    glass_colors: np.ndarray  # (F', 3)
    glass_alpha: np.ndarray  # (F',) opacity in (0, 1)
    cap_a: np.ndarray  # (C, 3) capsule end a [m]
    cap_b: np.ndarray  # (C, 3) capsule end b [m]
    cap_r: np.ndarray  # (C,) radius [m]
    cap_colors: np.ndarray  # (C, 3)
    volume: Optional[dict] = None  # {"density": (nx, ny, nz), "origin": (3,), "dx": float, "color": (3,)} or None

    def bounds(self):
        """Axis-aligned bounds [[lo], [hi]] [m] of everything drawn (None when empty)."""
        boxes = []
        for p in (self.points, self.glass_points):
            if len(p):
                boxes.append((p.min(0), p.max(0)))
        if len(self.cap_r):
            r = self.cap_r.max()  # (the same bits as the ends' elementwise min and max, reduced after)
            boxes.append((np.minimum(self.cap_a.min(0), self.cap_b.min(0)) - r,
                          np.maximum(self.cap_a.max(0), self.cap_b.max(0)) + r))
        if self.volume is not None:
            v = self.volume
            boxes.append((np.asarray(v["origin"]), np.asarray(v["origin"]) + v["dx"] * np.array(v["density"].shape)))
        if not boxes:
            return None
        return np.array([np.min([b[0] for b in boxes], 0), np.max([b[1] for b in boxes], 0)], np.float64)


def _colors(color, n, default=(0.7, 0.7, 0.7)):
    """(n, 3) float32 colours from None, one colour or n colours."""
    if color is None:
        color = default
    c = np.asarray(color, np.float32).reshape(-1, 3)
    if len(c) == 1:
        return np.repeat(c, n, axis=0)
    if len(c) != n:
        raise ValueError(f"colour array has {len(c)} entries for {n} elements")
    return c


def triangulate(counts, indices):
    """Fan-triangulate polygons: (T, 3) vertex indices and the polygon of each triangle (T,)."""
    counts = np.asarray(counts, np.int64).reshape(-1)
    indices = np.asarray(indices, np.int64).reshape(-1)
    if len(counts) == 0:
        return np.zeros((0, 3), np.int64), np.zeros(0, np.int64)
    if (counts == 3).all():
        return indices.reshape(-1, 3), np.arange(len(counts))
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    tri_per = np.maximum(counts - 2, 0)
    poly = np.repeat(np.arange(len(counts)), tri_per)
    k = np.arange(len(poly)) - np.repeat(np.cumsum(tri_per) - tri_per, tri_per)  # triangle within its polygon
    s = starts[poly]
    tris = np.stack([indices[s], indices[s + k + 1], indices[s + k + 2]], axis=1)
    return tris, poly


def corner_normals(points, tris, smooth=True):
    """(3 T, 3) shading normals: area-weighted vertex normals where they are close to the face
    normal (cos > SMOOTH_COS), the face normal elsewhere (creases, box corners)."""
    p = np.asarray(points, np.float64)
    if len(tris) == 0:
        return np.zeros((0, 3), np.float32)
    a, b, c = p[tris[:, 0]], p[tris[:, 1]], p[tris[:, 2]]
    fn = _cross(b - a, c - a)  # length = 2 x area
    unit = fn / np.maximum(_norm(fn), 1e-30)
    corners = np.repeat(unit, 3, axis=0)
    if smooth:
        # a vertex's normal: its faces' fn summed corner 0 of every face, then 1, then 2 (bincount
        # adds in input order: the same sums, bit for bit, as np.add.at corner by corner)
        at = np.asarray(tris).T.reshape(-1)
        vn = np.empty_like(p)
        for k in range(3):
            vn[:, k] = np.bincount(at, weights=np.tile(fn[:, k], 3), minlength=len(p))
        vn /= np.maximum(_norm(vn), 1e-30)
        vc = vn[tris.reshape(-1)]
        d = vc * corners
        ok = d[:, 0] + d[:, 1] + d[:, 2] > SMOOTH_COS
        corners[ok] = vc[ok]
    return corners.astype(np.float32)


# np.cross and np.linalg.norm(axis=1) of (n, 3) rows, the same operations in the same order
# (bit for bit) without their generality's overhead
def _cross(u, v):
    out = np.empty_like(u)
    out[:, 0] = u[:, 1] * v[:, 2] - u[:, 2] * v[:, 1]
    out[:, 1] = u[:, 2] * v[:, 0] - u[:, 0] * v[:, 2]
    out[:, 2] = u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]
    return out


def _norm(x):
    """(n, 1) lengths of rows x (n, 3)."""
    sq = x * x
    return np.sqrt(sq[:, 0] + sq[:, 1] + sq[:, 2])[:, None]


@dataclass(frozen=True)
class MeshFaces:
    """What a mesh's polygons and colour make of any V points: triangles (T, 3) int64 and a colour
    per triangle (T, 3) float32 (built once for a topology shared by many frames or worlds)."""

    triangles: np.ndarray
    face_colors: np.ndarray
    vertex_count: int  # V, the points these faces were built for (per-vertex colours depend on it)


def mesh_faces(counts, indices, color, vertex_count):
    """:class:`MeshFaces` of polygons (counts (P,), indices) over ``vertex_count`` points coloured
    by ``color``: None, one colour, one per vertex (averaged per triangle) or one per polygon;
    None when there are no triangles."""
    tris, poly = triangulate(counts, indices)
    if len(tris) == 0:
        return None
    c = None if color is None else np.asarray(color, np.float32).reshape(-1, 3)
    if c is None or len(c) == 1:
        fc = _colors(c, len(tris))
    elif len(c) == vertex_count:
        fc = c[tris].mean(1)
    elif len(c) == len(np.asarray(counts).reshape(-1)):
        fc = c[poly]
    else:
        fc = _colors(c[:1], len(tris))
    return MeshFaces(tris, fc, int(vertex_count))


def cube_mesh(size):
    """Points (8, 3), counts and indices of a cube of edge ``size`` centred at the origin."""
    h = 0.5 * float(size)
    pts = np.array([[(h if (i >> k) & 1 else -h) for k in range(3)] for i in range(8)])
    faces = [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]]
    return pts, [4] * 6, np.array(faces).reshape(-1)


def cone_mesh(radius, height, axis="Z", segments=24):
    """A closed cone along ``axis`` centred at the origin (apex at +height/2), as USD's Cone."""
    th = 2.0 * np.pi * np.arange(segments) / segments
    ring = np.stack([radius * np.cos(th), radius * np.sin(th), np.full(segments, -0.5 * height)], 1)
    pts = np.vstack([ring, [[0, 0, 0.5 * height], [0, 0, -0.5 * height]]])
    apex, base = segments, segments + 1
    tris = [[s, (s + 1) % segments, apex] for s in range(segments)] + \
           [[(s + 1) % segments, s, base] for s in range(segments)]
    perm = {"X": [2, 0, 1], "Y": [1, 2, 0], "Z": [0, 1, 2]}[axis]
    return pts[:, perm], [3] * len(tris), np.array(tris).reshape(-1)


@dataclass
class GeometryBuilder:
    """Accumulates one frame's geometry; see the module docstring."""

    _meshes: list = field(default_factory=list)
    _glass: list = field(default_factory=list)
    _caps: list = field(default_factory=list)
    volume: Optional[dict] = None

    def add_mesh(self, points, counts, indices, color=None, opacity=1.0, smooth=True):
        """Polygons (points (V, 3), counts (P,), indices) coloured by one colour, one per vertex
        (averaged per triangle) or one per polygon; ``opacity`` < 1 makes them translucent."""
        pts = np.asarray(points, np.float32).reshape(-1, 3)
        self.add_faces(pts, mesh_faces(counts, indices, color, len(pts)), opacity, smooth)

    def add_faces(self, points, faces, opacity=1.0, smooth=True):
        """``faces`` (:class:`MeshFaces` or None: nothing) over ``points`` (V, 3) [m]; as :meth:`add_mesh`."""
        if faces is None:
            return
        pts = np.asarray(points, np.float32).reshape(-1, 3)
        if opacity < 1.0:
            if opacity > 0.0:
                self._glass.append((pts, faces.triangles, faces.face_colors, float(opacity)))
        else:
            self._meshes.append((pts, faces.triangles, faces.face_colors, corner_normals(pts, faces.triangles, smooth)))

    def extend(self, other):
        """Add everything ``other`` (a GeometryBuilder) holds, after what this one holds."""
        self._meshes.extend(other._meshes)
        self._glass.extend(other._glass)
        self._caps.extend(other._caps)
        if other.volume is not None:
            self.volume = other.volume

    def add_capsules(self, a, b, radius, color=None):
        """Capsules from a (n, 3) to b (n, 3) [m] of radius (scalar or (n,)) [m]."""
        a = np.asarray(a, np.float32).reshape(-1, 3)
        b = np.asarray(b, np.float32).reshape(-1, 3)
        if len(a) == 0:
            return
        r = np.broadcast_to(np.asarray(radius, np.float32), (len(a),)).astype(np.float32)
        self._caps.append((a, b, r, _colors(color, len(a))))

    def add_spheres(self, centers, radius, color=None):
        """Spheres at centers (n, 3) [m] of radius (scalar or (n,)) [m]."""
        self.add_capsules(centers, centers, radius, color)

    def set_volume(self, density, origin, dx, color=(0.8, 0.8, 0.85)):
        """A density grid (nx, ny, nz) whose cell (0,0,0) spans [origin, origin + dx] [m]."""
        self.volume = {"density": np.ascontiguousarray(density, np.float32), "origin": np.asarray(origin, np.float32),
                       "dx": float(dx), "color": np.asarray(color, np.float32)}

    def build(self):
        def concat(parts, with_normals):
            if not parts:
                return (np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32), np.zeros((0, 3), np.float32),
                        np.zeros((0, 3) if with_normals else 0, np.float32))
            offsets = np.cumsum([0] + [len(p[0]) for p in parts[:-1]])
            pts = np.concatenate([p[0] for p in parts])
            tris = np.concatenate([p[1] + o for p, o in zip(parts, offsets)]).astype(np.int32)
            cols = np.concatenate([p[2] for p in parts])
            if with_normals:
                extra = np.concatenate([p[3] for p in parts])
            else:
                extra = np.concatenate([np.full(len(p[1]), p[3], np.float32) for p in parts])
            return pts, tris, cols, extra

        pts, tris, cols, normals = concat(self._meshes, True)
        gpts, gtris, gcols, galpha = concat(self._glass, False)
        if self._caps:
            a, b, r, c = (np.concatenate([cap[k] for cap in self._caps]) for k in range(4))
        else:
            a = b = c = np.zeros((0, 3), np.float32)
            r = np.zeros(0, np.float32)
        return FrameGeometry(pts, tris, cols, normals, gpts, gtris, gcols, galpha, a, b, r, c, self.volume)
