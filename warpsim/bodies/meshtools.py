"""Triangle-mesh helpers on the host (NumPy): welding, edge topology, boundary loops, caps,
Euler characteristic, enclosed volume and the generalised winding number.

Meshes are ``points`` (V, 3) float and ``faces`` (F, 3) int vertex indices, counter-clockwise
seen from outside for closed meshes (outward normals, positive volume).
"""

from __future__ import annotations

import numpy as np


def weld(points, faces, tolerance: float = 1.0e-6):
    """Merge vertices closer than about ``tolerance`` [m] (quantised to a grid of that size),
    drop faces that become degenerate and vertices no face uses.

    Returns (points (V', 3), faces (F', 3), kept (F,) bool mask of the input faces kept)."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    key = np.round(points / tolerance).astype(np.int64)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    f = inverse.reshape(-1)[faces]
    kept = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
    p, f = compact(points[first], f[kept])
    return p, f, kept


def compact(points, faces):
    """Remove vertices no face references; returns (points, faces) renumbered in order."""
    used = np.zeros(len(points), dtype=bool)
    used[faces.reshape(-1)] = True
    remap = np.cumsum(used) - 1
    return points[used], remap[faces]


def directed_edges(faces) -> np.ndarray:
    """The 3F directed edges (a, b) of the faces, face f's edges at rows f, F + f, 2F + f."""
    faces = np.asarray(faces)
    return np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])


def edge_topology(faces):
    """Undirected edges and their faces.

    Returns (edges (E, 2) with edges[:, 0] < edges[:, 1], counts (E,) faces per edge,
    edge_of (3F,) edge index of each directed edge in ``directed_edges`` order)."""
    d = directed_edges(faces)
    key = np.sort(d, axis=1)
    edges, edge_of, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    return edges, counts, edge_of.reshape(-1)


def check_manifold(faces, owner: str = "mesh", consistent: bool = False):
    """ValueError naming the first edge shared by more than two faces and, with ``consistent``,
    a pair of faces traversing a shared edge in the same direction (inconsistent winding).
    Returns edge_topology(faces)."""
    edges, counts, edge_of = edge_topology(faces)
    bad = np.flatnonzero(counts > 2)
    if len(bad):
        e = edges[bad[0]]
        n_faces = len(faces)
        users = sorted({int(k % n_faces) for k in np.flatnonzero(edge_of == bad[0])})
        raise ValueError(f"{owner} is non-manifold: edge ({e[0]}, {e[1]}) is shared by {counts[bad[0]]} faces "
                         f"{users}; every edge may belong to at most two faces (split or remove the extra faces)")
    if not consistent:
        return edges, counts, edge_of
    d = directed_edges(faces)
    _, dcount = np.unique(d, axis=0, return_counts=True)
    if np.any(dcount > 1):
        dup = np.unique(d, axis=0)[np.flatnonzero(dcount > 1)[0]]
        raise ValueError(f"{owner} has inconsistent winding: two faces traverse edge ({dup[0]}, {dup[1]}) in the "
                         "same direction; orient all faces the same way (e.g. trimesh.repair.fix_winding)")
    return edges, counts, edge_of


def boundary_loops(faces) -> list:
    """Closed loops of boundary edges (edges with one face), each an array of vertex indices in
    the direction the faces traverse them."""
    _, counts, edge_of = edge_topology(faces)
    d = directed_edges(faces)
    boundary = d[counts[edge_of] == 1]
    nxt = {int(a): int(b) for a, b in boundary}
    loops, seen = [], set()
    for start in nxt:
        if start in seen:
            continue
        loop, v = [], start
        while v not in seen:
            seen.add(v)
            loop.append(v)
            v = nxt[v]
        loops.append(np.array(loop, dtype=np.int64))
    return loops


def cap_loops(points, faces, loops):
    """Close each boundary loop with a fan of triangles around a new vertex at the loop's
    centroid, wound to match the neighbouring faces. Returns (points, faces)."""
    points = np.asarray(points, dtype=np.float64)
    new_points, new_faces = [points], [np.asarray(faces)]
    n = len(points)
    for loop in loops:
        center = n
        n += 1
        new_points.append(points[loop].mean(axis=0, keepdims=True))
        a, b = loop, np.roll(loop, -1)
        # the loop runs a -> b in its faces, so the cap traverses b -> a
        new_faces.append(np.stack([b, a, np.full_like(a, center)], axis=1))
    return np.concatenate(new_points), np.concatenate(new_faces)


def euler_characteristic(faces) -> int:
    """V - E + F over the vertices the faces use."""
    faces = np.asarray(faces)
    edges, _, _ = edge_topology(faces)
    return int(len(np.unique(faces)) - len(edges) + len(faces))


def is_closed(faces) -> bool:
    """Every edge belongs to exactly two faces, traversed in opposite directions."""
    _, counts, _ = edge_topology(faces)
    d = directed_edges(faces)
    return bool(np.all(counts == 2) and len(np.unique(d, axis=0)) == len(d))


def connected_components(faces, vertex_count=None) -> np.ndarray:
    """Component label per vertex (vertices joined by face edges), shape (V,)."""
    faces = np.asarray(faces)
    n = int(vertex_count if vertex_count is not None else faces.max() + 1)
    parent = np.arange(n)

    def find(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for a, b in directed_edges(faces):
        ra, rb = find(a), find(b)
        if ra != rb:
            parent[max(ra, rb)] = min(ra, rb)
    roots = np.array([find(i) for i in range(n)])
    _, labels = np.unique(roots, return_inverse=True)
    return labels


def signed_volume(points, faces) -> float:
    """Enclosed volume (divergence theorem), positive for outward-wound closed meshes."""
    p = np.asarray(points, dtype=np.float64)[np.asarray(faces)]
    return float(np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2])).sum() / 6.0)


def surface_area(points, faces) -> float:
    p = np.asarray(points, dtype=np.float64)[np.asarray(faces)]
    return float(0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1).sum())


def vertex_areas(points, faces) -> np.ndarray:
    """A third of the area of every face touching each vertex, shape (V,) [m^2]."""
    p = np.asarray(points, dtype=np.float64)
    f = np.asarray(faces)
    tri = p[f]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    out = np.zeros(len(p))
    for k in range(3):
        np.add.at(out, f[:, k], area / 3.0)
    return out


def winding_number(points, faces, queries, chunk: int = 256) -> np.ndarray:
    """Generalised winding number of a triangle mesh at each query point (Jacobson et al. 2013):
    the sum of signed solid angles / 4 pi; ~1 inside a closed outward mesh, ~0 outside.
    queries (Q, 3) -> (Q,)."""
    p = np.asarray(points, dtype=np.float64)
    tri = p[np.asarray(faces)]
    q = np.asarray(queries, dtype=np.float64).reshape(-1, 3)
    out = np.empty(len(q))
    for s in range(0, len(q), chunk):
        qq = q[s:s + chunk, None, None, :]
        a, b, c = (tri[None, :, k, :] - qq[:, :, 0, :] for k in range(3))
        la, lb, lc = (np.linalg.norm(x, axis=-1) for x in (a, b, c))
        det = np.einsum("qfi,qfi->qf", a, np.cross(b, c))
        den = (la * lb * lc + np.einsum("qfi,qfi->qf", a, b) * lc + np.einsum("qfi,qfi->qf", b, c) * la
               + np.einsum("qfi,qfi->qf", c, a) * lb)
        out[s:s + chunk] = 2.0 * np.arctan2(det, den).sum(axis=1) / (4.0 * np.pi)
    return out
