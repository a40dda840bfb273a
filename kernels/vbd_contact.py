"""Contact search and contact energies of vertex block descent (``warpsim.bodies.vbd.VBD``).

Search (once at the start of a step and again every ``detect_every`` iterations, at the current
positions x_d; one within the step is skipped, on the device, when every particle is well inside its bound,
``search_needed``): two levels as ``warpsim.kernels.soft_contact`` (the bodies' bounds in a small BVH, then
the subtree of each body met in a BVH grouped by body, ``collect_bodies``), three queries, each
writing its own fixed-capacity list, sorted ascending (no atomics on the lists, and no dependence on
the BVH's traversal order, so the lists and everything computed from them are the same bits on every
run, and a world of a sweep gets the bits of its scene run alone):

* every surface vertex against the triangles within the pair's radius (``vt_list``; the vertex's
  side of a vertex-triangle pair);
* every triangle against the surface vertices within the radius (``tv_list``; the triangle's side
  of the same pairs);
* every surface edge against the edges within the radius (``ee_list``),

one kernel, ``query_pairs``, with the query's kind as its first argument. The vertex query also stages
each pair it finds into the triangle's list, and the edge query meets each pair once (from the edge of the
lower body) and stages it into both edges' lists, each side's distance computed as that side's own query
computes it; a list that holds all its item's pairs is then only sorted, and a query with more pairs than
the capacity is run whole (``WHOLE``, ``HALF``, ``FINISH``): the lists, distances and smallest distances
of three whole queries, bit for bit, with one triangle query and half the edge traversal less.

Pairs sharing a particle are skipped; so are pairs of the same body unless self contact is on.
Each query also keeps the smallest distance of its pairs (``*_min``, [m]); ``displacement_bounds`` turns
them into each particle's step bound (the proof is in ``warpsim.bodies.vbd``). A query with more
pairs within the radius than a list's ``capacity`` keeps the nearest (``keep_nearest``), is counted in
``overflow`` (queries past capacity at this search and the most pairs one query met: integer atomics on
figures bounded by the number of queries and of pairs, zeroed at each search) and still lowers the
smallest distance with the rest, so an overflow can miss a far pair's force but never the bound.

After the search ``keep_near_pairs`` keeps, for each surface vertex, the list entries that can still push on
it before the next search (by the distances and the step bounds), so the colour sweeps gather over those
alone (the same sums, bit for bit).

Contact energy of one pair, written with four particles k and weights a_k (vertex-triangle: 1,
-b_0, -b_1, -b_2 with b the barycentrics of the triangle point nearest the vertex; edge-edge:
1 - s, s, -(1 - t), -t with s, t the parameters of the nearest points): r = sum a_k x_k, d = |r|,
n = r / d, and for d < r_c (``radius``)

    E = k_c / 2 (r_c - d)^2,       -dE/dx_k = k_c (r_c - d) a_k n,       H_kk ~ k_c a_k^2 n n^T

(the weights held fixed; the Hessian's curvature term -k_c (r_c - d) / d a_k^2 (I - n n^T) is dropped
so the block stays positive semi-definite, as in VBD). Friction (VBD's, after IPC): with the
normal force lambda = k_c (r_c - d) lagged, the tangential relative displacement over the step
u = (I - n n^T) sum a_k (x_k - x_k^t) and eps = ``friction_eps`` [m],

    f_k = -mu lambda a_k f1(|u|) / |u| u,     H_kk ~ mu lambda a_k^2 f1(|u|) / |u| (I - n n^T),

f1(y) = 2 y / eps - y^2 / eps^2 below eps, 1 above (static friction as a stiff spring up to eps).
"""

import warp as wp

from .soft_contact import BODY_BATCH, collect_bodies, segment_closest_params, triangle_barycentric

wp.set_module_options({"enable_backward": False})


@wp.func
def pair_force_hessian(r: wp.vec3, u: wp.vec3, a: float, radius: float, stiffness: float, friction: float,
                       friction_eps: float):
    """Force [N] and Hessian block [N/m] on a particle of weight ``a`` in a pair with relative
    position ``r`` = sum a_k x_k [m] and relative step displacement ``u`` [m] (module docstring);
    zero beyond ``radius``."""
    d = wp.length(r)
    if d >= radius or d < 1.0e-12 or a == 0.0:
        return wp.vec3(), wp.mat33()
    n = r / d
    lam = stiffness * (radius - d)
    nn = wp.outer(n, n)
    f = lam * a * n
    H = stiffness * a * a * nn
    if friction > 0.0:
        ut = u - wp.dot(u, n) * n
        y = wp.length(ut)
        s = float(0.0)
        if y < friction_eps:
            s = 2.0 / friction_eps - y / (friction_eps * friction_eps)
        else:
            s = 1.0 / y
        f = f - friction * lam * a * s * ut
        H = H + friction * lam * a * a * s * (wp.identity(3, dtype=float) - nn)
    return f, H


@wp.func
def spheres_apart(c1: wp.vec3, r1: float, c2: wp.vec3, r2: float, radius: float) -> bool:
    """Whether two bounding spheres (centres [m], radii [m]) are more than ``radius`` apart: then so are
    the primitives inside them (a cheap rejection before the nearest points)."""
    return wp.length(c1 - c2) > r1 + r2 + radius


@wp.func
def triangle_sphere(a: wp.vec3, b: wp.vec3, c: wp.vec3):
    """A bounding sphere of triangle abc: (centroid, largest corner distance) [m]."""
    m = (a + b + c) / 3.0
    return m, wp.max(wp.max(wp.length(a - m), wp.length(b - m)), wp.length(c - m))


@wp.func
def vertex_triangle_rel(x: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3):
    """(r = x - nearest point of triangle abc [m], barycentrics of that point)."""
    w = triangle_barycentric(x, a, b, c)
    return x - (w[0] * a + w[1] * b + w[2] * c), w


