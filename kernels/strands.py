"""Hair strand kernels: stretch and bending forces, kinematic roots, bending rest states.

A strand is a chain of ``stride = segments + 2`` consecutive particles starting at
``first + s * stride``: local vertex 0 is a *ghost* (inside the head, pinned), 1 the root on the
scalp (pinned), 2 .. segments + 1 the free hair vertices. Ghost and root move with the head, so
the ghost-root edge clamps the root direction.

Per strand vertex slot ``k = s * stride + v`` (shape (strand_count * stride,)):
  rest_length[k]: rest length [m] of the stretch spring (v, v + 1), used for v = 1 .. segments;
  bend_rest[k]: rest bending vector of the triple (v - 1, v, v + 1) in the vertex frame
      (v = 1 .. segments) [m].

Bending is linear in the second difference b = x[v-1] - 2 x[v] + x[v+1] [m]: energy
E = k_b / 2 |b - F c|^2, with c the rest bending vector expressed in the vertex frame F
(columns: tangent of the incoming edge, a normal parallel-transported from the root frame, their
cross product). The frame is lagged (not differentiated): a straight rest state (c = 0) is exactly
rotation invariant, a curved one turns with the strand. Forces: -k_b (b - F c) on v - 1 and
v + 1, +2 k_b (b - F c) on v.

One thread handles one strand and adds every force on its particles in a fixed order, so the
sums are bit-reproducible and need no atomics.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.func
def transport_normal(n: wp.vec3, t0: wp.vec3, t1: wp.vec3) -> wp.vec3:
    """Parallel transport of the unit normal ``n`` from unit tangent ``t0`` to ``t1`` (the
    minimal rotation taking t0 to t1), re-orthonormalised against t1."""
    c = wp.dot(t0, t1)
    a = wp.cross(t0, t1)
    r = n
    if c > -0.9999:
        r = n * c + wp.cross(a, n) + a * (wp.dot(a, n) / (1.0 + c))
    r = r - wp.dot(r, t1) * t1
    length = wp.length(r)
    if length > 1.0e-12:
        return r / length
    # the normal fell onto the tangent (a fold back): any unit vector normal to t1
    h = wp.vec3(1.0, 0.0, 0.0)
    if wp.abs(t1[0]) > 0.9:
        h = wp.vec3(0.0, 0.0, 1.0)
    return wp.normalize(wp.cross(t1, h))


@wp.func
def safe_normalize(u: wp.vec3) -> wp.vec3:
    length = wp.length(u)
    if length > 1.0e-12:
        return u / length
    return wp.vec3(1.0, 0.0, 0.0)


@wp.func
def vertex_frame(t: wp.vec3, n: wp.vec3) -> wp.mat33:
    """Frame with columns (t, n, t x n)."""
    b = wp.cross(t, n)
    return wp.mat33(t[0], n[0], b[0], t[1], n[1], b[1], t[2], n[2], b[2])


@wp.kernel
def eval_strand_forces(
    q: wp.array(dtype=wp.vec3),
    qd: wp.array(dtype=wp.vec3),
    first: int,
    stride: int,
    rest_length: wp.array(dtype=float),
    bend_rest: wp.array(dtype=wp.vec3),
    stretch_stiffness: wp.array(dtype=float),
    bend_stiffness: wp.array(dtype=float),
    stretch_damping: wp.array(dtype=float),
    bend_damping: wp.array(dtype=float),
    root_normal: wp.array(dtype=wp.vec3),
    f_out: wp.array(dtype=wp.vec3),
):
    """Adds the stretch springs f = -(k (l - L) + kd dl/dt) d_hat and the bending forces (module
    docstring; bending damping -kd_b (v[v-1] - 2 v[v] + v[v+1]) with the same pattern) of strand
    ``s`` to its particles. Stiffness [N/m], damping [N s/m] per strand."""
    s = wp.tid()
    base = first + s * stride
    slot = s * stride
    ks = stretch_stiffness[s]
    kb = bend_stiffness[s]
    ds = stretch_damping[s]
    db = bend_damping[s]
    n = root_normal[s]
    t_prev = safe_normalize(q[base + 1] - q[base])
    for v in range(1, stride - 1):
        i = base + v
        xa = q[i - 1]
        xb = q[i]
        xc = q[i + 1]
        if v >= 2:
            t = safe_normalize(xb - xa)
            n = transport_normal(n, t_prev, t)
            t_prev = t
        else:
            n = transport_normal(n, t_prev, t_prev)
        F = vertex_frame(t_prev, n)
        e = kb * (xa - 2.0 * xb + xc - F * bend_rest[slot + v]) + db * (qd[i - 1] - 2.0 * qd[i] + qd[i + 1])
        f_out[i - 1] = f_out[i - 1] - e
        f_out[i] = f_out[i] + 2.0 * e
        f_out[i + 1] = f_out[i + 1] - e
        u = xc - xb
        l = wp.length(u)
        if l > 1.0e-12:
            d = u / l
            ft = ks * (l - rest_length[slot + v]) + ds * wp.dot(qd[i + 1] - qd[i], d)
            f_out[i] = f_out[i] + ft * d
            f_out[i + 1] = f_out[i + 1] - ft * d


@wp.kernel
def bend_rest_from_world(
    q: wp.array(dtype=wp.vec3),
    first: int,
    stride: int,
    root_normal: wp.array(dtype=wp.vec3),
    world_rest: wp.array(dtype=wp.vec3),
    geometric: int,
    bend_rest_out: wp.array(dtype=wp.vec3),
):
    """bend_rest_out[slot] = F^T w for every bending vertex of strand ``s`` at positions ``q``:
    w = world_rest[slot] (a world-space rest bending vector [m]) or, with ``geometric`` = 1, the
    current second difference (the rest state of the shape as it is)."""
    s = wp.tid()
    base = first + s * stride
    slot = s * stride
    n = root_normal[s]
    t_prev = safe_normalize(q[base + 1] - q[base])
    for v in range(1, stride - 1):
        i = base + v
        if v >= 2:
            t = safe_normalize(q[i] - q[i - 1])
            n = transport_normal(n, t_prev, t)
            t_prev = t
        else:
            n = transport_normal(n, t_prev, t_prev)
        F = vertex_frame(t_prev, n)
        w = world_rest[slot + v]
        if geometric != 0:
            w = q[i - 1] - 2.0 * q[i] + q[i + 1]
        bend_rest_out[slot + v] = wp.transpose(F) * w


@wp.kernel
def bend_world_from_rest(
    q: wp.array(dtype=wp.vec3),
    first: int,
    stride: int,
    root_normal: wp.array(dtype=wp.vec3),
    bend_rest: wp.array(dtype=wp.vec3),
    world_out: wp.array(dtype=wp.vec3),
):
    """world_out[slot] = F c: the rest bending vectors in world space at positions ``q`` [m]."""
    s = wp.tid()
    base = first + s * stride
    slot = s * stride
    n = root_normal[s]
    t_prev = safe_normalize(q[base + 1] - q[base])
    for v in range(1, stride - 1):
        i = base + v
        if v >= 2:
            t = safe_normalize(q[i] - q[i - 1])
            n = transport_normal(n, t_prev, t)
            t_prev = t
        else:
            n = transport_normal(n, t_prev, t_prev)
        world_out[slot + v] = vertex_frame(t_prev, n) * bend_rest[slot + v]


@wp.kernel
def set_strand_roots(
    first: int,
    stride: int,
    head: wp.transform,
    ghost_local: wp.array(dtype=wp.vec3),
    root_local: wp.array(dtype=wp.vec3),
    normal_local: wp.array(dtype=wp.vec3),
    inv_dt: float,
    q: wp.array(dtype=wp.vec3),
    qd: wp.array(dtype=wp.vec3),
    root_normal_out: wp.array(dtype=wp.vec3),
):
    """Kinematic roots: ghost and root of strand ``s`` move to the head pose ``head`` applied to
    their head-frame positions [m]; their velocity is the displacement times ``inv_dt`` [1/s]
    (0: velocity set to zero); the root frame normal turns with the head."""
    s = wp.tid()
    base = first + s * stride
    g = wp.transform_point(head, ghost_local[s])
    r = wp.transform_point(head, root_local[s])
    qd[base] = (g - q[base]) * inv_dt
    qd[base + 1] = (r - q[base + 1]) * inv_dt
    q[base] = g
    q[base + 1] = r
    root_normal_out[s] = wp.transform_vector(head, normal_local[s])


@wp.kernel
def mesh_signed_distance(mesh: wp.uint64, points: wp.array(dtype=wp.vec3), distance_out: wp.array(dtype=float)):
    """Signed distance [m] of points (mesh frame) to a closed mesh, negative inside."""
    i = wp.tid()
    p = points[i]
    hit = wp.mesh_query_point_sign_normal(mesh, p, 1.0e6)
    d = 1.0e6
    if hit.result:
        c = wp.mesh_eval_position(mesh, hit.face, hit.u, hit.v)
        d = hit.sign * wp.length(p - c)
    distance_out[i] = d
