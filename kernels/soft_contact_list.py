"""Soft-body contact from a Verlet-style candidate list (``SoftContact(broad_phase="list")``).

The two-level BVH search of ``warpsim.kernels.soft_contact`` runs only on some steps and writes,
for every query (contact vertex v, slot v; surface edge e, slot V + e), the primitives (other
bodies' triangles, edges) closer than ``keep`` at the search, up to ``capacity`` per query, into
one buffer (both pair kinds, one launch). Every step then evaluates only those candidates
(``narrow_candidates``: same narrow phase, nearest contact per query, ties to the lower index),
which finds exactly the contacts of a full search as long as no contact vertex has moved more
than ``pad`` since the search (when each of the up to four particles of a pair moved at most
``pad``, the pair's distance changed by at most 2 pad) and none more than ``thickness / 2`` in
one step:

* vertex-triangle: a contact needs distance < max(thickness, search): keep = that + 2 pad;
* edge-edge: a contact needs distance < thickness, or the edges crossed during the step: with
  g the gap between the closest points (fixed parameters) at the step's start g0 and end g1,
  g0 . g1 < 0 gives |g1|^2 < g1 . (g1 - g0) <= |g1| |g1 - g0|, so |g1| < |g1 - g0| <= 2 m, m the
  largest move of a vertex in the step: keep = max(thickness, min(search, 2 m)) + 2 pad with m of
  the search's step, and a later step with m > thickness / 2 searches again.

The device decides when to search again (no host read-back): ``check_motion`` compares every
contact vertex with its position at the last search and raises ``flags[0]`` when one moved more
than ``pad``; ``search_candidates`` does nothing unless ``flags[0]`` is set. The host refits (or
rebuilds) the BVHs on a fixed cadence and raises the flag then (``begin_search``); a search between
two refits uses the refitted tree's stale leaves, so its boxes grow by ``motion[0]``, the largest
move of a contact vertex since the refit (exact float atomic max: order independent).

A query with more than ``capacity`` candidates keeps the first ``capacity`` and counts an
overflow (``flags[2]``, read at a frame's end): its contacts may be missed, so raise the capacity.
Contacts found are appended to a compact list (``active``) and their particles to ``touched`` (a
particle is appended by the contact that raises its count from 0): the pushes and impulses run
over those lists only. The order of either list depends on the thread schedule, the sums do not
(int64 fixed point), so runs stay bit-identical.
"""

import warp as wp

from .soft_contact import (
    apply_one,
    count_one_impulse,
    counts_toward_scale,
    edge_edge_candidate,
    edge_edge_test,
    first_body,
    nearer,
    next_body,
    resolve_one,
    segment_closest_params,
    triangle_barycentric,
    vertex_triangle_candidate,
    vertex_triangle_test,
)

wp.set_module_options({"enable_backward": False})

FLAG_SEARCH = wp.constant(0)  # flags[0]: search this step
FLAG_SEARCHES = wp.constant(1)  # flags[1]: searches done (statistics)
FLAG_OVERFLOW = wp.constant(2)  # flags[2]: queries that had more candidates than the capacity


@wp.kernel
def begin_search(
    vertex_particle: wp.array(dtype=int), q: wp.array(dtype=wp.vec3), x_tree_out: wp.array(dtype=wp.vec3),
    flags_io: wp.array(dtype=int), motion_out: wp.array(dtype=float),
):
    """After a refit or rebuild (host cadence): remember the contact vertices' positions of the
    tree, zero the motion since it and raise the search flag."""
    v = wp.tid()
    x_tree_out[v] = q[vertex_particle[v]]
    if v == 0:
        flags_io[FLAG_SEARCH] = 1
        motion_out[0] = 0.0