@wp.func
def edge_edge_rel(p1: wp.vec3, q1: wp.vec3, p2: wp.vec3, q2: wp.vec3):
    """(r = nearest point of edge p1q1 - nearest point of edge p2q2 [m], their parameters (s, t))."""
    st = segment_closest_params(p1, q1, p2, q2)
    return (p1 + st[0] * (q1 - p1)) - (p2 + st[1] * (q2 - p2)), st


@wp.func
def vertex_triangle_distance(p: int, x: wp.vec3, t: int, tri: wp.array(dtype=int), body: wp.array(dtype=int),
                             q: wp.array(dtype=wp.vec3), self_contact: int) -> float:
    """Distance [m] from particle p at x to triangle t; -1 when the pair is skipped (p a corner of t,
    or the same body without self contact)."""
    i = tri[3 * t]
    j = tri[3 * t + 1]
    k = tri[3 * t + 2]
    if i == p or j == p or k == p or (self_contact == 0 and body[i] == body[p]):
        return -1.0
    r, w = vertex_triangle_rel(x, q[i], q[j], q[k])
    return wp.length(r)


@wp.func
def edge_edge_distance(i: int, j: int, f: int, edges: wp.array(dtype=int), body: wp.array(dtype=int),
                       q: wp.array(dtype=wp.vec3), self_contact: int) -> float:
    """Distance [m] from edge ij to edge f; -1 when the pair is skipped (a shared particle, or the
    same body without self contact)."""
    k = edges[2 * f]
    m = edges[2 * f + 1]
    if i == k or i == m or j == k or j == m or (self_contact == 0 and body[i] == body[k]):
        return -1.0
    r, st = edge_edge_rel(q[i], q[j], q[k], q[m])
    return wp.length(r)


@wp.func
def keep_nearest(start: int, n: int, capacity: int, d: float, stored: int, list_io: wp.array(dtype=int),
                 distance_io: wp.array(dtype=float)) -> int:
    """Add pair ``stored`` at distance ``d`` [m] to the list at ``start`` holding ``n``: appended while
    there is room, else in place of the farthest (ties: the larger index) when nearer; returns n + 1
    (n + 1 > capacity: a pair was left out). The kept set does not depend on the order pairs come in."""
    if n < capacity:
        list_io[start + n] = stored
        distance_io[start + n] = d
        return n + 1
    worst = int(0)
    for k in range(1, capacity):
        a = start + k
        b = start + worst
        if distance_io[a] > distance_io[b] or (distance_io[a] == distance_io[b] and list_io[a] > list_io[b]):
            worst = k
    w = start + worst
    if d < distance_io[w] or (d == distance_io[w] and stored < list_io[w]):
        list_io[w] = stored
        distance_io[w] = d
    return n + 1


VERTEX_QUERY = wp.constant(0)
TRIANGLE_QUERY = wp.constant(1)
EDGE_QUERY = wp.constant(2)

WHOLE = wp.constant(0)  # query mode: every pair of the item, its own list (keep_nearest)
HALF = wp.constant(1)  # every pair once, from the item of the lower body (or index), staged into both lists
FINISH = wp.constant(2)  # the staged list when it holds every pair (sorted), else the WHOLE query


@wp.func
def corner_cap(kind: int, item: int, surface: wp.array(dtype=int), tri: wp.array(dtype=int),
               edges: wp.array(dtype=int), cap: wp.array(dtype=float)) -> float:
    """The largest cap [m] (``displacement_caps``) over the particles of primitive ``item``: a surface vertex, a
    triangle or an edge by ``kind``. Every point of the primitive moves at most that far between two searches."""
    if kind == VERTEX_QUERY:
        return cap[surface[item]]
    if kind == EDGE_QUERY:
        return wp.max(cap[edges[2 * item]], cap[edges[2 * item + 1]])
    return wp.max(wp.max(cap[tri[3 * item]], cap[tri[3 * item + 1]]), cap[tri[3 * item + 2]])


@wp.func
def pair_radius(thickness: float, cap_a: float, cap_b: float) -> float:
    """Query radius [m] of a pair whose sides' caps are ``cap_a`` and ``cap_b``: r_c + C_a + C_b, summed in
    the same order from either side (so both sides' queries list the same pairs, bit for bit)."""
    return thickness + wp.max(cap_a, cap_b) + wp.min(cap_a, cap_b)


@wp.func
def guessed_share(v: wp.vec3, v_prev: wp.vec3, a: wp.vec3, h: float, adaptive: int) -> float:
    """The share s in [0, 1] of the external acceleration ``a`` [m/s^2] VBD's adaptive initial guess takes: the part
    of it the particle took in its last step, (v - v_prev) / h . a / |a|^2 clamped (0 resting on a support, 1
    falling; 0 when a = 0); 1 when ``adaptive`` is 0 (``kernels.vbd.predict``, ``displacement_caps``)."""
    if adaptive == 0:
        return 1.0
    a2 = wp.dot(a, a)
    if a2 > 0.0:
        return wp.clamp(wp.dot((v - v_prev) / h, a) / a2, 0.0, 1.0)
    return 0.0


@wp.kernel
def displacement_caps(go: wp.array(dtype=int), body: wp.array(dtype=int), body_world: wp.array(dtype=int),
                      qd: wp.array(dtype=wp.vec3), qd_prev: wp.array(dtype=wp.vec3), f_ext: wp.array(dtype=wp.vec3),
                      inv_mass: wp.array(dtype=float), deficit: wp.array(dtype=wp.vec3), h: float, adaptive: int,
                      safety: float, lowest: float, highest: float, cap_out: wp.array(dtype=float)):
    """Particle p's cap C_p [m] for the search about to run, the most it may move before the next:
    ``safety`` x the length of its initial guess's step (|v| h + s |f / m| h^2, velocity [m/s] and the forces
    other than the springs [N] at the step's start, step h [s], s the share of the external acceleration the
    particle took in its last step, as ``kernels.vbd.predict`` guesses it: 0 at rest on a support, 1 falling;
    ``adaptive`` 0: s = 1) plus what the bound cut from its initial guess (``deficit`` [m]), within [``lowest``,
    ``highest``]. Nothing when ``go[w]`` is 0 for p's world w (its lists, built with the caps it has, stay)."""
    p = wp.tid()
    if go[body_world[body[p]]] == 0:
        return
    a = f_ext[p] * inv_mass[p]
    s = guessed_share(qd[p], qd_prev[p], a, h, adaptive)
    step = wp.length(qd[p]) * h + s * wp.length(a) * h * h
    cap_out[p] = wp.clamp(safety * step + wp.length(deficit[p]), lowest, highest)


