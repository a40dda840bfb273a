"""Soft-body contact kernels: vertices against triangles and edges against edges of other bodies
(or of the same body with self contact). ``warpsim.bodies.soft_contact.SoftContact`` launches
them after integration.

Broad phase, two levels (bodies, then the other bodies' primitives):

* ``body_bounds``: each body's bounds over the step (its contact vertices at the start and end),
  from chunks of its vertices with float atomic min/max; a small BVH over them, grouped by world.
* ``find_vertex_contacts``: every contact vertex queries the body BVH from its world's root with
  a box of half width ``max(thickness, search)``; for each *other* body it meets, it queries that
  body's subtree of one grouped ``wp.Bvh`` over all contact triangles (group = body, subtree root
  from ``group_roots``). A vertex never visits its own body's triangles unless self contact is on
  (then triangles touching the vertex, or within ``self_rest_distance`` of it in the rest pose,
  are skipped). Measured before the split (one BVH over all bodies), 67-77 % of the candidates a
  query visited were its own body's (``SoftContact.candidate_stats``).
* ``find_edge_contacts``: the same for every surface edge, with its bounds over the step padded
  by the thickness, against the grouped edge BVH (``edge_bounds``).
* Both, and the candidate list's searches (``warpsim.kernels.soft_contact_list``), walk the two
  levels alike: ``first_body`` takes the query's bounds, world and body, ``next_body`` returns the
  next body whose bounds meet them (taken from the body BVH in batches of ``BODY_BATCH``), and the
  query's loop visits that body's subtree of the primitive BVH, in the same order every time.
* ``find_*_all_pairs``: the same narrow phase over every triangle / edge of the world, no
  broad phase (the reference the tests compare with; O(vertices x triangles)).

Narrow phase. Vertex p against triangle abc: with c the closest point (barycentrics b) and n_f
the outward face normal, s = |p - c| in front of the face, -|p - c| right behind it (only when
c lies inside the triangle); a contact has -search < s < thickness, normal n = (p - c)/|p - c|
in front, n_f behind. Edge pq against edge rs (closest points c1 = p + u (q - p), c2 = r + t (s - r),
Ericson 5.1.9), only with both closest points inside their edges (0 < u, t < 1) and edges at
least ``EDGE_MIN_SINE`` (0.01) from parallel (otherwise a vertex is nearest and the vertex-triangle test
covers it): a contact when |c1 - c2| < thickness, normal (c1 - c2)/|c1 - c2|, or when the same
points at the start of the step (``q_prev``) lay on the other side ((c1 - c2) . (c1' - c2') < 0:
the edges passed through each other during the step) and |c1 - c2| < search, normal
(c1' - c2')/|c1' - c2'| (back to the side they came from). The edge BVH holds each edge's bounds
over the step (start and end).
Every vertex (edge) keeps its nearest contact,
ties broken by the lower triangle (edge) index, so the result does not depend on the order in
which the BVH returns candidates.

A contact joins four particles k with weights a_k (vertex-triangle: 1, -b_0, -b_1, -b_2; edge-edge:
1 - u, u, -(1 - t), -t): the relative velocity is sum a_k v_k, the effective inverse mass
W = sum a_k^2 w_k. Each of ``iterations`` passes (Jacobi: deltas from the same state, then
applied) lets ``resolve_one`` remove ``fraction`` of the depth thickness - (sum a_k x_k) . n
at the current positions (at detection, thickness - s) and apply J = -(1 + e) u_n / W when
u_n < 0 and Coulomb friction up to mu J; particle k receives
a_k w_k (impulse): sum m dv = J sum a_k = 0, momentum is conserved (pinned particles, w = 0, never
move). Each contact is scaled by 1 / (largest contact count among its particles): a particle in
several contacts receives a convex combination (Jacobi averaging).

Reproducibility: the deltas are summed in 64-bit fixed point (``FIXED_SCALE`` units per metre or
metre per second, resolution 2.3e-10) with integer atomics, and integer addition does not depend
on order: two runs are bit-identical on any device, and no float atomics are used.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})

FIXED_SCALE = wp.constant(4294967296.0)  # 2^32 fixed-point units per metre (m/s) for the deltas
FIXED_INV_SCALE = wp.constant(1.0 / 4294967296.0)
# edges closer to parallel (about 0.6 degrees) are left to vertex contacts. It was 0.2 (11.5
# degrees): stacked tori lie with many edges nearly parallel, and at 1/240 s 6-35 of them passed
# through the other torus's triangles unseen (4 tori of 14 x 7 vertices, benchmarks/check_heap.py)
EDGE_MIN_SINE = wp.constant(0.01)


@wp.func
def triangle_barycentric(p: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3) -> wp.vec3:
    """Barycentric weights (wa, wb, wc) of the point of triangle abc closest to p (Ericson,
    Real-Time Collision Detection, 5.1.5)."""
    ab = b - a
    ac = c - a
    ap = p - a
    d1 = wp.dot(ab, ap)
    d2 = wp.dot(ac, ap)
    if d1 <= 0.0 and d2 <= 0.0:
        return wp.vec3(1.0, 0.0, 0.0)
    bp = p - b
    d3 = wp.dot(ab, bp)
    d4 = wp.dot(ac, bp)
    if d3 >= 0.0 and d4 <= d3:
        return wp.vec3(0.0, 1.0, 0.0)
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        v = d1 / (d1 - d3)
        return wp.vec3(1.0 - v, v, 0.0)
    cp = p - c
    d5 = wp.dot(ab, cp)
    d6 = wp.dot(ac, cp)
    if d6 >= 0.0 and d5 <= d6:
        return wp.vec3(0.0, 0.0, 1.0)
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        w = d2 / (d2 - d6)
        return wp.vec3(1.0 - w, 0.0, w)
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        return wp.vec3(0.0, 1.0 - w, w)
    denom = 1.0 / (va + vb + vc)
    v = vb * denom
    w = vc * denom
    return wp.vec3(1.0 - v - w, v, w)


@wp.func
def segment_closest_params(p1: wp.vec3, q1: wp.vec3, p2: wp.vec3, q2: wp.vec3) -> wp.vec2:
    """Parameters (u, t) in [0, 1] of the closest points p1 + u (q1 - p1) and p2 + t (q2 - p2)
    of two segments (Ericson, Real-Time Collision Detection, 5.1.9)."""
    d1 = q1 - p1
    d2 = q2 - p2
    r = p1 - p2
    a = wp.dot(d1, d1)
    e = wp.dot(d2, d2)
    f = wp.dot(d2, r)
    eps = float(1.0e-20)
    u = float(0.0)
    t = float(0.0)
    if a <= eps and e <= eps:
        return wp.vec2(0.0, 0.0)
    if a <= eps:
        return wp.vec2(0.0, wp.clamp(f / e, 0.0, 1.0))
    c = wp.dot(d1, r)
    if e <= eps:
        return wp.vec2(wp.clamp(-c / a, 0.0, 1.0), 0.0)
    b = wp.dot(d1, d2)
    denom = a * e - b * b
    if denom > eps * a * e:
        u = wp.clamp((b * f - c * e) / denom, 0.0, 1.0)
    t = (b * u + f) / e
    if t < 0.0:
        t = 0.0
        u = wp.clamp(-c / a, 0.0, 1.0)
    elif t > 1.0:
        t = 1.0
        u = wp.clamp((b - c) / a, 0.0, 1.0)
    return wp.vec2(u, t)


@wp.func
def rest_distance(p: int, t: int, tri: wp.array(dtype=int), rest: wp.array(dtype=wp.vec3)) -> float:
    """Distance from particle p to triangle t in the rest pose [m]."""
    a = rest[tri[3 * t]]
    b = rest[tri[3 * t + 1]]
    c = rest[tri[3 * t + 2]]
    x = rest[p]
    w = triangle_barycentric(x, a, b, c)
    return wp.length(x - (w[0] * a + w[1] * b + w[2] * c))


# ------------------------------------------------------------------------------ narrow phase
@wp.func
def vertex_triangle_candidate(
    p: int, body: int, t: int, tri: wp.array(dtype=int), tri_body: wp.array(dtype=int),
    rest: wp.array(dtype=wp.vec3), inv_mass: wp.array(dtype=float), self_contact: int, self_rest_distance: float,
) -> bool:
    """Whether vertex p (of ``body``) may touch triangle t at all (topology filters only)."""
    own = tri_body[t] == body
    if own and self_contact == 0:
        return False
    i = tri[3 * t]
    j = tri[3 * t + 1]
    k = tri[3 * t + 2]
    if own:
        if i == p or j == p or k == p:
            return False
        if rest_distance(p, t, tri, rest) < self_rest_distance:
            return False
    return inv_mass[p] + inv_mass[i] + inv_mass[j] + inv_mass[k] > 0.0


@wp.func
def vertex_triangle_test(x: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3, thickness: float, search: float):
    """(distance [m], barycentrics, normal) of vertex x against triangle abc; distance -1 when
    they are no contact (module docstring)."""
    bary = triangle_barycentric(x, a, b, c)
    delta = x - (bary[0] * a + bary[1] * b + bary[2] * c)
    d = wp.length(delta)
    nf = wp.cross(b - a, c - a)
    area2 = wp.length(nf)
    if area2 < 1.0e-20:
        return -1.0, bary, nf
    nf = nf / area2
    s = d
    n = nf
    if wp.dot(delta, nf) < 0.0:
        # behind the face: a contact only when x lies right behind it (closest point inside)
        if bary[0] <= 0.0 or bary[1] <= 0.0 or bary[2] <= 0.0:
            return -1.0, bary, n
        s = -d
    elif d > 1.0e-9:
        n = delta / d
    if s >= thickness or s <= -search:
        return -1.0, bary, n
    return d, bary, n


@wp.func
def edge_edge_candidate(
    e: int, f: int, edges: wp.array(dtype=int), edge_body: wp.array(dtype=int), rest: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float), self_contact: int, self_rest_distance: float,
) -> bool:
    """Whether edge e may touch edge f at all (topology filters only)."""
    if e == f:
        return False
    own = edge_body[e] == edge_body[f]
    if own and self_contact == 0:
        return False
    a = edges[2 * e]
    b = edges[2 * e + 1]
    c = edges[2 * f]
    d = edges[2 * f + 1]
    if own:
        if a == c or a == d or b == c or b == d:
            return False
        ut = segment_closest_params(rest[a], rest[b], rest[c], rest[d])
        gap = (rest[a] + ut[0] * (rest[b] - rest[a])) - (rest[c] + ut[1] * (rest[d] - rest[c]))
        if wp.length(gap) < self_rest_distance:
            return False
    return inv_mass[a] + inv_mass[b] + inv_mass[c] + inv_mass[d] > 0.0


@wp.func
def edge_edge_test(
    f: int, xa: wp.vec3, xb: wp.vec3, pa: wp.vec3, pb: wp.vec3, edges: wp.array(dtype=int),
    q: wp.array(dtype=wp.vec3), q_prev: wp.array(dtype=wp.vec3), thickness: float, search: float,
):
    """(distance [m], (u, t), normal) of edge xa-xb (at the step's start pa-pb) against edge f;
    distance -1 when they are no contact (module docstring)."""
    c = edges[2 * f]
    dd = edges[2 * f + 1]
    xc = q[c]
    xd = q[dd]
    ut = segment_closest_params(xa, xb, xc, xd)
    # closest points inside both edges, edges not near parallel: otherwise a vertex is nearest
    # and the vertex-triangle contact handles it
    if ut[0] <= 0.0 or ut[0] >= 1.0 or ut[1] <= 0.0 or ut[1] >= 1.0:
        return -1.0, ut, wp.vec3()
    if wp.length(wp.cross(xb - xa, xd - xc)) < EDGE_MIN_SINE * wp.length(xb - xa) * wp.length(xd - xc):
        return -1.0, ut, wp.vec3()
    delta = (xa + ut[0] * (xb - xa)) - (xc + ut[1] * (xd - xc))
    d = wp.length(delta)
    # the same points at the start of the step: which side e was on
    before = (pa + ut[0] * (pb - pa)) - (q_prev[c] + ut[1] * (q_prev[dd] - q_prev[c]))
    if wp.dot(delta, before) < 0.0:
        # e passed through f during the step: push it back to the side it came from
        if d >= search or wp.length(before) < 1.0e-12:
            return -1.0, ut, wp.vec3()
        return d, ut, wp.normalize(before)
    if d <= 1.0e-9 or d >= thickness:
        return -1.0, ut, wp.vec3()
    return d, ut, delta / d


BODY_BATCH = 16  # other bodies taken from the body BVH per pass (queries never nest: see collect_bodies)
vec_bodies = wp.types.vector(length=BODY_BATCH, dtype=wp.int32)


@wp.func
def collect_bodies(body_bvh: wp.uint64, root: int, lower: wp.vec3, upper: wp.vec3, body: int, self_contact: int,
                   skip: int):
    """Up to BODY_BATCH bodies whose bounds meet [lower, upper] (the query's own body only with self
    contact), after skipping the first ``skip`` of them; returns (bodies, how many). On CUDA a BVH
    query keeps its stack in shared memory, one per thread, so two queries may not be open at once
    in a thread: the body query is run to its end (again for each batch) before any triangle query."""
    found = vec_bodies()
    count = int(0)
    seen = int(0)
    query = wp.bvh_query_aabb(body_bvh, lower, upper, root)
    other = int(0)
    while wp.bvh_query_next(query, other):
        if other == body and self_contact == 0:
            continue
        if seen >= skip and count < BODY_BATCH:
            found[count] = other
            count += 1
        seen += 1
    return found, count


@wp.struct
class OtherBodies:
    """A two-level query's cursor over the bodies (``first_body``, ``next_body``): the query's box,
    world and body, the batch of bodies taken from the body BVH, and the current body."""

    body_bvh: wp.uint64
    root: int  # the query's world's root in the body BVH
    lower: wp.vec3
    upper: wp.vec3
    body: int  # the query's own body (met only with self contact)
    self_contact: int
    batch: vec_bodies  # bodies of the current batch (collect_bodies)
    count: int  # how many
    next: int  # the batch's next body
    more: int  # 1 while the last batch was full (more bodies may follow)
    bodies: int  # bodies taken so far
    other: int  # the current body, -1 after the last


@wp.func
def next_body(c: OtherBodies) -> OtherBodies:
    """The cursor at the next body whose bounds meet the query's box (``c.other``, -1 after the last):
    the batch's next one, else the first of the next batch (``collect_bodies``), in the same order
    on every call."""
    while c.next >= c.count and c.more == 1:
        batch, count = collect_bodies(c.body_bvh, c.root, c.lower, c.upper, c.body, c.self_contact, c.bodies)
        c.batch = batch
        c.count = count
        c.bodies += count
        c.more = wp.where(count == BODY_BATCH, 1, 0)
        c.next = 0
    c.other = -1
    if c.next < c.count:
        c.other = c.batch[c.next]
        c.next += 1
    return c


@wp.func
def first_body(body_bvh: wp.uint64, root: int, lower: wp.vec3, upper: wp.vec3, body: int,
               self_contact: int) -> OtherBodies:
    """The two-level search of a query with bounds [lower, upper] (of ``body``, in the world whose
    body BVH root is ``root``): a cursor at the first body whose bounds meet it (the query's own body
    only with self contact). Every search in this module and ``soft_contact_list`` walks it as::

        others = first_body(body_bvh, root, lower, upper, body, self_contact)
        while others.other >= 0:
            query = wp.bvh_query_aabb(prim_bvh, lower, upper, prim_root[others.other])
            while wp.bvh_query_next(query, t):
                ...  # candidate t of body others.other
            others = next_body(others)

    ``others.bodies`` then counts the bodies taken. The candidates come straight from
    ``wp.bvh_query_next``: a cursor over them, returned through a function at every candidate,
    cost the donuts' search 20-50 % more CPU time; the bodies, a few per query, go through it."""
    # batch, count, next, more, bodies, other
    c = OtherBodies(body_bvh, root, lower, upper, body, self_contact, vec_bodies(), 0, 0, 1, 0, -1)
    return next_body(c)


@wp.func
def nearer(d: float, index: int, best_d: float, best: int) -> bool:
    """Nearest first, ties to the lower index (order independent)."""
    return d < best_d or (d == best_d and index < best)


@wp.func
def contact_depth(particles: wp.vec4i, weights: wp.vec4, n: wp.vec3, q: wp.array(dtype=wp.vec3),
                  thickness: float) -> float:
    """Depth [m] of a contact at positions q: thickness - (sum a_k x_k) . n (> 0: closer than the thickness)."""
    gap = wp.vec3()
    for k in range(4):
        gap += weights[k] * q[particles[k]]
    return thickness - wp.dot(gap, n)


@wp.func
def counts_toward_scale(particles: wp.vec4i, weights: wp.vec4, normal: wp.vec3, q: wp.array(dtype=wp.vec3),
                        count_within: float) -> bool:
    """Whether a contact counts in its particles' contact counts (the Jacobi scale of
    ``contact_scale``): its gap (sum a_k x_k) . n is under ``count_within`` (the thickness).
    Speculative contacts further apart (``reach``) do not: they act only when approaching fast,
    and counting them divided a dense patch's corrections by up to 37 (11 on average)."""
    return contact_depth(particles, weights, normal, q, count_within) > 0.0


@wp.func
def store_contact(
    slot: int, particles: wp.vec4i, weights: wp.vec4, normal: wp.vec3, q: wp.array(dtype=wp.vec3),
    count_within: float,
    contact_particles_out: wp.array(dtype=wp.vec4i), contact_weights_out: wp.array(dtype=wp.vec4),
    contact_normal_out: wp.array(dtype=wp.vec3), particle_contacts_io: wp.array(dtype=int), contact_total_io: wp.array(dtype=int), kind: int,
):
    contact_particles_out[slot] = particles
    contact_weights_out[slot] = weights
    contact_normal_out[slot] = normal
    if counts_toward_scale(particles, weights, normal, q, count_within):
        for k in range(4):
            wp.atomic_add(particle_contacts_io, particles[k], 1)
    wp.atomic_add(contact_total_io, kind, 1)


@wp.func
def clear_contact(slot: int, contact_particles_out: wp.array(dtype=wp.vec4i)):
    contact_particles_out[slot] = wp.vec4i(-1, -1, -1, -1)


# ------------------------------------------------------------------------------ vertex-triangle
@wp.func
def nearer_triangle(
    p: int, body: int, x: wp.vec3, t: int, tri: wp.array(dtype=int), tri_body: wp.array(dtype=int),
    q: wp.array(dtype=wp.vec3), rest: wp.array(dtype=wp.vec3), inv_mass: wp.array(dtype=float), thickness: float,
    search: float, self_contact: int, self_rest_distance: float, best_d: float, best: int, best_bary: wp.vec3,
    best_normal: wp.vec3,
):
    """(distance, triangle, barycentrics, normal) of vertex p's nearest contact so far after trying
    triangle t (the best so far when t is no candidate, no contact or not nearer)."""
    if vertex_triangle_candidate(p, body, t, tri, tri_body, rest, inv_mass, self_contact, self_rest_distance):
        d, bary, n = vertex_triangle_test(x, q[tri[3 * t]], q[tri[3 * t + 1]], q[tri[3 * t + 2]], thickness, search)
        if d >= 0.0 and nearer(d, t, best_d, best):
            return d, t, bary, n
    return best_d, best, best_bary, best_normal


@wp.func
def nearer_edge(
    e: int, f: int, xa: wp.vec3, xb: wp.vec3, pa: wp.vec3, pb: wp.vec3, edges: wp.array(dtype=int),
    edge_body: wp.array(dtype=int), q: wp.array(dtype=wp.vec3), q_prev: wp.array(dtype=wp.vec3),
    rest: wp.array(dtype=wp.vec3), inv_mass: wp.array(dtype=float), thickness: float, search: float,
    self_contact: int, self_rest_distance: float, best_d: float, best: int, best_ut: wp.vec2, best_normal: wp.vec3,
):
    """(distance, edge, (u, t), normal) of edge e's nearest contact so far after trying edge f (as
    ``nearer_triangle``)."""
    if edge_edge_candidate(e, f, edges, edge_body, rest, inv_mass, self_contact, self_rest_distance):
        d, ut, n = edge_edge_test(f, xa, xb, pa, pb, edges, q, q_prev, thickness, search)
        if d >= 0.0 and nearer(d, f, best_d, best):
            return d, f, ut, n
    return best_d, best, best_ut, best_normal


@wp.func
def finish_vertex_contact(
    v: int, p: int, best: int, best_bary: wp.vec3, best_normal: wp.vec3, q: wp.array(dtype=wp.vec3),
    count_within: float, tri: wp.array(dtype=int), contact_particles_out: wp.array(dtype=wp.vec4i),
    contact_weights_out: wp.array(dtype=wp.vec4), contact_normal_out: wp.array(dtype=wp.vec3),
    particle_contacts_io: wp.array(dtype=int),
    contact_total_io: wp.array(dtype=int),
):
    if best < 0:
        clear_contact(v, contact_particles_out)
        return
    store_contact(v, wp.vec4i(p, tri[3 * best], tri[3 * best + 1], tri[3 * best + 2]),
                  wp.vec4(1.0, -best_bary[0], -best_bary[1], -best_bary[2]), best_normal, q, count_within,
                  contact_particles_out, contact_weights_out, contact_normal_out,
                  particle_contacts_io, contact_total_io, 0)


@wp.kernel
def find_vertex_contacts(
    body_bvh: wp.uint64,
    world_root: wp.array(dtype=int),
    tri_bvh: wp.uint64,
    body_tri_root: wp.array(dtype=int),
    vertex_world: wp.array(dtype=int),
    vertex_particle: wp.array(dtype=int),
    vertex_body: wp.array(dtype=int),
    tri: wp.array(dtype=int),
    tri_body: wp.array(dtype=int),
    q: wp.array(dtype=wp.vec3),
    rest: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    thickness: float,
    search: float,
    count_within: float,
    self_contact: int,
    self_rest_distance: float,
    contact_particles_out: wp.array(dtype=wp.vec4i),
    contact_weights_out: wp.array(dtype=wp.vec4),
    contact_normal_out: wp.array(dtype=wp.vec3),
    particle_contacts_io: wp.array(dtype=int),
    contact_total_io: wp.array(dtype=int),
    candidates_out: wp.array(dtype=wp.vec4i),
):
    """Nearest triangle contact of contact vertex v (slot v), two levels: the body BVH (from its
    world's root) gives the other bodies whose bounds meet the vertex's box, then each such body's
    subtree of the grouped triangle BVH (``body_tri_root``) gives its triangles; the vertex's own
    body is skipped unless self contact is on. ``candidates_out`` (length 0: off) receives
    (triangles visited, of them own-body ones, bodies visited, contacts kept) for the diagnostics."""
    v = wp.tid()
    p = vertex_particle[v]
    body = vertex_body[v]
    x = q[p]
    reach = wp.max(thickness, search)
    lower = x - wp.vec3(reach)
    upper = x + wp.vec3(reach)
    best = int(-1)
    best_d = float(1.0e30)
    best_bary = wp.vec3()
    best_normal = wp.vec3()
    visited = int(0)
    own = int(0)
    others = first_body(body_bvh, world_root[vertex_world[v]], lower, upper, body, self_contact)
    while others.other >= 0:
        query = wp.bvh_query_aabb(tri_bvh, lower, upper, body_tri_root[others.other])
        t = int(0)
        while wp.bvh_query_next(query, t):
            visited += 1
            own += wp.where(others.other == body, 1, 0)
            best_d, best, best_bary, best_normal = nearer_triangle(
                p, body, x, t, tri, tri_body, q, rest, inv_mass, thickness, search, self_contact, self_rest_distance,
                best_d, best, best_bary, best_normal)
        others = next_body(others)
    finish_vertex_contact(v, p, best, best_bary, best_normal, q, count_within, tri, contact_particles_out,
                          contact_weights_out, contact_normal_out, particle_contacts_io,
                          contact_total_io)
    if candidates_out.shape[0] > 0:
        candidates_out[v] = wp.vec4i(visited, own, others.bodies, wp.where(best >= 0, 1, 0))


@wp.kernel
def find_vertex_contacts_all_pairs(
    world_tri_start: wp.array(dtype=int),
    vertex_world: wp.array(dtype=int),
    vertex_particle: wp.array(dtype=int),
    vertex_body: wp.array(dtype=int),
    tri: wp.array(dtype=int),
    tri_body: wp.array(dtype=int),
    q: wp.array(dtype=wp.vec3),
    rest: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    thickness: float,
    search: float,
    count_within: float,
    self_contact: int,
    self_rest_distance: float,
    contact_particles_out: wp.array(dtype=wp.vec4i),
    contact_weights_out: wp.array(dtype=wp.vec4),
    contact_normal_out: wp.array(dtype=wp.vec3),
    particle_contacts_io: wp.array(dtype=int),
    contact_total_io: wp.array(dtype=int),
):
    """As ``find_vertex_contacts`` over every triangle of the world (no broad phase; reference)."""
    v = wp.tid()
    p = vertex_particle[v]
    body = vertex_body[v]
    world = vertex_world[v]
    x = q[p]
    best = int(-1)
    best_d = float(1.0e30)
    best_bary = wp.vec3()
    best_normal = wp.vec3()
    for t in range(world_tri_start[world], world_tri_start[world + 1]):
        best_d, best, best_bary, best_normal = nearer_triangle(
            p, body, x, t, tri, tri_body, q, rest, inv_mass, thickness, search, self_contact, self_rest_distance,
            best_d, best, best_bary, best_normal)
    finish_vertex_contact(v, p, best, best_bary, best_normal, q, count_within, tri, contact_particles_out,
                          contact_weights_out, contact_normal_out, particle_contacts_io,
                          contact_total_io)


# ------------------------------------------------------------------------------ edge-edge
@wp.kernel
def triangle_bounds(
    tri: wp.array(dtype=int), q: wp.array(dtype=wp.vec3),
    lowers_out: wp.array(dtype=wp.vec3), uppers_out: wp.array(dtype=wp.vec3),
):
    """Bounds of triangle t at the current positions, for the triangle BVH."""
    t = wp.tid()
    a = q[tri[3 * t]]
    b = q[tri[3 * t + 1]]
    c = q[tri[3 * t + 2]]
    lowers_out[t] = wp.min(wp.min(a, b), c)
    uppers_out[t] = wp.max(wp.max(a, b), c)


@wp.kernel
def edge_bounds(
    edges: wp.array(dtype=int), q: wp.array(dtype=wp.vec3), q_prev: wp.array(dtype=wp.vec3),
    lowers_out: wp.array(dtype=wp.vec3), uppers_out: wp.array(dtype=wp.vec3),
):
    """Bounds of edge e over the step (its positions at the start and now), for the edge BVH."""
    e = wp.tid()
    a = edges[2 * e]
    b = edges[2 * e + 1]
    lowers_out[e] = wp.min(wp.min(q[a], q[b]), wp.min(q_prev[a], q_prev[b]))
    uppers_out[e] = wp.max(wp.max(q[a], q[b]), wp.max(q_prev[a], q_prev[b]))


@wp.kernel
def reset_bounds(lowers_out: wp.array(dtype=wp.vec3), uppers_out: wp.array(dtype=wp.vec3)):
    """Empty bounds (+inf lower, -inf upper) before ``body_bounds`` grows them."""
    b = wp.tid()
    lowers_out[b] = wp.vec3(1.0e30)
    uppers_out[b] = wp.vec3(-1.0e30)


@wp.kernel
def body_bounds(
    chunk_start: wp.array(dtype=int), chunk_body: wp.array(dtype=int), vertex_particle: wp.array(dtype=int),
    q: wp.array(dtype=wp.vec3), q_prev: wp.array(dtype=wp.vec3),
    lowers_io: wp.array(dtype=wp.vec3), uppers_io: wp.array(dtype=wp.vec3),
):
    """Grow body bounds by chunk k of contact vertices (one body's vertices
    ``chunk_start[k] .. chunk_start[k + 1]``) at the step's start and end: they hold the body's
    triangles now and its edges over the step. Float atomic min/max: order independent, exact."""
    k = wp.tid()
    lo = wp.vec3(1.0e30)
    hi = wp.vec3(-1.0e30)
    for v in range(chunk_start[k], chunk_start[k + 1]):
        p = vertex_particle[v]
        lo = wp.min(lo, wp.min(q[p], q_prev[p]))
        hi = wp.max(hi, wp.max(q[p], q_prev[p]))
    b = chunk_body[k]
    wp.atomic_min(lowers_io, b, lo)
    wp.atomic_max(uppers_io, b, hi)


@wp.kernel
def group_roots(bvh: wp.uint64, roots_out: wp.array(dtype=int)):
    """Root node of group g (a body, or a world) of a grouped BVH, after a rebuild."""
    g = wp.tid()
    roots_out[g] = wp.bvh_get_group_root(bvh, g)


@wp.func
def finish_edge_contact(
    slot: int, e: int, best: int, best_ut: wp.vec2, best_normal: wp.vec3, q: wp.array(dtype=wp.vec3),
    count_within: float, edges: wp.array(dtype=int), contact_particles_out: wp.array(dtype=wp.vec4i),
    contact_weights_out: wp.array(dtype=wp.vec4), contact_normal_out: wp.array(dtype=wp.vec3),
    particle_contacts_io: wp.array(dtype=int),
    contact_total_io: wp.array(dtype=int),
):
    if best < 0:
        clear_contact(slot, contact_particles_out)
        return
    u = best_ut[0]
    t = best_ut[1]
    store_contact(slot, wp.vec4i(edges[2 * e], edges[2 * e + 1], edges[2 * best], edges[2 * best + 1]),
                  wp.vec4(1.0 - u, u, t - 1.0, -t), best_normal, q, count_within,
                  contact_particles_out, contact_weights_out, contact_normal_out,
                  particle_contacts_io, contact_total_io, 1)


@wp.kernel
def find_edge_contacts(
    body_bvh: wp.uint64,
    world_root: wp.array(dtype=int),
    edge_bvh: wp.uint64,
    body_edge_root: wp.array(dtype=int),
    edge_world: wp.array(dtype=int),
    edges: wp.array(dtype=int),
    edge_body: wp.array(dtype=int),
    q: wp.array(dtype=wp.vec3),
    q_prev: wp.array(dtype=wp.vec3),
    rest: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    thickness: float,
    search: float,
    count_within: float,
    self_contact: int,
    self_rest_distance: float,
    slot_offset: int,
    contact_particles_out: wp.array(dtype=wp.vec4i),
    contact_weights_out: wp.array(dtype=wp.vec4),
    contact_normal_out: wp.array(dtype=wp.vec3),
    particle_contacts_io: wp.array(dtype=int),
    contact_total_io: wp.array(dtype=int),
    candidates_out: wp.array(dtype=wp.vec4i),
):
    """Nearest edge contact of surface edge e (slot offset + e), two levels as
    ``find_vertex_contacts`` (body BVH, then the other bodies' subtrees of the grouped edge BVH);
    ``candidates_out`` as there (slot e)."""
    e = wp.tid()
    body = edge_body[e]
    xa = q[edges[2 * e]]
    xb = q[edges[2 * e + 1]]
    pa = q_prev[edges[2 * e]]
    pb = q_prev[edges[2 * e + 1]]
    best = int(-1)
    best_d = float(1.0e30)
    best_ut = wp.vec2()
    best_normal = wp.vec3()
    lower = wp.min(wp.min(xa, xb), wp.min(pa, pb)) - wp.vec3(thickness)
    upper = wp.max(wp.max(xa, xb), wp.max(pa, pb)) + wp.vec3(thickness)
    visited = int(0)
    own = int(0)
    others = first_body(body_bvh, world_root[edge_world[e]], lower, upper, body, self_contact)
    while others.other >= 0:
        query = wp.bvh_query_aabb(edge_bvh, lower, upper, body_edge_root[others.other])
        f = int(0)
        while wp.bvh_query_next(query, f):
            visited += 1
            own += wp.where(others.other == body, 1, 0)
            best_d, best, best_ut, best_normal = nearer_edge(
                e, f, xa, xb, pa, pb, edges, edge_body, q, q_prev, rest, inv_mass, thickness, search, self_contact,
                self_rest_distance, best_d, best, best_ut, best_normal)
        others = next_body(others)
    finish_edge_contact(slot_offset + e, e, best, best_ut, best_normal, q, count_within, edges,
                        contact_particles_out, contact_weights_out, contact_normal_out,
                        particle_contacts_io, contact_total_io)
    if candidates_out.shape[0] > 0:
        candidates_out[e] = wp.vec4i(visited, own, others.bodies, wp.where(best >= 0, 1, 0))


@wp.kernel
def find_edge_contacts_all_pairs(
    world_edge_start: wp.array(dtype=int),
    edge_world: wp.array(dtype=int),
    edges: wp.array(dtype=int),
    edge_body: wp.array(dtype=int),
    q: wp.array(dtype=wp.vec3),
    q_prev: wp.array(dtype=wp.vec3),
    rest: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    thickness: float,
    search: float,
    count_within: float,
    self_contact: int,
    self_rest_distance: float,
    slot_offset: int,
    contact_particles_out: wp.array(dtype=wp.vec4i),
    contact_weights_out: wp.array(dtype=wp.vec4),
    contact_normal_out: wp.array(dtype=wp.vec3),
    particle_contacts_io: wp.array(dtype=int),
    contact_total_io: wp.array(dtype=int),
):
    """As ``find_edge_contacts`` over every edge of the world (no broad phase; reference)."""
    e = wp.tid()
    world = edge_world[e]
    xa = q[edges[2 * e]]
    xb = q[edges[2 * e + 1]]
    pa = q_prev[edges[2 * e]]
    pb = q_prev[edges[2 * e + 1]]
    best = int(-1)
    best_d = float(1.0e30)
    best_ut = wp.vec2()
    best_normal = wp.vec3()
    for f in range(world_edge_start[world], world_edge_start[world + 1]):
        best_d, best, best_ut, best_normal = nearer_edge(
            e, f, xa, xb, pa, pb, edges, edge_body, q, q_prev, rest, inv_mass, thickness, search, self_contact,
            self_rest_distance, best_d, best, best_ut, best_normal)
    finish_edge_contact(slot_offset + e, e, best, best_ut, best_normal, q, count_within, edges,
                        contact_particles_out, contact_weights_out, contact_normal_out,
                        particle_contacts_io, contact_total_io)


# ------------------------------------------------------------------------------ response
@wp.func
def contact_scale(particles: wp.vec4i, counts: wp.array(dtype=int)) -> float:
    """1 / the largest contact count among the four particles of a contact."""
    m = wp.max(wp.max(counts[particles[0]], counts[particles[1]]), wp.max(counts[particles[2]], counts[particles[3]]))
    return 1.0 / float(wp.max(m, 1))


@wp.func
def effective_inv_mass(particles: wp.vec4i, weights: wp.vec4, inv_mass: wp.array(dtype=float)) -> float:
    W = float(0.0)
    for k in range(4):
        W += weights[k] * weights[k] * inv_mass[particles[k]]
    return W


@wp.func
def to_fixed(x: float) -> wp.int64:
    return wp.int64(wp.float64(x) * wp.float64(FIXED_SCALE))


@wp.func
def scatter_contact(
    particles: wp.vec4i, weights: wp.vec4, inv_mass: wp.array(dtype=float), delta: wp.vec3,
    out: wp.array2d(dtype=wp.int64),
):
    """out[particle k] += a_k w_k delta in fixed point (integer atomics: order independent)."""
    for k in range(4):
        p = particles[k]
        dk = (weights[k] * inv_mass[p]) * delta
        for c in range(3):
            wp.atomic_add(out, p, c, to_fixed(dk[c]))


@wp.func
def scatter_push(particles: wp.vec4i, weights: wp.vec4, inv_mass: wp.array(dtype=float),
                 particle_contacts: wp.array(dtype=int), n: wp.vec3, depth: float, W: float, fraction: float,
                 dx_io: wp.array2d(dtype=wp.int64)):
    """A contact's position push: ``fraction`` of its depth [m] along n, Jacobi-scaled by its
    particles' contact counts (``contact_scale``), shared by ``resolve_one`` and ``push_one``."""
    scatter_contact(particles, weights, inv_mass, (fraction * contact_scale(particles, particle_contacts) * depth / W) * n,
                    dx_io)


@wp.func
def relative_velocity(particles: wp.vec4i, weights: wp.vec4, qd: wp.array(dtype=wp.vec3)) -> wp.vec3:
    """Relative velocity [m/s] of a contact's two sides: sum a_k v_k."""
    rel = wp.vec3()
    for k in range(4):
        rel += weights[k] * qd[particles[k]]
    return rel


@wp.func
def approach_slack(depth: float, inv_dt: float) -> float:
    """Approach speed [m/s] that closes a speculative contact's gap to the thickness in one step
    (0 within the thickness, and for every contact when ``inv_dt`` is 0)."""
    return wp.max(-depth, 0.0) * inv_dt


@wp.func
def needs_impulse(c: int, q: wp.array(dtype=wp.vec3), qd: wp.array(dtype=wp.vec3), inv_mass: wp.array(dtype=float),
                  contact_particles: wp.array(dtype=wp.vec4i), contact_weights: wp.array(dtype=wp.vec4),
                  contact_normal: wp.array(dtype=wp.vec3), thickness: float, inv_dt: float) -> bool:
    """Whether ``resolve_one`` gives contact slot c a normal impulse at (q, qd): a stored pair of
    movable particles approaching faster than its slack (the same functions, so the same bits)."""
    particles = contact_particles[c]
    if particles[0] < 0:
        return False
    weights = contact_weights[c]
    if effective_inv_mass(particles, weights, inv_mass) <= 0.0:
        return False
    n = contact_normal[c]
    depth = contact_depth(particles, weights, n, q, thickness)
    return wp.dot(relative_velocity(particles, weights, qd), n) < -approach_slack(depth, inv_dt)


@wp.func
def count_one_impulse(c: int, q: wp.array(dtype=wp.vec3), qd: wp.array(dtype=wp.vec3),
                      inv_mass: wp.array(dtype=float), contact_particles: wp.array(dtype=wp.vec4i),
                      contact_weights: wp.array(dtype=wp.vec4), contact_normal: wp.array(dtype=wp.vec3),
                      thickness: float, inv_dt: float, impulse_counts_io: wp.array(dtype=int)):
    """Add 1 to the impulse counts of slot c's particles if it gets an impulse in this pass: before each
    pass every particle's number of contacts that ``resolve_one`` gives an impulse in it (the
    impulses' Jacobi scale). Counting every stored pair instead diluted the few that act (a dense
    heap's pairs are mostly speculative and still); counting only pairs within the thickness gave a
    vertex in 20 speculative pairs, all approaching, 20 full impulses in one pass (19.9 m/s after a
    3.4 m/s approach: the donuts heap at 1/240 s)."""
    if needs_impulse(c, q, qd, inv_mass, contact_particles, contact_weights, contact_normal, thickness, inv_dt):
        particles = contact_particles[c]
        for k in range(4):
            wp.atomic_add(impulse_counts_io, particles[k], 1)


@wp.func
def resolve_one(
    c: int,
    q: wp.array(dtype=wp.vec3),
    qd: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    contact_particles: wp.array(dtype=wp.vec4i),
    contact_weights: wp.array(dtype=wp.vec4),
    contact_normal: wp.array(dtype=wp.vec3),
    particle_contacts: wp.array(dtype=int),
    impulse_counts: wp.array(dtype=int),
    thickness: float,
    fraction: float,
    restitution: float,
    friction: float,
    inv_dt: float,
    dx_io: wp.array2d(dtype=wp.int64),
    dv_io: wp.array2d(dtype=wp.int64),
):
    """One pass of contact slot c (module docstring): the position push removing ``fraction`` of the
    depth thickness - (sum a_k x_k) . n at the current positions (mass-weighted: the centre of mass
    does not move; no pull when the pair is already apart) and the normal impulse with restitution
    and Coulomb friction from the current velocities. A speculative contact (``inv_dt`` = 1 / step
    > 0: found within ``reach`` beyond the thickness) may still approach by its gap beyond the
    thickness in one step; only faster approach is removed (no restitution: no impact yet).
    ``inv_dt`` 0: every approach is an impact. The push is scaled by 1 / the particles' largest count
    of pairs within the thickness (``particle_contacts``), the impulse by 1 / their largest count of
    pairs given an impulse in this pass (``impulse_counts``, from ``count_one_impulse``)."""
    particles = contact_particles[c]
    if particles[0] < 0:
        return
    weights = contact_weights[c]
    W = effective_inv_mass(particles, weights, inv_mass)
    if W <= 0.0:
        return
    n = contact_normal[c]
    depth = contact_depth(particles, weights, n, q, thickness)
    if depth > 0.0:
        scatter_push(particles, weights, inv_mass, particle_contacts, n, depth, W, fraction, dx_io)
    rel = relative_velocity(particles, weights, qd)
    un = wp.dot(rel, n)
    slack = approach_slack(depth, inv_dt)
    if un >= -slack:
        return
    jn = -(1.0 + restitution) * un / W
    if slack > 0.0:
        jn = -(un + slack) / W
    impulse = jn * n
    vt = rel - un * n
    vt_len = wp.length(vt)
    if vt_len > 0.0 and friction > 0.0:
        jt = wp.min(friction * jn, vt_len / W)
        impulse = impulse - (jt / vt_len) * vt
    scatter_contact(particles, weights, inv_mass, contact_scale(particles, impulse_counts) * impulse, dv_io)


@wp.func
def take_delta(i: int, delta_io: wp.array2d(dtype=wp.int64)) -> wp.vec3:
    """Row i of a fixed-point delta buffer as a vec3, clearing the row."""
    d = wp.vec3()
    for c in range(3):
        d[c] = float(wp.float64(delta_io[i, c]) * wp.float64(FIXED_INV_SCALE))
        delta_io[i, c] = wp.int64(0)
    return d


@wp.func
def apply_one(
    i: int,
    dx_io: wp.array2d(dtype=wp.int64),
    dv_io: wp.array2d(dtype=wp.int64),
    q_io: wp.array(dtype=wp.vec3),
    qd_io: wp.array(dtype=wp.vec3),
):
    """q[i] += dx[i], qd[i] += dv[i] (from fixed point), then clear both."""
    q_io[i] = q_io[i] + take_delta(i, dx_io)
    qd_io[i] = qd_io[i] + take_delta(i, dv_io)


@wp.func
def push_one(
    c: int,
    q: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    contact_particles: wp.array(dtype=wp.vec4i),
    contact_weights: wp.array(dtype=wp.vec4),
    contact_normal: wp.array(dtype=wp.vec3),
    particle_contacts: wp.array(dtype=int),
    thickness: float,
    fraction: float,
    max_depth: float,
    dx_io: wp.array2d(dtype=wp.int64),
):
    """The position push of ``resolve_one`` alone, for contact slot c, at positions q (no
    velocities: ``SoftContact.project_positions`` inside a solver's iterations). A pair deeper than
    ``max_depth`` [m] is left alone: its vertex has passed the plane stored at the search (or slid
    off its triangle), and pushing it along the stored normal would throw it (the collider's next
    search sees it afresh)."""
    particles = contact_particles[c]
    if particles[0] < 0:
        return
    weights = contact_weights[c]
    W = effective_inv_mass(particles, weights, inv_mass)
    n = contact_normal[c]
    depth = contact_depth(particles, weights, n, q, thickness)
    if W <= 0.0 or depth <= 0.0 or depth > max_depth:
        return
    scatter_push(particles, weights, inv_mass, particle_contacts, n, depth, W, fraction, dx_io)


@wp.kernel
def push_listed(
    stride: int,
    listed: wp.array(dtype=int),
    slots: wp.array(dtype=int),
    q: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    contact_particles: wp.array(dtype=wp.vec4i),
    contact_weights: wp.array(dtype=wp.vec4),
    contact_normal: wp.array(dtype=wp.vec3),
    particle_contacts: wp.array(dtype=int),
    thickness: float,
    fraction: float,
    max_depth: float,
    dx_io: wp.array2d(dtype=wp.int64),
):
    """``push_one`` for the listed contact slots (``list_touched``; ``stride`` threads, each every
    stride-th of the listed[0] slots)."""
    for i in range(wp.tid(), listed[0], stride):
        push_one(slots[i], q, inv_mass, contact_particles, contact_weights, contact_normal, particle_contacts,
                 thickness, fraction, max_depth, dx_io)


@wp.kernel
def list_touched(contact_particles: wp.array(dtype=wp.vec4i), mark_io: wp.array(dtype=int),
                 touched_out: wp.array(dtype=int), count_io: wp.array(dtype=int), slots_out: wp.array(dtype=int),
                 slot_count_io: wp.array(dtype=int)):
    """Append contact slot c to ``slots`` if it holds a contact, and each of its particles to
    ``touched`` once (the thread that raises its mark from 0 appends it). The lists' order varies on
    a GPU; the passes over them sum fixed-point deltas, which do not depend on it."""
    c = wp.tid()
    particles = contact_particles[c]
    if particles[0] < 0:
        return
    slots_out[wp.atomic_add(slot_count_io, 0, 1)] = c
    for k in range(4):
        p = particles[k]
        if p >= 0:
            if wp.atomic_add(mark_io, p, 1) == 0:
                touched_out[wp.atomic_add(count_io, 0, 1)] = p


@wp.kernel
def apply_touched(stride: int, count: wp.array(dtype=int), touched: wp.array(dtype=int),
                  dx_io: wp.array2d(dtype=wp.int64), dv_io: wp.array2d(dtype=wp.int64), q_io: wp.array(dtype=wp.vec3),
                  qd_io: wp.array(dtype=wp.vec3), positions_only: int, impulse_counts_io: wp.array(dtype=int)):
    """``apply_one`` for the listed particles (``stride`` threads, each every stride-th), or with
    ``positions_only`` q += dx alone (``push_listed``'s passes; dv is untouched); their impulse
    counts are zeroed for the next pass."""
    for i in range(wp.tid(), count[0], stride):
        p = touched[i]
        impulse_counts_io[p] = 0
        if positions_only != 0:
            q_io[p] = q_io[p] + take_delta(p, dx_io)
        else:
            apply_one(p, dx_io, dv_io, q_io, qd_io)


@wp.kernel
def clear_touched(stride: int, count: wp.array(dtype=int), touched: wp.array(dtype=int), mark_io: wp.array(dtype=int)):
    """Lower the marks of the listed particles (the count is zeroed after, by a memset)."""
    for i in range(wp.tid(), count[0], stride):
        mark_io[touched[i]] = 0


# ------------------------------------------------------------------------------ implicit contact
# Contact as a penalty force inside implicit Euler (``SoftContactForce``): for each contact slot
# (particles k, weights a_k, normal n) found by the last search, depth d = thickness - (sum a_k x_k) . n;
# while d > 0 the energy 1/2 k_c d^2 gives particle k the force F_k = (k_c d - c_c u_n) a_k n
# (u_n = (sum a_k v_k) . n; sum a_k = 0: momentum is conserved). The Jacobian -k_c (a a^T) (x) n n^T
# is replaced by the diagonal blocks -m k_c a_k^2 n n^T, m the number of nonzero weights: by
# Cauchy-Schwarz (sum a_k x_k)^2 <= m sum a_k^2 x_k^2, so the diagonal stiffness is at least the
# true one in every direction and the linearly implicit step stays stable at any step size (with
# a softer diagonal, z = h^2 k / m past 4/3 of its inverse scale, it would not). Sums in fixed point.
@wp.kernel
def eval_contact_forces(
    q: wp.array(dtype=wp.vec3),
    qd: wp.array(dtype=wp.vec3),
    contact_particles: wp.array(dtype=wp.vec4i),
    contact_weights: wp.array(dtype=wp.vec4),
    contact_normal: wp.array(dtype=wp.vec3),
    thickness: float,
    stiffness: float,
    damping: float,
    f_io: wp.array2d(dtype=wp.int64),
):
    """Penalty force of contact slot c at (q, qd) into f_io (fixed point; see above)."""
    c = wp.tid()
    particles = contact_particles[c]
    if particles[0] < 0:
        return
    weights = contact_weights[c]
    n = contact_normal[c]
    depth = contact_depth(particles, weights, n, q, thickness)
    if depth <= 0.0:
        return
    rel = wp.vec3()
    for k in range(4):
        rel += weights[k] * qd[particles[k]]
    magnitude = stiffness * depth - damping * wp.dot(rel, n)
    if magnitude <= 0.0:  # a penalty pushes, never pulls
        return
    for k in range(4):
        fk = (weights[k] * magnitude) * n
        for i in range(3):
            wp.atomic_add(f_io, particles[k], i, to_fixed(fk[i]))  # int64 fixed point: any order, same bits


@wp.kernel
def eval_contact_jacobian(
    q: wp.array(dtype=wp.vec3),
    contact_particles: wp.array(dtype=wp.vec4i),
    contact_weights: wp.array(dtype=wp.vec4),
    contact_normal: wp.array(dtype=wp.vec3),
    thickness: float,
    coefficient: float,
    blocks_io: wp.array2d(dtype=wp.int64),
):
    """Diagonal blocks coefficient m a_k^2 n n^T of contact slot c (coefficient = -(ck k_c + cd c_c):
    ck df/dx + cd df/dv with the diagonal stand-in above) into blocks_io (n, 9), fixed point."""
    c = wp.tid()
    particles = contact_particles[c]
    if particles[0] < 0:
        return
    weights = contact_weights[c]
    n = contact_normal[c]
    if contact_depth(particles, weights, n, q, thickness) <= 0.0:
        return
    m = float(0.0)
    for k in range(4):
        if weights[k] != 0.0:
            m += 1.0
    nn = wp.outer(n, n)
    for k in range(4):
        block = (coefficient * m * weights[k] * weights[k]) * nn
        for i in range(3):
            for j in range(3):
                wp.atomic_add(blocks_io, particles[k], 3 * i + j, to_fixed(block[i, j]))  # int64: order-free


@wp.kernel
def add_fixed_forces(f_io: wp.array2d(dtype=wp.int64), f_out: wp.array(dtype=wp.vec3)):
    """f_out[i] += f_io[i] (from fixed point), then clear f_io."""
    i = wp.tid()
    f = wp.vec3()
    for c in range(3):
        f[c] = float(wp.float64(f_io[i, c]) * wp.float64(FIXED_INV_SCALE))
        f_io[i, c] = wp.int64(0)
    f_out[i] = f_out[i] + f


@wp.kernel
def add_fixed_blocks(blocks_io: wp.array2d(dtype=wp.int64), diag_out: wp.array(dtype=wp.mat33)):
    """diag_out[i] += blocks_io[i] (row-major 3x3, from fixed point), then clear blocks_io."""
    i = wp.tid()
    b = wp.mat33()
    for r in range(3):
        for c in range(3):
            b[r, c] = float(wp.float64(blocks_io[i, 3 * r + c]) * wp.float64(FIXED_INV_SCALE))
            blocks_io[i, 3 * r + c] = wp.int64(0)
    diag_out[i] = diag_out[i] + b


@wp.kernel
def eval_contact_coupling(
    q: wp.array(dtype=wp.vec3),
    contact_particles: wp.array(dtype=wp.vec4i),
    contact_weights: wp.array(dtype=wp.vec4),
    contact_normal: wp.array(dtype=wp.vec3),
    thickness: float,
    coefficient: float,
    blocks_io: wp.array2d(dtype=wp.int64),
    rows_out: wp.array(dtype=int),
    cols_out: wp.array(dtype=int),
    values_out: wp.array(dtype=wp.mat33),
):
    """The exact Jacobian of contact slot c's penalty, coefficient (a a^T) (x) n n^T: diagonal
    blocks coefficient a_k^2 n n^T into blocks_io (fixed point) and the 12 coupling blocks
    coefficient a_j a_k n n^T (j != k) as triplets 12 c .. 12 c + 11. A slot without a pushing
    contact writes zero blocks at (0, 0), so the number of triplets never changes."""
    c = wp.tid()
    particles = contact_particles[c]
    active = int(0)
    weights = wp.vec4()
    nn = wp.mat33()
    if particles[0] >= 0:
        weights = contact_weights[c]
        n = contact_normal[c]
        if contact_depth(particles, weights, n, q, thickness) > 0.0:
            active = 1
            nn = wp.outer(n, n)
    slot = 12 * c
    for j in range(4):
        if active == 1:
            block = (coefficient * weights[j] * weights[j]) * nn
            for r in range(3):
                for s in range(3):
                    wp.atomic_add(blocks_io, particles[j], 3 * r + s, to_fixed(block[r, s]))  # int64: order-free
        for k in range(4):
            if k != j:
                if active == 1:
                    rows_out[slot] = particles[j]
                    cols_out[slot] = particles[k]
                    values_out[slot] = (coefficient * weights[j] * weights[k]) * nn
                else:
                    rows_out[slot] = 0
                    cols_out[slot] = 0
                    values_out[slot] = wp.mat33()
                slot += 1
