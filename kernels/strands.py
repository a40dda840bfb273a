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
E = k_b / 2 |b - F c|^2, with c the rest bending vector expressed in the vertex frame F (columns:
the unit tangent t of the incoming edge, a normal n carried from the root frame by projection
transport n_v = normalize(n_(v-1) - (n_(v-1) . t_v) t_v), and t x n). The root frame turns with
the head, so a curved rest shape turns with the strand; a straight one (c = 0) is the plain
second-difference bending. The forces are -grad E *including* the frames' dependence on the
positions (a reverse sweep from the tip), so they are conservative: a lagged frame (treated as
constant) makes a curved strand a follower-force system that gains energy and flutters (measured:
the 32-segment groom's top speed grew from 0.35 to 2.2 m/s over 5 s).

One thread handles one strand and adds every force on its particles in a fixed order, so the
sums are bit-reproducible and need no atomics.
"""

import warp as wp

from .collide import collide_particle_capsule

wp.set_module_options({"enable_backward": False})


@wp.func
def transport_normal(n: wp.vec3, t: wp.vec3) -> wp.vec3:
    """The unit normal ``n`` carried onto the plane normal to the unit tangent ``t``: n - (n . t) t,
    normalised (projection transport: a rotation-minimising frame to first order)."""
    m = n - wp.dot(n, t) * t
    length = wp.length(m)
    if length > 1.0e-6:
        return m / length
    # the normal fell onto the tangent (a right-angle fold): any unit vector normal to t
    h = wp.vec3(1.0, 0.0, 0.0)
    if wp.abs(t[0]) > 0.9:
        h = wp.vec3(0.0, 0.0, 1.0)
    return wp.normalize(wp.cross(t, h))


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
    frame_t_tmp: wp.array(dtype=wp.vec3),
    frame_n_tmp: wp.array(dtype=wp.vec3),
    f_out: wp.array(dtype=wp.vec3),
):
    """Adds the forces of strand ``s`` to its particles: stretch springs f = -(k (l - L) + kd dl/dt)
    d_hat, and -grad E of the bending energy (module docstring) including the frames' dependence on
    the positions (a reverse sweep from the tip through the projection transport), so the bending
    forces are conservative; bending damping -kd_b (v[v-1] - 2 v[v] + v[v+1]) in the same pattern.
    Stiffness [N/m], damping [N s/m] per strand; frame_*_tmp: per-slot scratch (the frames)."""
    s = wp.tid()
    base = first + s * stride
    slot = s * stride
    ks = stretch_stiffness[s]
    kb = bend_stiffness[s]
    ds = stretch_damping[s]
    db = bend_damping[s]
    t = safe_normalize(q[base + 1] - q[base])
    n = transport_normal(root_normal[s], t)
    for v in range(1, stride - 1):
        i = base + v
        xa = q[i - 1]
        xb = q[i]
        xc = q[i + 1]
        if v >= 2:
            t = safe_normalize(xb - xa)
            n = transport_normal(n, t)
        frame_t_tmp[slot + v] = t
        frame_n_tmp[slot + v] = n
        e = kb * (xa - 2.0 * xb + xc - vertex_frame(t, n) * bend_rest[slot + v]) + db * (
            qd[i - 1] - 2.0 * qd[i] + qd[i + 1])
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
    # reverse sweep: dE/dw = -kb (b - w) flows into the frames (t_v, n_v), n_v into n_(v-1) and t_v,
    # t_v into x_v and x_(v-1); the force is minus that gradient
    carry = wp.vec3()  # dE/dn_v from the frames after v
    for r in range(stride - 2):
        v = stride - 2 - r
        if v < 2:
            break
        i = base + v
        t = frame_t_tmp[slot + v]
        n = frame_n_tmp[slot + v]
        c = bend_rest[slot + v]
        w = c[0] * t + c[1] * n + c[2] * wp.cross(t, n)
        wbar = -kb * (q[i - 1] - 2.0 * q[i] + q[i + 1] - w)
        tbar = c[0] * wbar + c[2] * wp.cross(n, wbar)
        nbar = carry + c[1] * wbar + c[2] * wp.cross(wbar, t)
        n_prev = frame_n_tmp[slot + v - 1]
        proj = wp.dot(n_prev, t)
        mlen = wp.sqrt(wp.max(1.0 - proj * proj, 1.0e-12))
        mbar = (nbar - wp.dot(nbar, n) * n) / mlen
        carry = mbar - wp.dot(mbar, t) * t
        tbar = tbar - proj * mbar - wp.dot(t, mbar) * n_prev
        l = wp.length(q[i] - q[i - 1])
        if l > 1.0e-12:
            ubar = (tbar - wp.dot(tbar, t) * t) / l
            f_out[i] = f_out[i] - ubar
            f_out[i - 1] = f_out[i - 1] + ubar


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
    t = safe_normalize(q[base + 1] - q[base])
    n = transport_normal(root_normal[s], t)
    for v in range(1, stride - 1):
        i = base + v
        if v >= 2:
            t = safe_normalize(q[i] - q[i - 1])
            n = transport_normal(n, t)
        F = vertex_frame(t, n)
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
    t = safe_normalize(q[base + 1] - q[base])
    n = transport_normal(root_normal[s], t)
    for v in range(1, stride - 1):
        i = base + v
        if v >= 2:
            t = safe_normalize(q[i] - q[i - 1])
            n = transport_normal(n, t)
        world_out[slot + v] = vertex_frame(t, n) * bend_rest[slot + v]


@wp.func
def place_roots(
    s: int,
    first: int,
    stride: int,
    head_prev: wp.transform,
    head: wp.transform,
    ghost_local: wp.array(dtype=wp.vec3),
    root_local: wp.array(dtype=wp.vec3),
    normal_local: wp.array(dtype=wp.vec3),
    inv_dt: float,
    q: wp.array(dtype=wp.vec3),
    qd: wp.array(dtype=wp.vec3),
    root_normal_out: wp.array(dtype=wp.vec3),
):
    """Ghost and root of strand ``s`` at the head pose ``head`` applied to their head-frame
    positions [m]; their velocity is their displacement from pose ``head_prev`` times ``inv_dt``
    [1/s] (from the poses, not from the integrated positions, which a pinned particle's velocity
    extrapolates); the root frame normal turns with the head."""
    base = first + s * stride
    g = wp.transform_point(head, ghost_local[s])
    r = wp.transform_point(head, root_local[s])
    qd[base] = (g - wp.transform_point(head_prev, ghost_local[s])) * inv_dt
    qd[base + 1] = (r - wp.transform_point(head_prev, root_local[s])) * inv_dt
    q[base] = g
    q[base + 1] = r
    root_normal_out[s] = wp.transform_vector(head, normal_local[s])


@wp.kernel
def set_strand_roots(
    first: int,
    stride: int,
    head_prev: wp.transform,
    head: wp.transform,
    ghost_local: wp.array(dtype=wp.vec3),
    root_local: wp.array(dtype=wp.vec3),
    normal_local: wp.array(dtype=wp.vec3),
    inv_dt: float,
    q: wp.array(dtype=wp.vec3),
    qd: wp.array(dtype=wp.vec3),
    root_normal_out: wp.array(dtype=wp.vec3),
):
    """Kinematic roots (``place_roots``) between the head poses ``head_prev`` and ``head``."""
    place_roots(wp.tid(), first, stride, head_prev, head, ghost_local, root_local, normal_local, inv_dt, q, qd,
                root_normal_out)


@wp.kernel
def set_strand_roots_posed(
    first: int,
    stride: int,
    poses: wp.array(dtype=wp.transform),
    step: int,
    ghost_local: wp.array(dtype=wp.vec3),
    root_local: wp.array(dtype=wp.vec3),
    normal_local: wp.array(dtype=wp.vec3),
    inv_dt: float,
    q: wp.array(dtype=wp.vec3),
    qd: wp.array(dtype=wp.vec3),
    root_normal_out: wp.array(dtype=wp.vec3),
):
    """``set_strand_roots`` with the head poses of the frame's step ``step`` read from the device
    (poses[2 step], poses[2 step + 1]: before and after it), so a captured frame replays with new
    poses."""
    place_roots(wp.tid(), first, stride, poses[2 * step], poses[2 * step + 1], ghost_local, root_local, normal_local,
                inv_dt, q, qd, root_normal_out)


@wp.kernel
def collide_sphere_posed(
    inv_mass: wp.array(dtype=float),
    radius: wp.array(dtype=float),
    q_prev: wp.array(dtype=wp.vec3),
    poses: wp.array(dtype=wp.transform),
    step: int,
    shape_radius: float,
    restitution: float,
    friction: float,
    mode: int,
    thickness: float,
    stiffness: float,
    damping_ratio: float,
    dt: float,
    forces: wp.array(dtype=wp.vec3),
    q_io: wp.array(dtype=wp.vec3),
    qd_io: wp.array(dtype=wp.vec3),
):
    """A solid sphere (``collide_particle_capsule`` with a = b = 0, continuous detection) between
    the poses poses[2 step] and poses[2 step + 1] read from the device (``set_strand_roots_posed``);
    the head moves, so there is no early-out (far_half < 0)."""
    collide_particle_capsule(wp.tid(), inv_mass, radius, q_prev, 1, wp.vec3(), wp.vec3(), shape_radius, 0,
                             poses[2 * step], poses[2 * step + 1], wp.vec3(), -1.0, restitution, friction, mode,
                             thickness, stiffness, damping_ratio, dt, forces, q_io, qd_io)


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