@wp.kernel
def capped_boxes(surface: wp.array(dtype=int), tri: wp.array(dtype=int), edges: wp.array(dtype=int),
                 q: wp.array(dtype=wp.vec3), cap: wp.array(dtype=float),
                 tri_lower_out: wp.array(dtype=wp.vec3), tri_upper_out: wp.array(dtype=wp.vec3),
                 point_lower_out: wp.array(dtype=wp.vec3), point_upper_out: wp.array(dtype=wp.vec3),
                 edge_lower_out: wp.array(dtype=wp.vec3), edge_upper_out: wp.array(dtype=wp.vec3)):
    """The boxes [m] of the three BVHs at positions ``q``, each primitive's grown by its cap (``corner_cap``):
    triangle k for k < T, surface vertex k for k < V, edge k for k < E (launched over max(T, V, E))."""
    k = wp.tid()
    if k < tri_lower_out.shape[0]:
        a = q[tri[3 * k]]
        b = q[tri[3 * k + 1]]
        c = q[tri[3 * k + 2]]
        grow = wp.vec3(corner_cap(TRIANGLE_QUERY, k, surface, tri, edges, cap))
        tri_lower_out[k] = wp.min(wp.min(a, b), c) - grow
        tri_upper_out[k] = wp.max(wp.max(a, b), c) + grow
    if k < point_lower_out.shape[0]:
        x = q[surface[k]]
        grow = wp.vec3(cap[surface[k]])
        point_lower_out[k] = x - grow
        point_upper_out[k] = x + grow
    if k < edge_lower_out.shape[0]:
        a = q[edges[2 * k]]
        b = q[edges[2 * k + 1]]
        grow = wp.vec3(corner_cap(EDGE_QUERY, k, surface, tri, edges, cap))
        edge_lower_out[k] = wp.min(a, b) - grow
        edge_upper_out[k] = wp.max(a, b) + grow


@wp.kernel
def body_caps(surface: wp.array(dtype=int), body: wp.array(dtype=int), cap: wp.array(dtype=float),
              body_cap_io: wp.array(dtype=float)):
    """The largest cap [m] of each body's surface vertices (``body_cap_io`` zero before; a float atomic max:
    exact, order independent)."""
    s = wp.tid()
    p = surface[s]
    wp.atomic_max(body_cap_io, body[p], cap[p])


@wp.kernel
def grow_bodies(body_cap_io: wp.array(dtype=float), lowers_io: wp.array(dtype=wp.vec3),
                uppers_io: wp.array(dtype=wp.vec3)):
    """Grow body b's box [m] by its largest cap (``body_caps``), so that it holds every primitive's grown box
    (a primitive's cap is one of its body's), and zero that cap for the next search."""
    b = wp.tid()
    grow = wp.vec3(body_cap_io[b])
    lowers_io[b] = lowers_io[b] - grow
    uppers_io[b] = uppers_io[b] + grow
    body_cap_io[b] = 0.0


@wp.func
def query_box(kind: int, item: int, surface: wp.array(dtype=int), tri: wp.array(dtype=int),
              edges: wp.array(dtype=int), body: wp.array(dtype=int), q: wp.array(dtype=wp.vec3), pad: float):
    """(lower, upper, body) of query ``item``: a surface vertex, a triangle or an edge by ``kind``, its
    box grown by ``pad`` [m]."""
    lower = wp.vec3(1.0e30)
    upper = wp.vec3(-1.0e30)
    first = int(0)
    corners = int(3)
    if kind == VERTEX_QUERY:
        first = surface[item]
        corners = 1
    elif kind == EDGE_QUERY:
        first = edges[2 * item]
        corners = 2
    else:
        first = tri[3 * item]
    for c in range(corners):
        p = first
        if kind == TRIANGLE_QUERY:
            p = tri[3 * item + c]
        elif kind == EDGE_QUERY:
            p = edges[2 * item + c]
        lower = wp.min(lower, q[p])
        upper = wp.max(upper, q[p])
    return lower - wp.vec3(pad), upper + wp.vec3(pad), body[first]


@wp.func
def query_pair(kind: int, item: int, other: int, surface: wp.array(dtype=int), tri: wp.array(dtype=int),
               edges: wp.array(dtype=int), body: wp.array(dtype=int), q: wp.array(dtype=wp.vec3),
               self_contact: int):
    """(distance [m] or -1 when skipped, what the list stores) of query ``item`` and BVH item ``other``:
    vertex against triangle (stores the triangle), triangle against vertex (the vertex's particle), edge
    against edge (the edge)."""
    if kind == VERTEX_QUERY:
        p = surface[item]
        return vertex_triangle_distance(p, q[p], other, tri, body, q, self_contact), other
    if kind == TRIANGLE_QUERY:
        p = surface[other]
        return vertex_triangle_distance(p, q[p], item, tri, body, q, self_contact), p
    return edge_edge_distance(edges[2 * item], edges[2 * item + 1], other, edges, body, q, self_contact), other


@wp.func
def stage_pair(index: int, stored: int, d: float, capacity: int, list_io: wp.array(dtype=int),
               distance_io: wp.array(dtype=float), count_io: wp.array(dtype=int)):
    """Put pair ``stored`` at distance ``d`` [m] into list ``index``'s next slot (an integer atomic: the slots'
    order depends on the threads', the ``FINISH`` pass sorts them); past ``capacity`` only counted."""
    slot = wp.atomic_add(count_io, index, 1)
    if slot < capacity:
        list_io[index * capacity + slot] = stored
        distance_io[index * capacity + slot] = d


