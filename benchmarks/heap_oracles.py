"""The heap's crossing check on a Warp device: how many surface edges of each body pass through another body's
triangles, the count of ``tests/test_soft_contact_scale.py``'s NumPy oracle ``edges_through_other_bodies`` (summed
over the body pairs), in seconds where the NumPy one takes minutes (a heap of 100 tori of 2,000 vertices: 182 s a
check on the H200's host).

Each surface edge queries a BVH of all triangles (float32 boxes grown by ``PAD`` so that rounding drops no
candidate) and tests, in float64 as the oracle does (Moeller-Trumbore, the same strict inequalities), every
candidate triangle of another body; an edge counts once for each other body it passes through (the oracle counts
it in each pair (a, b)). No float atomics: each edge writes its own count.

    from heap_oracles import edges_through_other_bodies_count
    crossings = edges_through_other_bodies_count(x, bodies, device)
"""

import numpy as np
import warp as wp

from warpsim.bodies import meshtools

PAD = 1.0e-5
"""[m] the boxes' margin in the BVH (float32 rounding of positions near 1 m is about 6e-8 m)."""

MOST_BODIES = 8
"""Other bodies one edge is counted against at most (more would need a heap of tori threaded on one edge)."""


@wp.func
def segment_crosses(p0: wp.vec3d, p1: wp.vec3d, a: wp.vec3d, b: wp.vec3d, c: wp.vec3d) -> bool:
    """Whether segment p0-p1 passes through triangle abc (Moeller-Trumbore, strict inside, the NumPy oracle's
    conditions)."""
    d = p1 - p0
    e1 = b - a
    e2 = c - a
    h = wp.cross(d, e2)
    det = wp.dot(h, e1)
    if wp.abs(det) <= wp.float64(1.0e-14):
        return False
    f = wp.float64(1.0) / det
    s = p0 - a
    u = f * wp.dot(s, h)
    q = wp.cross(s, e1)
    v = f * wp.dot(d, q)
    t = f * wp.dot(q, e2)
    zero = wp.float64(0.0)
    one = wp.float64(1.0)
    return u > zero and v > zero and u + v < one and t > zero and t < one


@wp.kernel
def count_crossings(bvh: wp.uint64, x: wp.array(dtype=wp.vec3d), edges: wp.array(dtype=int),
                    edge_body: wp.array(dtype=int), faces: wp.array(dtype=int), face_body: wp.array(dtype=int),
                    pad: float, count_out: wp.array(dtype=int)):
    """Other bodies edge e passes through (each counted once, at most ``MOST_BODIES``) into ``count_out[e]``."""
    e = wp.tid()
    p0 = x[edges[2 * e]]
    p1 = x[edges[2 * e + 1]]
    lo = wp.vec3(float(wp.min(p0[0], p1[0])), float(wp.min(p0[1], p1[1])), float(wp.min(p0[2], p1[2])))
    hi = wp.vec3(float(wp.max(p0[0], p1[0])), float(wp.max(p0[1], p1[1])), float(wp.max(p0[2], p1[2])))
    query = wp.bvh_query_aabb(bvh, lo - wp.vec3(pad), hi + wp.vec3(pad))
    own = edge_body[e]
    seen = wp.vector(length=MOST_BODIES, dtype=int)
    n = int(0)
    t = int(0)
    while wp.bvh_query_next(query, t):
        body = face_body[t]
        if body == own:
            continue
        known = int(0)
        for k in range(MOST_BODIES):
            if k < n and seen[k] == body:
                known = 1
        if known == 1 or n >= MOST_BODIES:
            continue
        if segment_crosses(p0, p1, x[faces[3 * t]], x[faces[3 * t + 1]], x[faces[3 * t + 2]]):
            seen[n] = body
            n += 1
    count_out[e] = n


def edges_through_other_bodies_count(x, bodies, device) -> int:
    """Surface edges of each body passing through other bodies' triangles, summed over the bodies (the total of
    the NumPy oracle ``edges_through_other_bodies``): ``x`` (N, 3) positions [m], ``bodies`` SoftBody records."""
    faces = np.concatenate([b.faces for b in bodies]).astype(np.int64)
    face_body = np.concatenate([np.full(len(b.faces), k) for k, b in enumerate(bodies)])
    edge_sets = [meshtools.edge_topology(b.faces)[0] for b in bodies]
    edges = np.concatenate(edge_sets).astype(np.int64)
    edge_body = np.concatenate([np.full(len(e), k) for k, e in enumerate(edge_sets)])
    corners = x[faces].astype(np.float64)
    lowers = (corners.min(1) - PAD).astype(np.float32)
    uppers = (corners.max(1) + PAD).astype(np.float32)
    bvh = wp.Bvh(wp.array(lowers, dtype=wp.vec3, device=device), wp.array(uppers, dtype=wp.vec3, device=device))
    counts = wp.zeros(len(edges), dtype=int, device=device)
    wp.launch(count_crossings, len(edges), inputs=[
        bvh.id, wp.array(x.astype(np.float64), dtype=wp.vec3d, device=device),
        wp.array(edges.reshape(-1).astype(np.int32), dtype=int, device=device),
        wp.array(edge_body.astype(np.int32), dtype=int, device=device),
        wp.array(faces.reshape(-1).astype(np.int32), dtype=int, device=device),
        wp.array(face_body.astype(np.int32), dtype=int, device=device), PAD, counts], device=device)
    return int(counts.numpy().sum())