@wp.kernel
def check_motion(
    vertex_particle: wp.array(dtype=int), q: wp.array(dtype=wp.vec3), q_prev: wp.array(dtype=wp.vec3),
    x_search: wp.array(dtype=wp.vec3), x_tree: wp.array(dtype=wp.vec3), pad: float, step_limit: float,
    flags_io: wp.array(dtype=int), motion_io: wp.array(dtype=float),
):
    """motion[0] = max over contact vertices of the distance moved since the refit, motion[1] =
    max distance moved in this step (zeroed by the last ``end_search``; atomic max only when larger than the
    value read: the result is the exact maximum); raise the search flag when a vertex moved more
    than ``pad`` since the last search or more than ``step_limit`` in this step."""
    v = wp.tid()
    p = vertex_particle[v]
    x = q[p]
    moved = wp.length(x - x_tree[v])
    if moved > motion_io[0]:
        wp.atomic_max(motion_io, 0, moved)
    step = wp.length(x - q_prev[p])
    if step > motion_io[1]:
        wp.atomic_max(motion_io, 1, step)
    if (wp.length(x - x_search[v]) > pad or step > step_limit) and flags_io[FLAG_SEARCH] == 0:
        flags_io[FLAG_SEARCH] = 1


@wp.kernel
def end_search(flags_io: wp.array(dtype=int), motion_io: wp.array(dtype=float), total_out: wp.array(dtype=int),
               listed_out: wp.array(dtype=int)):
    """After ``search_candidates``: lower the search flag and count the search; zero this step's
    largest move (for the next step's ``check_motion``) and the contact counts and list lengths
    (for ``narrow_candidates``): one launch instead of four clears."""
    if flags_io[FLAG_SEARCH] != 0:
        flags_io[FLAG_SEARCH] = 0
        flags_io[FLAG_SEARCHES] = flags_io[FLAG_SEARCHES] + 1
    motion_io[1] = 0.0
    for k in range(2):
        total_out[k] = 0
        listed_out[k] = 0


@wp.func
def push_candidate(slot: int, found: int, item: int, capacity: int, cand_out: wp.array(dtype=int)) -> int:
    """Store candidate ``item`` as the query's ``found``-th (if it fits); returns found + 1."""
    if found < capacity:
        cand_out[slot * capacity + found] = item
    return found + 1


@wp.func
def search_vertex(
    v: int, grow: float, keep: float, body_bvh: wp.uint64, world_root: wp.array(dtype=int), tri_bvh: wp.uint64,
    body_tri_root: wp.array(dtype=int), vertex_world: wp.array(dtype=int), vertex_particle: wp.array(dtype=int),
    vertex_body: wp.array(dtype=int), tri: wp.array(dtype=int), tri_body: wp.array(dtype=int),
    q: wp.array(dtype=wp.vec3), rest: wp.array(dtype=wp.vec3), inv_mass: wp.array(dtype=float),
    self_contact: int, self_rest_distance: float, capacity: int, cand_out: wp.array(dtype=int),
) -> int:
    """Triangles of the other bodies within ``keep`` of contact vertex v (query box half width
    ``grow``: keep + the tree's staleness); returns how many (may exceed the capacity)."""
    p = vertex_particle[v]
    body = vertex_body[v]
    x = q[p]
    lower = x - wp.vec3(grow)
    upper = x + wp.vec3(grow)
    found = int(0)
    others = first_body(body_bvh, world_root[vertex_world[v]], lower, upper, body, self_contact)
    while others.other >= 0:
        query = wp.bvh_query_aabb(tri_bvh, lower, upper, body_tri_root[others.other])
        t = int(0)
        while wp.bvh_query_next(query, t):
            if vertex_triangle_candidate(p, body, t, tri, tri_body, rest, inv_mass, self_contact, self_rest_distance):
                a = q[tri[3 * t]]
                b = q[tri[3 * t + 1]]
                c = q[tri[3 * t + 2]]
                w = triangle_barycentric(x, a, b, c)
                if wp.length(x - (w[0] * a + w[1] * b + w[2] * c)) < keep:
                    found = push_candidate(v, found, t, capacity, cand_out)
        others = next_body(others)
    return found