@wp.kernel
def query_pairs(
    go: wp.array(dtype=int), kind: int, mode: int, body_bvh: wp.uint64, world_roots: wp.array(dtype=int),
    body_world: wp.array(dtype=int),
    bvh: wp.uint64, roots: wp.array(dtype=int),
    surface: wp.array(dtype=int), tri: wp.array(dtype=int), edges: wp.array(dtype=int), body: wp.array(dtype=int),
    q: wp.array(dtype=wp.vec3), thickness: float, cap: wp.array(dtype=float), self_contact: int, capacity: int,
    list_out: wp.array(dtype=int), distance_out: wp.array(dtype=float), count_out: wp.array(dtype=int),
    min_out: wp.array(dtype=float), overflow_io: wp.array(dtype=int), mirror: int,
    mirror_list_io: wp.array(dtype=int), mirror_distance_io: wp.array(dtype=float),
    mirror_count_io: wp.array(dtype=int),
):
    """Pairs of query ``item`` within their radius r_c + C_a + C_b [m] (``pair_radius``: ``thickness`` and the
    two sides' caps, ``corner_cap``; the query's box grown by r_c + C_a, the BVH's boxes by their own caps,
    ``capped_boxes``) (``kind``: surface vertices against the triangle BVH, triangles against the vertex BVH,
    edges against the edge BVH), listed in ``list_out[item capacity ..]`` (the ``capacity`` nearest,
    ``keep_nearest``) in ascending order, their count, and the smallest distance of those pairs (1e30 when there
    are none). A query with more pairs than ``capacity``
    adds 1 to ``overflow_io[kind]`` and raises ``overflow_io[3 + kind]`` to its number of pairs (both zeroed
    before the search: they count queries of one search, never pairs over many, so they cannot wrap). Two
    levels: the bodies of the query's world whose bounds meet the box
    (``collect_bodies`` from the world's root of the body BVH), then each one's subtree of the grouped BVH.

    The other side of each pair found (``mirror`` 1: the triangle's side of a vertex's pair, the other edge's
    side of an edge's pair, its distance computed as that side's query computes it) is staged into the mirror
    lists (``stage_pair``; their counts zeroed before). ``mode`` ``HALF`` (edges) meets each pair once, from the
    edge of the lower body (within one body, the lower edge), and stages both sides; ``FINISH`` then takes a
    list that holds every pair of its item (count at most ``capacity``: the pairs, and so the sorted list and
    the smallest distance, of the ``WHOLE`` query, bit for bit) and queries the rest whole. Nothing when
    ``go[w]`` is 0 for the item's world w (its search skipped: ``search_needed``)."""
    item = wp.tid()
    own_cap = corner_cap(kind, item, surface, tri, edges, cap)
    lower, upper, own = query_box(kind, item, surface, tri, edges, body, q, thickness + own_cap)
    if go[body_world[own]] == 0:
        return
    other_kind = wp.where(kind == VERTEX_QUERY, TRIANGLE_QUERY, wp.where(kind == TRIANGLE_QUERY, VERTEX_QUERY,
                                                                           EDGE_QUERY))
    n = int(0)
    total = int(0)
    dmin = float(1.0e30)
    search = int(1)
    if mode == FINISH and count_out[item] <= capacity:
        n = count_out[item]
        for k in range(n):
            dmin = wp.min(dmin, distance_out[item * capacity + k])
        search = 0
    seen = int(0)
    more = search
    while more == 1:
        found, count = collect_bodies(body_bvh, world_roots[body_world[own]], lower, upper, own, self_contact,
                                      seen)
        seen += count
        more = wp.where(count == BODY_BATCH, 1, 0)
        for g in range(count):
            if mode == HALF and found[g] < own:
                continue
            query = wp.bvh_query_aabb(bvh, lower, upper, roots[found[g]])
            other = int(0)
            while wp.bvh_query_next(query, other):
                if mode == HALF and found[g] == own and other < item:
                    continue
                d, stored = query_pair(kind, item, other, surface, tri, edges, body, q, self_contact)
                if d < 0.0:
                    continue
                radius = pair_radius(thickness, own_cap, corner_cap(other_kind, other, surface, tri, edges, cap))
                if d < radius:
                    if mode == HALF:
                        stage_pair(item, stored, d, capacity, list_out, distance_out, count_out)
                    else:
                        dmin = wp.min(dmin, d)
                        n = wp.min(keep_nearest(item * capacity, n, capacity, d, stored, list_out, distance_out),
                                   capacity)
                        total += 1
                if mirror == 1:
                    if kind == VERTEX_QUERY:
                        if d < radius:
                            stage_pair(other, surface[item], d, capacity, mirror_list_io, mirror_distance_io,
                                       mirror_count_io)
                    else:
                        d2, stored2 = query_pair(kind, other, item, surface, tri, edges, body, q, self_contact)
                        if d2 >= 0.0 and d2 < radius:
                            stage_pair(other, item, d2, capacity, mirror_list_io, mirror_distance_io,
                                       mirror_count_io)
    if mode == HALF:
        return
    if total > capacity:
        wp.atomic_add(overflow_io, kind, 1)
        wp.atomic_max(overflow_io, 3 + kind, total)
    # ascending order: the list (and the sums over it) does not depend on the BVH's traversal order, so a
    # world of a sweep (one BVH for all worlds) gets the bits of the same scene run alone
    for a in range(1, n):
        value = list_out[item * capacity + a]
        distance = distance_out[item * capacity + a]
        b = a - 1
        while b >= 0 and list_out[item * capacity + b] > value:
            list_out[item * capacity + b + 1] = list_out[item * capacity + b]
            distance_out[item * capacity + b + 1] = distance_out[item * capacity + b]
            b -= 1
        list_out[item * capacity + b + 1] = value
        distance_out[item * capacity + b + 1] = distance
    count_out[item] = n
    min_out[item] = dmin


