"""Mouse picking against what is drawn, and the drag target (pure NumPy).

* :func:`ray_triangles`: nearest hit of a ray with a triangle mesh (Moller-Trumbore).
* :func:`pick_mesh_vertex`: the grabbable vertex of the hit triangle nearest the hit point.
* :func:`pick_point`: the grabbable point nearest a ray (within its drawn radius, if given).
* :func:`camera_plane_target`: the pointer's ray met with the plane through the grabbed point
  that faces the camera: where the drag spring pulls the grabbed particle.
* :func:`segment_ribbons`: crossed ribbons around drawn curve segments (hair): a mesh the browser
  can hit, so a click on the curves picks the nearest curve point to the pointer's ray.
"""
from __future__ import annotations

import numpy as np

__all__ = ["camera_plane_target", "pick_mesh_vertex", "pick_point", "pointer_ray", "ray_triangles", "segment_ribbons",
           "segment_ribbon_triangles"]


def _unit(v, what):
    v = np.asarray(v, np.float64).reshape(3)
    n = np.linalg.norm(v)
    if not np.isfinite(n) or n == 0.0:
        raise ValueError(f"{what} {v.tolist()} must be a finite non-zero vector")
    return v / n


def ray_triangles(origin, direction, vertices, triangles, eps=1e-12):
    """(distance t [m] along the unit ray, triangle index, hit point) of the nearest hit with
    t > 0, or (inf, -1, None). ``vertices`` (V, 3), ``triangles`` (T, 3) ints."""
    o = np.asarray(origin, np.float64).reshape(3)
    d = _unit(direction, "ray direction")
    v = np.asarray(vertices, np.float64)
    tri = np.asarray(triangles, np.int64).reshape(-1, 3)
    if len(tri) == 0:
        return np.inf, -1, None
    a, b, c = v[tri[:, 0]], v[tri[:, 1]], v[tri[:, 2]]
    e1, e2 = b - a, c - a
    p = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, p)
    ok = np.abs(det) > eps
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = o - a
    u = np.einsum("ij,ij->i", s, p) * inv
    q = np.cross(s, e1)
    w = (q @ d) * inv
    t = np.einsum("ij,ij->i", e2, q) * inv
    hit = ok & (u >= 0) & (w >= 0) & (u + w <= 1) & (t > 0)
    if not hit.any():
        return np.inf, -1, None
    t = np.where(hit, t, np.inf)
    k = int(np.argmin(t))
    return float(t[k]), k, o + t[k] * d


def pick_mesh_vertex(origin, direction, vertices, triangles, grabbable=None):
    """Vertex to grab where the ray hits the mesh: of the hit triangle's grabbable vertices the
    one nearest the hit point, else the grabbable vertex nearest the hit point; -1 on a miss.
    ``grabbable``: bool (V,) (None: all)."""
    _, k, hit = ray_triangles(origin, direction, vertices, triangles)
    if k < 0:
        return -1
    v = np.asarray(vertices, np.float64)
    ok = np.ones(len(v), bool) if grabbable is None else np.asarray(grabbable, bool)
    corners = [int(i) for i in np.asarray(triangles).reshape(-1, 3)[k] if ok[int(i)]]
    candidates = np.array(corners) if corners else np.flatnonzero(ok)
    if len(candidates) == 0:
        return -1
    return int(candidates[np.argmin(np.linalg.norm(v[candidates] - hit, axis=1))])


def pick_point(origin, direction, points, radius=None, grabbable=None):
    """Index of the grabbable point nearest the ray (in front of its origin), or -1 when none is
    within ``radius`` [m] of it (None: no limit)."""
    o = np.asarray(origin, np.float64).reshape(3)
    d = _unit(direction, "ray direction")
    p = np.asarray(points, np.float64).reshape(-1, 3)
    if len(p) == 0:
        return -1
    rel = p - o
    t = rel @ d
    dist = np.linalg.norm(rel - np.outer(t, d), axis=1)
    dist[t < 0] = np.inf
    if grabbable is not None:
        dist[~np.asarray(grabbable, bool)] = np.inf
    k = int(np.argmin(dist))
    if not np.isfinite(dist[k]) or (radius is not None and dist[k] > radius):
        return -1
    return k


def pointer_ray(camera_position, pointer_point):
    """(origin, unit direction) of the pointer's ray: from the camera through a world point that
    lies under the pointer (e.g. the pointer projected onto any plane)."""
    o = np.asarray(camera_position, np.float64).reshape(3)
    return o, _unit(np.asarray(pointer_point, np.float64) - o, "pointer ray")


def camera_plane_target(ray_origin, ray_direction, grabbed_point, view_direction):
    """Where the pointer's ray meets the plane through ``grabbed_point`` whose normal is the
    camera's ``view_direction``; the grabbed point itself when the ray runs parallel to it."""
    o = np.asarray(ray_origin, np.float64).reshape(3)
    d = _unit(ray_direction, "ray direction")
    n = _unit(view_direction, "view direction")
    g = np.asarray(grabbed_point, np.float64).reshape(3)
    denom = d @ n
    if abs(denom) < 1e-9:
        return g.copy()
    return o + ((g - o) @ n / denom) * d


def segment_ribbon_triangles(count) -> np.ndarray:
    """Triangles (4 count, 3) uint32 of :func:`segment_ribbons` for ``count`` segments."""
    base = 8 * np.arange(int(count), dtype=np.uint32)[:, None]
    quads = np.array([[0, 1, 3], [0, 3, 2], [4, 5, 7], [4, 7, 6]], np.uint32)
    return (base[:, None, :] + quads[None, :, :]).reshape(-1, 3)


def segment_ribbons(segments, half_width) -> np.ndarray:
    """Vertices (8 S, 3) float32 of two crossed quads of half width ``half_width`` [m] around each
    segment of ``segments`` (S, 2, 3) (both planes contain the segment, at right angles, so the
    ribbon shows an edge to no camera); triangles from :func:`segment_ribbon_triangles`."""
    seg = np.asarray(segments, np.float32).reshape(-1, 2, 3)
    d = seg[:, 1] - seg[:, 0]
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    helper = np.where(np.abs(d[:, 1:2]) < 0.9, np.array([[0.0, 1.0, 0.0]], np.float32),
                      np.array([[1.0, 0.0, 0.0]], np.float32))
    n1 = np.cross(d, helper)
    n1 /= np.maximum(np.linalg.norm(n1, axis=1, keepdims=True), 1e-12)
    n2 = np.cross(d, n1)
    w = np.float32(half_width)
    out = np.empty((len(seg), 8, 3), np.float32)
    for k, n in enumerate((n1, n2)):
        out[:, 4 * k + 0] = seg[:, 0] - w * n
        out[:, 4 * k + 1] = seg[:, 0] + w * n
        out[:, 4 * k + 2] = seg[:, 1] - w * n
        out[:, 4 * k + 3] = seg[:, 1] + w * n
    return out.reshape(-1, 3)