@wp.func
def search_edge(
    e: int, slot: int, grow: float, keep: float, body_bvh: wp.uint64, world_root: wp.array(dtype=int),
    edge_bvh: wp.uint64, body_edge_root: wp.array(dtype=int), edge_world: wp.array(dtype=int),
    edges: wp.array(dtype=int), edge_body: wp.array(dtype=int), q: wp.array(dtype=wp.vec3),
    rest: wp.array(dtype=wp.vec3), inv_mass: wp.array(dtype=float), self_contact: int, self_rest_distance: float,
    capacity: int, cand_out: wp.array(dtype=int),
) -> int:
    """Edges of the other bodies within ``keep`` of surface edge e (as ``search_vertex``)."""
    body = edge_body[e]
    xa = q[edges[2 * e]]
    xb = q[edges[2 * e + 1]]
    lower = wp.min(xa, xb) - wp.vec3(grow)
    upper = wp.max(xa, xb) + wp.vec3(grow)
    found = int(0)
    others = first_body(body_bvh, world_root[edge_world[e]], lower, upper, body, self_contact)
    while others.other >= 0:
        query = wp.bvh_query_aabb(edge_bvh, lower, upper, body_edge_root[others.other])
        f = int(0)
        while wp.bvh_query_next(query, f):
            if edge_edge_candidate(e, f, edges, edge_body, rest, inv_mass, self_contact, self_rest_distance):
                xc = q[edges[2 * f]]
                xd = q[edges[2 * f + 1]]
                ut = segment_closest_params(xa, xb, xc, xd)
                if wp.length((xa + ut[0] * (xb - xa)) - (xc + ut[1] * (xd - xc))) < keep:
                    found = push_candidate(slot, found, f, capacity, cand_out)
        others = next_body(others)
    return found


@wp.kernel
def search_candidates(
    flags_io: wp.array(dtype=int),
    motion: wp.array(dtype=float),
    thickness: float,
    edge_thickness: float,
    search: float,
    pad: float,
    body_bvh: wp.uint64,
    world_root: wp.array(dtype=int),
    tri_bvh: wp.uint64,
    body_tri_root: wp.array(dtype=int),
    edge_bvh: wp.uint64,
    body_edge_root: wp.array(dtype=int),
    vertex_world: wp.array(dtype=int),
    vertex_particle: wp.array(dtype=int),
    vertex_body: wp.array(dtype=int),
    tri: wp.array(dtype=int),
    tri_body: wp.array(dtype=int),
    edge_world: wp.array(dtype=int),
    edges: wp.array(dtype=int),
    edge_body: wp.array(dtype=int),
    q: wp.array(dtype=wp.vec3),
    rest: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    self_contact: int,
    self_rest_distance: float,
    capacity: int,
    x_search_out: wp.array(dtype=wp.vec3),
    cand_out: wp.array(dtype=int),
    count_out: wp.array(dtype=int),
):
    """Candidates of query i (vertex i < V, else edge i - V) when the search flag is up; both pair
    kinds in one launch and one buffer (``capacity`` slots a query). Kept within
    max(thickness, search) + 2 pad of a vertex, max(edge_thickness, min(search, 2 motion[1])) + 2 pad of
    an edge (module docstring; the detection distances of the two kinds, thickness + reach and
    thickness + edge reach); query boxes grow by the tree's staleness motion[0]."""
    i = wp.tid()
    if flags_io[FLAG_SEARCH] == 0:
        return
    V = vertex_particle.shape[0]
    found = int(0)
    if i < V:
        keep = wp.max(thickness, search) + 2.0 * pad
        x_search_out[i] = q[vertex_particle[i]]
        found = search_vertex(i, keep + motion[0], keep, body_bvh, world_root, tri_bvh, body_tri_root, vertex_world,
                              vertex_particle, vertex_body, tri, tri_body, q, rest, inv_mass, self_contact,
                              self_rest_distance, capacity, cand_out)
    else:
        keep = wp.max(edge_thickness, wp.min(search, 2.0 * motion[1])) + 2.0 * pad
        found = search_edge(i - V, i, keep + motion[0], keep, body_bvh, world_root, edge_bvh, body_edge_root, edge_world, edges,
                            edge_body, q, rest, inv_mass, self_contact, self_rest_distance, capacity, cand_out)
    if found > capacity:
        wp.atomic_add(flags_io, FLAG_OVERFLOW, 1)
    count_out[i] = wp.min(found, capacity)