@wp.kernel
def search_needed(q: wp.array(dtype=wp.vec3), reference: wp.array(dtype=wp.vec3), bound: wp.array(dtype=float),
                  deficit: wp.array(dtype=wp.vec3), fraction: float, body: wp.array(dtype=int),
                  body_world: wp.array(dtype=int), go_out: wp.array(dtype=int)):
    """``go_out[w]`` = 1 (zeroed before) for particle i's world w when i has moved more than ``fraction`` of its bound [m] from
    its reference [m] since the last search, or still has some of its initial guess cut (``deficit`` [m], not
    zero): a search within the step would then let it move on; else the search is skipped (every particle
    far inside its bound: the lists and bounds of the last search still hold, ``warpsim.bodies.vbd``). Per
    world, so that a world of a sweep searches when its scene run alone would (the same bits)."""
    i = wp.tid()
    if wp.length(q[i] - reference[i]) > fraction * bound[i] or wp.length(deficit[i]) > 0.0:
        go_out[body_world[body[i]]] = 1  # every thread that writes writes 1: no atomic needed


@wp.kernel
def begin_search(go: wp.array(dtype=int), tri: wp.array(dtype=int), edges: wp.array(dtype=int),
                 body: wp.array(dtype=int), body_world: wp.array(dtype=int), tri_count_out: wp.array(dtype=int),
                 edge_count_out: wp.array(dtype=int), overflow_out: wp.array(dtype=int),
                 searches_io: wp.array(dtype=int)):
    """Zero the list counts of the triangles and edges of each world that searches (``go[w]`` not 0: the queries
    stage into them) and, when any world searches, the overflow counters, and count the worlds' searches
    (``searches_io[0]``); launched over max(T, E) threads."""
    k = wp.tid()
    if k < tri_count_out.shape[0]:
        if go[body_world[body[tri[3 * k]]]] != 0:
            tri_count_out[k] = 0
    if k < edge_count_out.shape[0]:
        if go[body_world[body[edges[2 * k]]]] != 0:
            edge_count_out[k] = 0
    if k == 0:
        worlds = int(0)
        for w in range(go.shape[0]):
            if go[w] != 0:
                worlds += 1
        if worlds > 0:
            for m in range(overflow_out.shape[0]):
                overflow_out[m] = 0
        searches_io[0] = searches_io[0] + worlds


@wp.func
def sphere_gap(sphere: wp.vec4, x: wp.vec3):
    """(distance [m] of x outside the static sphere (centre, radius) = sphere, outward normal)."""
    r = x - wp.vec3(sphere[0], sphere[1], sphere[2])
    length = wp.length(r)
    n = wp.vec3(0.0, 1.0, 0.0)
    if length > 1.0e-12:
        n = r / length
    return length - sphere[3], n


@wp.kernel
def displacement_bounds(
    go: wp.array(dtype=int), body: wp.array(dtype=int), body_world: wp.array(dtype=int), q: wp.array(dtype=wp.vec3),
    slot: wp.array(dtype=int), vertex_min: wp.array(dtype=float),
    tri_offsets: wp.array(dtype=int), tris: wp.array(dtype=int), tri_min: wp.array(dtype=float),
    edge_offsets: wp.array(dtype=int), edge_list: wp.array(dtype=int), edge_min: wp.array(dtype=float),
    planes: wp.array(dtype=wp.vec4), spheres: wp.array(dtype=wp.vec4), fraction: float, cap: wp.array(dtype=float),
    reference_out: wp.array(dtype=wp.vec3), bound_out: wp.array(dtype=float),
):
    """Particle p's step bound [m]: ``fraction`` x the smallest distance from p's primitives (the
    vertex, its triangles, its edges) to any non-incident primitive the queries listed, or to a
    plane or a sphere (static), at most its cap (``cap`` [m], ``displacement_caps``); and its reference position
    (now). Nothing
    when ``go[w]`` is 0 for p's world w."""
    p = wp.tid()
    if go[body_world[body[p]]] == 0:
        return
    x = q[p]
    dmin = cap[p] / fraction
    s = slot[p]
    if s >= 0:
        dmin = wp.min(dmin, vertex_min[s])
        for k in range(tri_offsets[p], tri_offsets[p + 1]):
            dmin = wp.min(dmin, tri_min[tris[k]])
        for k in range(edge_offsets[p], edge_offsets[p + 1]):
            dmin = wp.min(dmin, edge_min[edge_list[k]])
    for k in range(planes.shape[0]):
        plane = planes[k]
        dmin = wp.min(dmin, wp.max(wp.dot(wp.vec3(plane[0], plane[1], plane[2]), x) - plane[3], 0.0))
    for k in range(spheres.shape[0]):
        gap, normal = sphere_gap(spheres[k], x)
        dmin = wp.min(dmin, wp.max(gap, 0.0))
    reference_out[p] = x
    bound_out[p] = fraction * dmin


@wp.func
def vertex_triangle_pair(x: wp.vec3, dx: wp.vec3, t: int, q: wp.array(dtype=wp.vec3), q0: wp.array(dtype=wp.vec3),
                         tri: wp.array(dtype=int), radius: float, stiffness: float, friction: float,
                         friction_eps: float):
    """Force [N] and Hessian block [N/m] on a vertex at ``x`` (step displacement ``dx`` [m]) from its pair
    with triangle t (the vertex's side); zero when the bounding spheres are apart."""
    i = tri[3 * t]
    j = tri[3 * t + 1]
    k = tri[3 * t + 2]
    centre, extent = triangle_sphere(q[i], q[j], q[k])
    if spheres_apart(x, 0.0, centre, extent, radius):
        return wp.vec3(), wp.mat33()
    r, w = vertex_triangle_rel(x, q[i], q[j], q[k])
    u = dx - (w[0] * (q[i] - q0[i]) + w[1] * (q[j] - q0[j]) + w[2] * (q[k] - q0[k]))
    return pair_force_hessian(r, u, 1.0, radius, stiffness, friction, friction_eps)


