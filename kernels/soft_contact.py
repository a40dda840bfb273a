"""Soft-body contact kernels: vertices of one body against the triangles of another (or of itself).

Per step (``warpsim.bodies.soft_contact.SoftContact`` launches them after integration):

1. ``find_soft_contacts``: every contact vertex p queries the triangle BVHs of the other bodies
   (one ``wp.Mesh`` per body, refitted every step; its own too with self contact) within
   ``search`` [m] and keeps the nearest triangle (never one that touches p or, on its own body,
   lies within ``self_rest_distance`` of it in the rest pose). One BVH per body keeps a vertex's
   own neighbourhood out of its queries (one BVH over all bodies was measured 27x slower on
   the CPU, 53.6 against 1.96 ms for four separate tori of 2,000 vertices: every query walked
   its own body's nearby triangles). With c the closest
   point (barycentrics b) and n_f the outward face normal, the signed distance is
   s = |p - c| in front of the face and -|p - c| behind it (only when p lies right behind the
   face: c inside the triangle); a contact has -search < s < thickness, normal n = (p - c)/|p - c|
   in front, n_f behind, depth thickness - s. Every particle counts the contacts it takes part in.
2. ``push_soft_contacts`` / ``impulse_soft_contacts``: the vertex and the triangle's three
   vertices (weights b) act as one two-body contact with inverse mass
   W = w_p + sum_k b_k^2 w_k. The position push removes the depth, the normal impulse
   J = -(1 + e) u_n / W stops the approach (u_n = (v_p - sum b_k v_k) . n < 0), Coulomb friction
   takes at most mu J of the slip. The vertex gets +w_p J and triangle vertex k gets -b_k w_k J,
   so sum m dv = 0: momentum is conserved exactly (pinned particles, w = 0, never move). Each
   contact is scaled by 1 / (largest contact count among its four particles), so a particle in
   several contacts receives a convex combination (Jacobi averaging; no overshoot). Deltas are
   summed with atomics into ``dx``/``dv`` and applied by ``apply_soft_contact_deltas``; the
   impulse pass is repeated ``iterations`` times on the updated velocities.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})


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
def rest_distance(p: int, t: int, tri: wp.array(dtype=int), rest: wp.array(dtype=wp.vec3)) -> float:
    """Distance from particle p to triangle t in the rest pose [m]."""
    a = rest[tri[3 * t]]
    b = rest[tri[3 * t + 1]]
    c = rest[tri[3 * t + 2]]
    x = rest[p]
    w = triangle_barycentric(x, a, b, c)
    return wp.length(x - (w[0] * a + w[1] * b + w[2] * c))


@wp.kernel
def find_soft_contacts(
    meshes: wp.array(dtype=wp.uint64),
    tri_start: wp.array(dtype=int),
    q: wp.array(dtype=wp.vec3),
    rest: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    tri: wp.array(dtype=int),
    vertex_particle: wp.array(dtype=int),
    vertex_body: wp.array(dtype=int),
    thickness: float,
    search: float,
    self_contact: int,
    self_rest_distance: float,
    contact_tri_out: wp.array(dtype=int),
    contact_bary_out: wp.array(dtype=wp.vec3),
    contact_normal_out: wp.array(dtype=wp.vec3),
    contact_depth_out: wp.array(dtype=float),
    particle_contacts_io: wp.array(dtype=int),
    contact_total_io: wp.array(dtype=int),
):
    """Nearest triangle contact of contact vertex v (module docstring, step 1); -1 when none."""
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
    best_s = float(0.0)
    for other in range(meshes.shape[0]):
        if other == body and self_contact == 0:
            continue
        query = wp.mesh_query_aabb(meshes[other], lower, upper)
        local = int(0)
        while wp.mesh_query_aabb_next(query, local):
            t = tri_start[other] + local
            i = tri[3 * t]
            j = tri[3 * t + 1]
            k = tri[3 * t + 2]
            if other == body:
                if i == p or j == p or k == p:
                    continue
                if rest_distance(p, t, tri, rest) < self_rest_distance:
                    continue
            w = inv_mass[p] + inv_mass[i] + inv_mass[j] + inv_mass[k]
            if w == 0.0:
                continue
            a = q[i]
            b = q[j]
            c = q[k]
            bary = triangle_barycentric(x, a, b, c)
            cp = bary[0] * a + bary[1] * b + bary[2] * c
            delta = x - cp
            d = wp.length(delta)
            nf = wp.cross(b - a, c - a)
            area2 = wp.length(nf)
            if area2 < 1.0e-20:
                continue
            nf = nf / area2
            side = wp.dot(delta, nf)
            s = d
            n = nf
            if side < 0.0:
                # behind the face: a contact only when p lies right behind it (closest point inside)
                if bary[0] <= 0.0 or bary[1] <= 0.0 or bary[2] <= 0.0:
                    continue
                s = -d
            elif d > 1.0e-9:
                n = delta / d
            if s >= thickness or s <= -search:
                continue
            if d < best_d:
                best_d = d
                best = t
                best_bary = bary
                best_normal = n
                best_s = s
    contact_tri_out[v] = best
    if best >= 0:
        contact_bary_out[v] = best_bary
        contact_normal_out[v] = best_normal
        contact_depth_out[v] = thickness - best_s
        wp.atomic_add(particle_contacts_io, p, 1)
        wp.atomic_add(particle_contacts_io, tri[3 * best], 1)
        wp.atomic_add(particle_contacts_io, tri[3 * best + 1], 1)
        wp.atomic_add(particle_contacts_io, tri[3 * best + 2], 1)
        wp.atomic_add(contact_total_io, 0, 1)


@wp.func
def contact_particles(v: int, t: int, tri: wp.array(dtype=int), vertex_particle: wp.array(dtype=int)):
    """(vertex particle, triangle particles i, j, k) of contact vertex v against triangle t."""
    return vertex_particle[v], tri[3 * t], tri[3 * t + 1], tri[3 * t + 2]


@wp.func
def contact_scale(p: int, i: int, j: int, k: int, counts: wp.array(dtype=int)) -> float:
    """1 / the largest contact count among the four particles of a contact."""
    m = wp.max(wp.max(counts[p], counts[i]), wp.max(counts[j], counts[k]))
    return 1.0 / float(wp.max(m, 1))


@wp.func
def scatter_contact(
    p: int, i: int, j: int, k: int, bary: wp.vec3, inv_mass: wp.array(dtype=float), delta: wp.vec3,
    out: wp.array(dtype=wp.vec3),
):
    """out[p] += w_p delta; out[k-th triangle vertex] -= b_k w_k delta (equal and opposite)."""
    wp.atomic_add(out, p, inv_mass[p] * delta)
    wp.atomic_sub(out, i, (bary[0] * inv_mass[i]) * delta)
    wp.atomic_sub(out, j, (bary[1] * inv_mass[j]) * delta)
    wp.atomic_sub(out, k, (bary[2] * inv_mass[k]) * delta)


@wp.func
def effective_inv_mass(p: int, i: int, j: int, k: int, bary: wp.vec3, inv_mass: wp.array(dtype=float)) -> float:
    return (inv_mass[p] + bary[0] * bary[0] * inv_mass[i] + bary[1] * bary[1] * inv_mass[j]
            + bary[2] * bary[2] * inv_mass[k])


@wp.kernel
def push_soft_contacts(
    inv_mass: wp.array(dtype=float),
    tri: wp.array(dtype=int),
    vertex_particle: wp.array(dtype=int),
    contact_tri: wp.array(dtype=int),
    contact_bary: wp.array(dtype=wp.vec3),
    contact_normal: wp.array(dtype=wp.vec3),
    contact_depth: wp.array(dtype=float),
    particle_contacts: wp.array(dtype=int),
    fraction: float,
    dx_io: wp.array(dtype=wp.vec3),
):
    """Position push removing ``fraction`` of each contact's depth along its normal (mass-weighted:
    the centre of mass does not move)."""
    v = wp.tid()
    t = contact_tri[v]
    if t < 0:
        return
    p, i, j, k = contact_particles(v, t, tri, vertex_particle)
    bary = contact_bary[v]
    W = effective_inv_mass(p, i, j, k, bary, inv_mass)
    if W <= 0.0:
        return
    push = (fraction * contact_scale(p, i, j, k, particle_contacts) * contact_depth[v] / W) * contact_normal[v]
    scatter_contact(p, i, j, k, bary, inv_mass, push, dx_io)


@wp.kernel
def impulse_soft_contacts(
    qd: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    tri: wp.array(dtype=int),
    vertex_particle: wp.array(dtype=int),
    contact_tri: wp.array(dtype=int),
    contact_bary: wp.array(dtype=wp.vec3),
    contact_normal: wp.array(dtype=wp.vec3),
    particle_contacts: wp.array(dtype=int),
    restitution: float,
    friction: float,
    dv_io: wp.array(dtype=wp.vec3),
):
    """Normal impulse with restitution and Coulomb friction per contact (module docstring)."""
    v = wp.tid()
    t = contact_tri[v]
    if t < 0:
        return
    p, i, j, k = contact_particles(v, t, tri, vertex_particle)
    bary = contact_bary[v]
    n = contact_normal[v]
    W = effective_inv_mass(p, i, j, k, bary, inv_mass)
    if W <= 0.0:
        return
    rel = qd[p] - (bary[0] * qd[i] + bary[1] * qd[j] + bary[2] * qd[k])
    un = wp.dot(rel, n)
    if un >= 0.0:
        return
    jn = -(1.0 + restitution) * un / W
    impulse = jn * n
    vt = rel - un * n
    vt_len = wp.length(vt)
    if vt_len > 0.0 and friction > 0.0:
        jt = wp.min(friction * jn, vt_len / W)
        impulse = impulse - (jt / vt_len) * vt
    scatter_contact(p, i, j, k, bary, inv_mass, contact_scale(p, i, j, k, particle_contacts) * impulse, dv_io)


@wp.kernel
def apply_soft_contact_deltas(
    dx_io: wp.array(dtype=wp.vec3),
    dv_io: wp.array(dtype=wp.vec3),
    q_io: wp.array(dtype=wp.vec3),
    qd_io: wp.array(dtype=wp.vec3),
):
    """q += dx, qd += dv, then clear both buffers."""
    i = wp.tid()
    q_io[i] = q_io[i] + dx_io[i]
    qd_io[i] = qd_io[i] + dv_io[i]
    dx_io[i] = wp.vec3()
    dv_io[i] = wp.vec3()