@wp.func
def list_contact(
    slot: int, particles: wp.vec4i, weights: wp.vec4, normal: wp.vec3, kind: int, q: wp.array(dtype=wp.vec3),
    count_within: float,
    contact_particles_out: wp.array(dtype=wp.vec4i), contact_weights_out: wp.array(dtype=wp.vec4),
    contact_normal_out: wp.array(dtype=wp.vec3), particle_contacts_io: wp.array(dtype=int),
    seen_io: wp.array(dtype=int),
    contact_total_io: wp.array(dtype=int), active_out: wp.array(dtype=int), touched_out: wp.array(dtype=int),
    listed_io: wp.array(dtype=int),
):
    """Store contact ``slot``, append it to ``active`` and each of its particles seen for the
    first time to ``touched`` (listed[0], listed[1]: their lengths); the particles' contact
    counts (the Jacobi scale) take it only within ``count_within`` (``counts_toward_scale``)."""
    contact_particles_out[slot] = particles
    contact_weights_out[slot] = weights
    contact_normal_out[slot] = normal
    counted = counts_toward_scale(particles, weights, normal, q, count_within)
    for k in range(4):
        if wp.atomic_add(seen_io, particles[k], 1) == 0:
            touched_out[wp.atomic_add(listed_io, 1, 1)] = particles[k]
        if counted:
            wp.atomic_add(particle_contacts_io, particles[k], 1)
    wp.atomic_add(contact_total_io, kind, 1)
    active_out[wp.atomic_add(listed_io, 0, 1)] = slot


@wp.kernel
def narrow_candidates(
    cand: wp.array(dtype=int),
    cand_count: wp.array(dtype=int),
    capacity: int,
    vertex_particle: wp.array(dtype=int),
    tri: wp.array(dtype=int),
    edges: wp.array(dtype=int),
    q: wp.array(dtype=wp.vec3),
    q_prev: wp.array(dtype=wp.vec3),
    thickness: float,
    edge_thickness: float,
    search: float,
    count_within: float,
    contact_particles_out: wp.array(dtype=wp.vec4i),
    contact_weights_out: wp.array(dtype=wp.vec4),
    contact_normal_out: wp.array(dtype=wp.vec3),
    particle_contacts_io: wp.array(dtype=int),
    seen_io: wp.array(dtype=int),
    contact_total_io: wp.array(dtype=int),
    active_out: wp.array(dtype=int),
    touched_out: wp.array(dtype=int),
    listed_io: wp.array(dtype=int),
):
    """Nearest contact of query i among its candidates (vertex-triangle for i < V, else edge-edge),
    the narrow phase of ``warpsim.kernels.soft_contact``; slot i cleared when there is none."""
    i = wp.tid()
    V = vertex_particle.shape[0]
    best = int(-1)
    best_d = float(1.0e30)
    best_w = wp.vec3()
    best_normal = wp.vec3()
    contact_particles_out[i] = wp.vec4i(-1, -1, -1, -1)
    if i < V:
        p = vertex_particle[i]
        x = q[p]
        for k in range(cand_count[i]):
            t = cand[i * capacity + k]
            d, bary, n = vertex_triangle_test(x, q[tri[3 * t]], q[tri[3 * t + 1]], q[tri[3 * t + 2]], thickness,
                                              search)
            if d >= 0.0 and nearer(d, t, best_d, best):
                best_d = d
                best = t
                best_w = bary
                best_normal = n
        if best >= 0:
            list_contact(i, wp.vec4i(p, tri[3 * best], tri[3 * best + 1], tri[3 * best + 2]),
                         wp.vec4(1.0, -best_w[0], -best_w[1], -best_w[2]), best_normal, 0, q, count_within,
                         contact_particles_out, contact_weights_out, contact_normal_out, particle_contacts_io,
                         seen_io, contact_total_io, active_out, touched_out, listed_io)
        return
    e = i - V
    xa = q[edges[2 * e]]
    xb = q[edges[2 * e + 1]]
    pa = q_prev[edges[2 * e]]
    pb = q_prev[edges[2 * e + 1]]
    for k in range(cand_count[i]):
        f = cand[i * capacity + k]
        d, ut, n = edge_edge_test(f, xa, xb, pa, pb, edges, q, q_prev, edge_thickness, search)
        if d >= 0.0 and nearer(d, f, best_d, best):
            best_d = d
            best = f
            best_w = wp.vec3(ut[0], ut[1], 0.0)
            best_normal = n
    if best >= 0:
        u = best_w[0]
        s = best_w[1]
        list_contact(i, wp.vec4i(edges[2 * e], edges[2 * e + 1], edges[2 * best], edges[2 * best + 1]),
                     wp.vec4(1.0 - u, u, s - 1.0, -s), best_normal, 1, q, count_within, contact_particles_out,
                     contact_weights_out, contact_normal_out, particle_contacts_io, seen_io, contact_total_io,
                     active_out, touched_out, listed_io)