@wp.func
def corner_triangle(p: int, x: wp.vec3, t: int, q: wp.array(dtype=wp.vec3), q0: wp.array(dtype=wp.vec3),
                    tri: wp.array(dtype=int)):
    """Triangle t with its corner p at ``x``: (corners [m] as rows, their step displacements [m], bounding
    sphere centre [m] and radius [m], which corner p is)."""
    corner = int(0)
    if tri[3 * t + 1] == p:
        corner = 1
    elif tri[3 * t + 2] == p:
        corner = 2
    xs = wp.mat33()
    ds = wp.mat33()
    for m in range(3):
        v = tri[3 * t + m]
        xv = q[v]
        if v == p:
            xv = x
        xs[m] = xv
        ds[m] = xv - q0[v]
    centre, extent = triangle_sphere(xs[0], xs[1], xs[2])
    return xs, ds, centre, extent, corner


@wp.func
def triangle_vertex_pair(xs: wp.mat33, ds: wp.mat33, centre: wp.vec3, extent: float, corner: int, v: int,
                         q: wp.array(dtype=wp.vec3), q0: wp.array(dtype=wp.vec3), radius: float, stiffness: float,
                         friction: float, friction_eps: float):
    """Force [N] and Hessian block [N/m] on corner ``corner`` of a triangle (``corner_triangle``) from its
    pair with vertex v (the triangle's side); zero when the bounding spheres are apart."""
    if spheres_apart(q[v], 0.0, centre, extent, radius):
        return wp.vec3(), wp.mat33()
    r, w = vertex_triangle_rel(q[v], xs[0], xs[1], xs[2])
    u = (q[v] - q0[v]) - (w[0] * ds[0] + w[1] * ds[1] + w[2] * ds[2])
    return pair_force_hessian(r, u, -w[corner], radius, stiffness, friction, friction_eps)


@wp.func
def edge_with(p: int, x: wp.vec3, e: int, q: wp.array(dtype=wp.vec3), q0: wp.array(dtype=wp.vec3),
              edges: wp.array(dtype=int)):
    """Edge e with its end p at ``x``: (ends [m] as rows 0 and 1, their step displacements [m] as rows,
    bounding sphere centre [m] and radius [m], 1 when p is the first end else 0)."""
    i = edges[2 * e]
    j = edges[2 * e + 1]
    xi = q[i]
    xj = q[j]
    if i == p:
        xi = x
    else:
        xj = x
    xs = wp.matrix_from_rows(xi, xj, wp.vec3())
    ds = wp.matrix_from_rows(xi - q0[i], xj - q0[j], wp.vec3())
    return xs, ds, 0.5 * (xi + xj), 0.5 * wp.length(xj - xi), wp.where(i == p, 1, 0)


@wp.func
def edge_edge_pair(xs: wp.mat33, ds: wp.mat33, centre: wp.vec3, extent: float, first: int, g: int,
                   q: wp.array(dtype=wp.vec3), q0: wp.array(dtype=wp.vec3), edges: wp.array(dtype=int), radius: float,
                   stiffness: float, friction: float, friction_eps: float):
    """Force [N] and Hessian block [N/m] on an end of an edge (``edge_with``) from its pair with edge g;
    zero when the bounding spheres are apart."""
    k = edges[2 * g]
    m = edges[2 * g + 1]
    if spheres_apart(centre, extent, 0.5 * (q[k] + q[m]), 0.5 * wp.length(q[m] - q[k]), radius):
        return wp.vec3(), wp.mat33()
    r, st = edge_edge_rel(xs[0], xs[1], q[k], q[m])
    u = (1.0 - st[0]) * ds[0] + st[0] * ds[1] - (1.0 - st[1]) * (q[k] - q0[k]) - st[1] * (q[m] - q0[m])
    weight = wp.where(first == 1, 1.0 - st[0], st[0])
    return pair_force_hessian(r, u, weight, radius, stiffness, friction, friction_eps)


@wp.kernel
def keep_near_pairs(
    go: wp.array(dtype=int), body: wp.array(dtype=int), body_world: wp.array(dtype=int), surface: wp.array(dtype=int),
    tri: wp.array(dtype=int), edges: wp.array(dtype=int), capacity: int,
    vt_list: wp.array(dtype=int), vt_distance: wp.array(dtype=float), vt_count: wp.array(dtype=int),
    tri_offsets: wp.array(dtype=int), tris: wp.array(dtype=int), tv_list: wp.array(dtype=int),
    tv_distance: wp.array(dtype=float), tv_count: wp.array(dtype=int),
    edge_offsets: wp.array(dtype=int), edge_list: wp.array(dtype=int), ee_list: wp.array(dtype=int),
    ee_distance: wp.array(dtype=float), ee_count: wp.array(dtype=int),
    reference: wp.array(dtype=wp.vec3), bound: wp.array(dtype=float), radius: float, near_capacity: int,
    near_out: wp.array(dtype=int), near_end_out: wp.array(dtype=int),
):
    """After a search, for surface vertex s (particle p): the positions in the three lists of the pairs
    that can still push on p before the next search, in the gather's order (p's vertex-triangle pairs, its
    triangles' pairs, its edges' pairs), into ``near_out[s near_capacity ..]``, and where each of the three
    parts ends in ``near_end_out[3 s ..]`` (-1 first when more than ``near_capacity``: the gather then walks
    the whole lists).

    A pair at distance D [m] at the search, its two sides within bounds b_a and b_b of where they were
    (every point of a side is a convex combination of its corners: b = the largest corner bound), is at
    least D - b_a - b_b apart until the next search; at ``radius`` or more it exerts nothing, so leaving it
    out changes no bit. Left out only with a slack of 1e-3 ``radius`` + 1e-5 |x_p| beyond that (far more than
    the rounding of the distances), so a pair the gather would find inside the radius is always kept. Nothing
    when ``go[w]`` is 0 for p's world w."""
    s = wp.tid()
    p = surface[s]
    if go[body_world[body[p]]] == 0:
        return
    reach = radius + 1.0e-3 * radius + 1.0e-5 * wp.length(reference[p])
    bp = bound[p]
    base = s * near_capacity
    n = int(0)
    for k in range(vt_count[s]):
        a = s * capacity + k
        t = vt_list[a]
        far = wp.max(wp.max(bound[tri[3 * t]], bound[tri[3 * t + 1]]), bound[tri[3 * t + 2]])
        if vt_distance[a] - bp - far < reach:
            if n < near_capacity:
                near_out[base + n] = a
            n += 1
    near_end_out[3 * s] = n
    for c in range(tri_offsets[p], tri_offsets[p + 1]):
        t = tris[c]
        own = wp.max(wp.max(bound[tri[3 * t]], bound[tri[3 * t + 1]]), bound[tri[3 * t + 2]])
        for k in range(tv_count[t]):
            a = t * capacity + k
            if tv_distance[a] - own - bound[tv_list[a]] < reach:
                if n < near_capacity:
                    near_out[base + n] = a
                n += 1
    near_end_out[3 * s + 1] = n
    for c in range(edge_offsets[p], edge_offsets[p + 1]):
        e = edge_list[c]
        own = wp.max(bound[edges[2 * e]], bound[edges[2 * e + 1]])
        for k in range(ee_count[e]):
            a = e * capacity + k
            g = ee_list[a]
            if ee_distance[a] - own - wp.max(bound[edges[2 * g]], bound[edges[2 * g + 1]]) < reach:
                if n < near_capacity:
                    near_out[base + n] = a
                n += 1
    near_end_out[3 * s + 2] = n
    if n > near_capacity:
        near_end_out[3 * s] = -1


