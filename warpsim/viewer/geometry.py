"""Geometry helpers for drawing (pure NumPy): polygon triangulation, segment lists from curves,
unit meshes for instancer prototypes and spheres, quaternion order."""
from __future__ import annotations

import math

import numpy as np

from ..bodies.shapes import icosphere  # below the viewer: scenes (the hair's head) draw it too

__all__ = ["curve_segments", "icosphere", "subsample", "triangulate", "unit_mesh", "xyzw_to_wxyz"]


def triangulate(counts, indices):
    """Fan-triangulate polygons: ``counts`` (F,) vertices per face, ``indices`` (sum counts,) ->
    (T, 3) uint32 triangles (a quad 0 1 2 3 becomes 0 1 2 and 0 2 3)."""
    counts = np.asarray(counts, np.int64).reshape(-1)
    indices = np.asarray(indices, np.int64).reshape(-1)
    if len(counts) and (counts == 3).all():
        return indices.reshape(-1, 3).astype(np.uint32)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    tris = []
    for k in range(3, int(counts.max(initial=3)) + 1):  # faces with >= k vertices give triangle k-2
        sel = starts[counts >= k]
        if len(sel):
            tris.append(np.stack([indices[sel], indices[sel + k - 2], indices[sel + k - 1]], axis=1))
    if not tris:
        return np.zeros((0, 3), np.uint32)
    return np.concatenate(tris).astype(np.uint32)


def curve_segments(points, counts):
    """Line segments (S, 2, 3) of linear curves: ``points`` (V, 3) for ``counts`` (C,) vertices
    per curve; consecutive vertices of each curve are joined."""
    points = np.asarray(points, np.float32).reshape(-1, 3)
    counts = np.asarray(counts, np.int64).reshape(-1)
    if len(counts) and (counts == 2).all():
        return points.reshape(-1, 2, 3)
    ends = np.cumsum(counts)
    keep = np.ones(len(points), bool)
    keep[ends - 1] = False  # the last vertex of a curve starts no segment
    first = np.flatnonzero(keep[: len(points) - 1]) if len(points) else np.zeros(0, np.int64)
    return np.stack([points[first], points[first + 1]], axis=1)


def _axis_frame(axis):
    """Rotation taking +z to ``axis`` ('X', 'Y' or 'Z') as a 3x3 matrix."""
    return {"Z": np.eye(3), "X": np.array([[0, 0, 1], [0, 1, 0], [-1, 0, 0]], float),
            "Y": np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0]], float)}[axis]


def unit_mesh(type_name, attrs, segments=16):
    """(vertices, triangles) for a static UsdGeom gprim given its attribute values (``attrs``:
    {name: value}): Sphere (radius), Cube (size), Cone / Capsule / Cylinder (radius, height,
    axis) or Mesh (points, faceVertexCounts, faceVertexIndices)."""
    if type_name == "Mesh":
        return (np.asarray(attrs["points"], np.float32),
                triangulate(attrs["faceVertexCounts"], attrs["faceVertexIndices"]))
    if type_name == "Sphere":
        v, f = icosphere(2)
        return v * float(attrs.get("radius", 1.0)), f
    if type_name == "Cube":
        s = 0.5 * float(attrs.get("size", 2.0))
        corners = np.array([[(s if (i >> k) & 1 else -s) for k in range(3)] for i in range(8)], np.float32)
        quads = [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]]
        return corners, triangulate([4] * 6, np.array(quads).reshape(-1))
    r = float(attrs.get("radius", 1.0))
    h = float(attrs.get("height", 2.0))
    th = np.linspace(0.0, 2.0 * math.pi, segments, endpoint=False)
    ring = np.stack([np.cos(th), np.sin(th), np.zeros_like(th)], 1) * r
    if type_name == "Cone":
        verts = np.concatenate([ring - [0, 0, h / 2], [[0, 0, h / 2]], [[0, 0, -h / 2]]])
        apex, base = segments, segments + 1
        tris = [(i, (i + 1) % segments, apex) for i in range(segments)]
        tris += [((i + 1) % segments, i, base) for i in range(segments)]
    else:  # Capsule / Cylinder: a closed tube (capsule caps drawn flat)
        verts = np.concatenate([ring - [0, 0, h / 2], ring + [0, 0, h / 2], [[0, 0, -h / 2 - (r if type_name == "Capsule" else 0)]],
                                [[0, 0, h / 2 + (r if type_name == "Capsule" else 0)]]])
        lo, hi = 2 * segments, 2 * segments + 1
        tris = []
        for i in range(segments):
            j = (i + 1) % segments
            tris += [(i, j, j + segments), (i, j + segments, i + segments), (j, i, lo),
                     (i + segments, j + segments, hi)]
    rot = _axis_frame(str(attrs.get("axis", "Z")))
    return (verts @ rot.T).astype(np.float32), np.array(tris, np.uint32)


def xyzw_to_wxyz(q):
    """Quaternions (n, 4) from USD's (x, y, z, w) order... as stored by warpsim's instancers
    (``quath[]`` in x, y, z, w) to viser's (w, x, y, z)."""
    q = np.asarray(q, np.float32).reshape(-1, 4)
    return q[:, [3, 0, 1, 2]]


def subsample(count, limit):
    """Indices of at most ``limit`` of ``count`` elements, evenly strided (None: all)."""
    if limit is None or count <= limit:
        return None
    return np.arange(0, count, math.ceil(count / limit))