@wp.kernel
def resolve_listed(
    stride: int,
    listed: wp.array(dtype=int),
    active: wp.array(dtype=int),
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
    """``resolve_one`` for every found contact: thread t of ``stride`` threads takes contacts t,
    t + stride, ... (the launch does not grow with the contact slots)."""
    for i in range(wp.tid(), listed[0], stride):
        resolve_one(active[i], q, qd, inv_mass, contact_particles, contact_weights, contact_normal,
                    particle_contacts, impulse_counts, thickness, fraction, restitution, friction, inv_dt, dx_io, dv_io)


@wp.kernel
def count_listed_impulses(
    stride: int, listed: wp.array(dtype=int), active: wp.array(dtype=int), q: wp.array(dtype=wp.vec3),
    qd: wp.array(dtype=wp.vec3), inv_mass: wp.array(dtype=float), contact_particles: wp.array(dtype=wp.vec4i),
    contact_weights: wp.array(dtype=wp.vec4), contact_normal: wp.array(dtype=wp.vec3), thickness: float,
    inv_dt: float, impulse_counts_io: wp.array(dtype=int),
):
    """``count_one_impulse`` for every found contact (``stride`` threads, as ``resolve_listed``)."""
    for i in range(wp.tid(), listed[0], stride):
        count_one_impulse(active[i], q, qd, inv_mass, contact_particles, contact_weights, contact_normal, thickness,
                          inv_dt, impulse_counts_io)


@wp.kernel
def apply_listed(
    stride: int,
    listed: wp.array(dtype=int),
    touched: wp.array(dtype=int),
    dx_io: wp.array2d(dtype=wp.int64),
    dv_io: wp.array2d(dtype=wp.int64),
    q_io: wp.array(dtype=wp.vec3),
    qd_io: wp.array(dtype=wp.vec3),
    impulse_counts_io: wp.array(dtype=int),
):
    """``apply_one`` for every particle in a contact (``stride`` threads, as ``resolve_listed``), and
    zero its impulse count for the next pass."""
    for i in range(wp.tid(), listed[1], stride):
        p = touched[i]
        apply_one(p, dx_io, dv_io, q_io, qd_io)
        impulse_counts_io[p] = 0


@wp.kernel
def forget_listed(stride: int, listed: wp.array(dtype=int), touched: wp.array(dtype=int),
                  particle_contacts_io: wp.array(dtype=int), seen_io: wp.array(dtype=int)):
    """At a step's start, before ``narrow_candidates`` counts afresh: zero the contact counts and seen
    marks of the last step's particles. They stay set between steps, so a solver that pushes the
    stored contacts inside its iterations (``SoftContact.project_positions``) scales them as the
    BVH search's steps do (zeroed after the last pass, they left those pushes unscaled)."""
    for i in range(wp.tid(), listed[1], stride):
        p = touched[i]
        particle_contacts_io[p] = 0
        seen_io[p] = 0