@wp.func
def moved(p: int, x: wp.vec3, v: int, q: wp.array(dtype=wp.vec3), reference: wp.array(dtype=wp.vec3)) -> float:
    """How far [m] particle v (at ``x`` when it is p) is from its reference (its position at the search)."""
    return wp.length(wp.where(v == p, x, q[v]) - reference[v])


@wp.func
def still_apart(room: float, v: int, q: wp.array(dtype=wp.vec3), reference: wp.array(dtype=wp.vec3)) -> bool:
    """Whether particle v has moved less than ``room`` [m] (> 0) from its reference (its position at the
    search): a side of a pair whose corners all have keeps the pair out of reach (``contact_force_hessian``)."""
    return room > 0.0 and wp.length_sq(q[v] - reference[v]) < room * room


@wp.func
def lane_start(begin: int, lane: int, lanes: int) -> int:
    """The first index at or after ``begin`` that lane ``lane`` of ``lanes`` takes when indices 0, 1, 2, ... are
    dealt to the lanes in turn (index i to lane i mod ``lanes``): ``begin`` itself when ``lanes`` is 1."""
    return begin + (lane + lanes - begin % lanes) % lanes


@wp.func
def same_colour(colour: wp.array(dtype=int), own: int, a: int, b: int, c: int) -> float:
    """1 + how many of particles a, b, c have colour ``own``: the pair's Hessian block is scaled by it
    (``contact_force_hessian``)."""
    return 1.0 + wp.where(colour[a] == own, 1.0, 0.0) + wp.where(colour[b] == own, 1.0, 0.0) + wp.where(
        colour[c] == own, 1.0, 0.0)


@wp.func
def contact_force_hessian(
    p: int, x: wp.vec3, lane: int, lanes: int, q: wp.array(dtype=wp.vec3), q0: wp.array(dtype=wp.vec3),
    slot: wp.array(dtype=int),
    tri: wp.array(dtype=int), edges: wp.array(dtype=int), capacity: int,
    vt_list: wp.array(dtype=int), vt_count: wp.array(dtype=int),
    tri_offsets: wp.array(dtype=int), tris: wp.array(dtype=int), tv_list: wp.array(dtype=int),
    tv_count: wp.array(dtype=int),
    edge_offsets: wp.array(dtype=int), edge_list: wp.array(dtype=int), ee_list: wp.array(dtype=int),
    ee_count: wp.array(dtype=int), near: wp.array(dtype=int), near_end: wp.array(dtype=int), near_capacity: int,
    vt_distance: wp.array(dtype=float), tv_distance: wp.array(dtype=float), ee_distance: wp.array(dtype=float),
    planes: wp.array(dtype=wp.vec4), spheres: wp.array(dtype=wp.vec4), radius: float, stiffness: float,
    friction: float, friction_eps: float, reference: wp.array(dtype=wp.vec3), colour: wp.array(dtype=int),
):
    """Sum of the contact forces [N] and Hessian blocks [N/m] on particle p at position ``x`` (the
    other particles at ``q``; ``q0`` the step's start): its vertex-triangle pairs as the vertex
    and as a triangle corner, its edges' edge-edge pairs, the planes and spheres; fixed order. Lane ``lane``
    of ``lanes`` (``kernels.vbd.solve_colour_lanes``) sums every ``lanes``-th of the pairs, counted in that
    order from 0 (``lane_start``: pair i to lane i mod ``lanes``), and of the planes, then of the spheres, each
    counted from 0; lane 0 of 1 sums them all. The pairs
    are those ``keep_near_pairs`` kept for p (the same sums: the pairs left out add nothing), or every
    listed pair where p's kept pairs did not fit. A kept pair at distance D [m] at the search whose two sides
    have moved by less than D - ``radius`` (each side: its largest corner displacement from ``reference``,
    the positions of the search) is still farther apart than ``radius`` and adds nothing: skipped before its
    nearest points (``still_apart``; the same slack as ``keep_near_pairs``), so the sums keep their bits. Each
    pair's Hessian block is scaled by 1 + the number of the pair's other particles of p's colour (``colour``,
    ``same_colour``: they are solved at the same time as p, ``kernels.vbd``'s docstring); planes and spheres are
    static."""
    f = wp.vec3()
    H = wp.mat33()
    s = slot[p]
    if s >= 0:
        dx = x - q0[p]
        own_colour = colour[p]
        if near_end[3 * s] >= 0:
            base = s * near_capacity
            reach = radius + 1.0e-3 * radius + 1.0e-5 * wp.length(reference[p])
            own = wp.length(x - reference[p])
            for k in range(lane_start(0, lane, lanes), near_end[3 * s], lanes):
                a = near[base + k]
                t = vt_list[a]
                room = vt_distance[a] - own - reach
                if still_apart(room, tri[3 * t], q, reference) and still_apart(room, tri[3 * t + 1], q, reference):
                    if still_apart(room, tri[3 * t + 2], q, reference):
                        continue
                fc, Hc = vertex_triangle_pair(x, dx, t, q, q0, tri, radius, stiffness, friction, friction_eps)
                f += fc
                H += same_colour(colour, own_colour, tri[3 * t], tri[3 * t + 1], tri[3 * t + 2]) * Hc
            xs = wp.mat33()
            ds = wp.mat33()
            centre = wp.vec3()
            extent = float(0.0)
            corner = int(0)
            built = int(-1)
            t = int(-1)
            lo = -1 - capacity  # t's pairs are at [lo, lo + capacity) of the lists
            for k in range(lane_start(near_end[3 * s], lane, lanes), near_end[3 * s + 1], lanes):
                a = near[base + k]
                if a < lo or a >= lo + capacity:  # a triangle's pairs come together: one division a triangle
                    t = a // capacity
                    lo = t * capacity
                    own = wp.max(wp.max(moved(p, x, tri[3 * t], q, reference),
                                        moved(p, x, tri[3 * t + 1], q, reference)),
                                 moved(p, x, tri[3 * t + 2], q, reference))
                if still_apart(tv_distance[a] - own - reach, tv_list[a], q, reference):
                    continue
                if t != built:  # the triangle's corners only for a pair that is not skipped
                    xs, ds, centre, extent, corner = corner_triangle(p, x, t, q, q0, tri)
                    built = t
                fc, Hc = triangle_vertex_pair(xs, ds, centre, extent, corner, tv_list[a], q, q0, radius, stiffness,
                                              friction, friction_eps)
                f += fc
                H += same_colour(colour, own_colour, tv_list[a], tri[3 * t + (corner + 1) % 3],
                                 tri[3 * t + (corner + 2) % 3]) * Hc
            built = int(-1)
            e = int(-1)
            lo = -1 - capacity
            for k in range(lane_start(near_end[3 * s + 1], lane, lanes), near_end[3 * s + 2], lanes):
                a = near[base + k]
                if a < lo or a >= lo + capacity:
                    e = a // capacity
                    lo = e * capacity
                    own = wp.max(moved(p, x, edges[2 * e], q, reference), moved(p, x, edges[2 * e + 1], q, reference))
                g = ee_list[a]
                room = ee_distance[a] - own - reach
                if still_apart(room, edges[2 * g], q, reference) and still_apart(room, edges[2 * g + 1], q, reference):
                    continue
                if e != built:
                    xs, ds, centre, extent, corner = edge_with(p, x, e, q, q0, edges)
                    built = e
                fc, Hc = edge_edge_pair(xs, ds, centre, extent, corner, g, q, q0, edges, radius, stiffness,
                                        friction, friction_eps)
                f += fc
                H += same_colour(colour, own_colour, edges[2 * e + corner], edges[2 * g], edges[2 * g + 1]) * Hc
        else:
            done = vt_count[s]  # entries dealt so far (lane_start)
            for n in range(lane, vt_count[s], lanes):
                t = vt_list[s * capacity + n]
                fc, Hc = vertex_triangle_pair(x, dx, t, q, q0, tri, radius, stiffness, friction, friction_eps)
                f += fc
                H += same_colour(colour, own_colour, tri[3 * t], tri[3 * t + 1], tri[3 * t + 2]) * Hc
            for a in range(tri_offsets[p], tri_offsets[p + 1]):
                t = tris[a]
                first = lane_start(done, lane, lanes) - done
                if first < tv_count[t]:  # the triangle's corners only for a lane with one of its pairs
                    xs, ds, centre, extent, corner = corner_triangle(p, x, t, q, q0, tri)
                    for n in range(first, tv_count[t], lanes):
                        v = tv_list[t * capacity + n]
                        fc, Hc = triangle_vertex_pair(xs, ds, centre, extent, corner, v, q, q0, radius, stiffness,
                                                      friction, friction_eps)
                        f += fc
                        H += same_colour(colour, own_colour, v, tri[3 * t + (corner + 1) % 3],
                                         tri[3 * t + (corner + 2) % 3]) * Hc
                done += tv_count[t]
            for a in range(edge_offsets[p], edge_offsets[p + 1]):
                e = edge_list[a]
                first = lane_start(done, lane, lanes) - done
                if first < ee_count[e]:
                    xs, ds, centre, extent, end = edge_with(p, x, e, q, q0, edges)
                    for n in range(first, ee_count[e], lanes):
                        g = ee_list[e * capacity + n]
                        fc, Hc = edge_edge_pair(xs, ds, centre, extent, end, g, q, q0, edges, radius, stiffness,
                                                friction, friction_eps)
                        f += fc
                        H += same_colour(colour, own_colour, edges[2 * e + end], edges[2 * g], edges[2 * g + 1]) * Hc
                done += ee_count[e]
    for k in range(lane, planes.shape[0], lanes):
        plane = planes[k]
        normal = wp.vec3(plane[0], plane[1], plane[2])
        d = wp.max(wp.dot(normal, x) - plane[3], 1.0e-9)
        fc, Hc = pair_force_hessian(d * normal, x - q0[p], 1.0, radius, stiffness, friction, friction_eps)
        f += fc
        H += Hc
    for k in range(lane, spheres.shape[0], lanes):
        gap, normal = sphere_gap(spheres[k], x)
        fc, Hc = pair_force_hessian(wp.max(gap, 1.0e-9) * normal, x - q0[p], 1.0, radius, stiffness, friction,
                                    friction_eps)
        f += fc
        H += Hc
    return f, H
