"""Sag-free initialization kernels (float64): the linear map from rest-state changes to particle
forces, its transpose, and the deterministic reductions and vector updates of the least-squares
solve in ``warpsim.strands.sag_free``.

Unknowns ``u`` (float64, one vector) are rest-state changes scaled so that ``u^T u`` is twice the
elastic energy of the change (minimum complementary energy): a length spring of stiffness k
[N/m] has tension t = sqrt(k) u [N] (rest length L = l - u / sqrt(k)); a strand bending vertex has
three entries, force pattern g = sqrt(k_b) u [N] (+g, -2 g, +g on the triple, and -J^T g through
the bending frames' gradient J, linearised at the current rest state; rest bending vector
w = b + u / sqrt(k_b)). Forces live in a flat float64 array of 3 entries per particle; pinned
particles (inverse mass 0) always get 0.

Sums run in a fixed order (per-particle gathers through a CSR adjacency, one thread per strand,
dot products over fixed strided partial sums then summed by one thread), so a solve is bit-reproducible.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.func
def load3(a: wp.array(dtype=wp.float64), i: int) -> wp.vec3d:
    return wp.vec3d(a[3 * i], a[3 * i + 1], a[3 * i + 2])


@wp.func
def load3_at(a: wp.array(dtype=wp.float64), start: int) -> wp.vec3d:
    return wp.vec3d(a[start], a[start + 1], a[start + 2])


@wp.func
def add3(a: wp.array(dtype=wp.float64), i: int, v: wp.vec3d):
    a[3 * i] = a[3 * i] + v[0]
    a[3 * i + 1] = a[3 * i + 1] + v[1]
    a[3 * i + 2] = a[3 * i + 2] + v[2]


@wp.func
def unit_d(a: wp.vec3, b: wp.vec3) -> wp.vec3d:
    """(a - b) / |a - b| in float64 (zero for coincident points)."""
    u = wp.vec3d(wp.float64(a[0]) - wp.float64(b[0]), wp.float64(a[1]) - wp.float64(b[1]),
                 wp.float64(a[2]) - wp.float64(b[2]))
    l = wp.length(u)
    if l > wp.float64(1.0e-15):
        return u / l
    return wp.vec3d()


@wp.kernel
def springs_apply(
    q: wp.array(dtype=wp.vec3),
    spring_indices: wp.array(dtype=int),
    sqrt_k: wp.array(dtype=wp.float64),
    adjacency_offsets: wp.array(dtype=int),
    adjacency_springs: wp.array(dtype=int),
    inv_mass: wp.array(dtype=float),
    u: wp.array(dtype=wp.float64),
    u_offset: int,
    f_out: wp.array(dtype=wp.float64),
):
    """f_out[i] = sum over springs s at particle i of -t_s d_hat (d = x_i - x_other), t_s =
    sqrt_k[s] u[u_offset + s]; overwrites f_out (0 at pinned particles)."""
    i = wp.tid()
    f = wp.vec3d()
    if inv_mass[i] > 0.0:
        for a in range(adjacency_offsets[i], adjacency_offsets[i + 1]):
            s = adjacency_springs[a]
            j = spring_indices[2 * s]
            if j == i:
                j = spring_indices[2 * s + 1]
            f = f - (sqrt_k[s] * u[u_offset + s]) * unit_d(q[i], q[j])
    f_out[3 * i] = f[0]
    f_out[3 * i + 1] = f[1]
    f_out[3 * i + 2] = f[2]


@wp.kernel
def springs_apply_transpose(
    q: wp.array(dtype=wp.vec3),
    spring_indices: wp.array(dtype=int),
    sqrt_k: wp.array(dtype=wp.float64),
    r: wp.array(dtype=wp.float64),
    u_offset: int,
    u_out: wp.array(dtype=wp.float64),
):
    """u_out[u_offset + s] = sqrt_k[s] d_hat . (r_j - r_i), d = x_i - x_j."""
    s = wp.tid()
    i = spring_indices[2 * s]
    j = spring_indices[2 * s + 1]
    u_out[u_offset + s] = sqrt_k[s] * wp.dot(unit_d(q[i], q[j]), load3(r, j) - load3(r, i))


@wp.func
def to_d(a: wp.vec3) -> wp.vec3d:
    return wp.vec3d(wp.float64(a[0]), wp.float64(a[1]), wp.float64(a[2]))


@wp.func
def project_normal(n: wp.vec3d, t: wp.vec3d) -> wp.vec3d:
    """Projection transport of the strand frames (as ``kernels.strands.transport_normal``)."""
    m = n - wp.dot(n, t) * t
    length = wp.length(m)
    if length > wp.float64(1.0e-6):
        return m / length
    h = wp.vec3d(wp.float64(1.0), wp.float64(0.0), wp.float64(0.0))
    if wp.abs(t[0]) > wp.float64(0.9):
        h = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(1.0))
    return wp.normalize(wp.cross(t, h))


@wp.func
def strand_frames(
    q: wp.array(dtype=wp.vec3), base: int, slot: int, stride: int, root_normal: wp.vec3,
    frame_t: wp.array(dtype=wp.vec3d), frame_n: wp.array(dtype=wp.vec3d),
):
    """The vertex frames (t_v, n_v) of one strand in float64 into frame_t / frame_n[slot + v]."""
    t = unit_d(q[base + 1], q[base])
    n = project_normal(to_d(root_normal), t)
    for v in range(1, stride - 1):
        if v >= 2:
            t = unit_d(q[base + v], q[base + v - 1])
            n = project_normal(n, t)
        frame_t[slot + v] = t
        frame_n[slot + v] = n


@wp.kernel
def strands_apply(
    q: wp.array(dtype=wp.vec3),
    first: int,
    stride: int,
    sqrt_stretch: wp.array(dtype=wp.float64),
    sqrt_bend: wp.array(dtype=wp.float64),
    root_normal: wp.array(dtype=wp.vec3),
    bend_rest: wp.array(dtype=wp.vec3),
    frame_t: wp.array(dtype=wp.vec3d),
    frame_n: wp.array(dtype=wp.vec3d),
    inv_mass: wp.array(dtype=float),
    u: wp.array(dtype=wp.float64),
    stretch_offset: int,
    bend_offset: int,
    f_out: wp.array(dtype=wp.float64),
):
    """Adds the forces of strand ``s``'s unknowns to its free particles, linearised at the current
    bending rest state: stretch tension t = sqrt_stretch u pulls vertex v toward v + 1 and back;
    bending g = sqrt_bend u (3 entries) gives +g, -2 g, +g on (v - 1, v, v + 1) and -J_v^T g,
    J_v = d(F_v c_v)/dx the frames' gradient (the reverse sweep of ``eval_strand_forces``)."""
    s = wp.tid()
    base = first + s * stride
    slot = s * stride
    cs = sqrt_stretch[s]
    cb = sqrt_bend[s]
    strand_frames(q, base, slot, stride, root_normal[s], frame_t, frame_n)
    two = wp.float64(2.0)
    for v in range(1, stride - 1):
        i = base + v
        k = slot + v
        g = cb * load3_at(u, bend_offset + 3 * k)
        t = (cs * u[stretch_offset + k]) * unit_d(q[i + 1], q[i])
        if inv_mass[i - 1] > 0.0:
            add3(f_out, i - 1, g)
        if inv_mass[i] > 0.0:
            add3(f_out, i, t - two * g)
        if inv_mass[i + 1] > 0.0:
            add3(f_out, i + 1, g - t)
    carry = wp.vec3d()
    for r in range(stride - 2):
        v = stride - 2 - r
        if v < 2:
            break
        i = base + v
        k = slot + v
        t = frame_t[k]
        n = frame_n[k]
        c = to_d(bend_rest[k])
        wbar = cb * load3_at(u, bend_offset + 3 * k)
        tbar = c[0] * wbar + c[2] * wp.cross(n, wbar)
        nbar = carry + c[1] * wbar + c[2] * wp.cross(wbar, t)
        n_prev = frame_n[k - 1]
        proj = wp.dot(n_prev, t)
        mlen = wp.sqrt(wp.max(wp.float64(1.0) - proj * proj, wp.float64(1.0e-12)))
        mbar = (nbar - wp.dot(nbar, n) * n) / mlen
        carry = mbar - wp.dot(mbar, t) * t
        tbar = tbar - proj * mbar - wp.dot(t, mbar) * n_prev
        l = wp.length(to_d(q[i]) - to_d(q[i - 1]))
        ubar = (tbar - wp.dot(tbar, t) * t) / l
        if inv_mass[i] > 0.0:
            add3(f_out, i, -ubar)
        if inv_mass[i - 1] > 0.0:
            add3(f_out, i - 1, ubar)


@wp.kernel
def strands_apply_transpose(
    q: wp.array(dtype=wp.vec3),
    first: int,
    stride: int,
    sqrt_stretch: wp.array(dtype=wp.float64),
    sqrt_bend: wp.array(dtype=wp.float64),
    root_normal: wp.array(dtype=wp.vec3),
    bend_rest: wp.array(dtype=wp.vec3),
    frame_t: wp.array(dtype=wp.vec3d),
    frame_n: wp.array(dtype=wp.vec3d),
    r: wp.array(dtype=wp.float64),
    stretch_offset: int,
    bend_offset: int,
    u_out: wp.array(dtype=wp.float64),
):
    """The transpose of ``strands_apply``: the frames' part is a tangent sweep from the root
    (dw_v = J_v r); slots 0 and stride - 1 of each strand are unused: 0."""
    s = wp.tid()
    base = first + s * stride
    slot = s * stride
    cs = sqrt_stretch[s]
    cb = sqrt_bend[s]
    zero = wp.float64(0.0)
    u_out[stretch_offset + slot] = zero
    u_out[stretch_offset + slot + stride - 1] = zero
    for j in range(3):
        u_out[bend_offset + 3 * slot + j] = zero
        u_out[bend_offset + 3 * (slot + stride - 1) + j] = zero
    strand_frames(q, base, slot, stride, root_normal[s], frame_t, frame_n)
    dn = wp.vec3d()  # the root frame is kinematic
    for v in range(1, stride - 1):
        i = base + v
        k = slot + v
        t = frame_t[k]
        n = frame_n[k]
        dt = wp.vec3d()
        if v >= 2:
            l = wp.length(to_d(q[i]) - to_d(q[i - 1]))
            dx = load3(r, i) - load3(r, i - 1)
            dt = (dx - wp.dot(dx, t) * t) / l
            n_prev = frame_n[k - 1]
            proj = wp.dot(n_prev, t)
            mlen = wp.sqrt(wp.max(wp.float64(1.0) - proj * proj, wp.float64(1.0e-12)))
            dm = dn - (wp.dot(dn, t) + wp.dot(n_prev, dt)) * t - proj * dt
            dn = (dm - wp.dot(dm, n) * n) / mlen
        c = to_d(bend_rest[k])
        dw = c[0] * dt + c[1] * dn + c[2] * (wp.cross(dt, n) + wp.cross(t, dn))
        d = unit_d(q[i + 1], q[i])
        u_out[stretch_offset + k] = cs * wp.dot(d, load3(r, i) - load3(r, i + 1))
        b = cb * (load3(r, i - 1) - wp.float64(2.0) * load3(r, i) + load3(r, i + 1) - dw)
        u_out[bend_offset + 3 * k] = b[0]
        u_out[bend_offset + 3 * k + 1] = b[1]
        u_out[bend_offset + 3 * k + 2] = b[2]


@wp.kernel
def external_rhs(
    f: wp.array(dtype=wp.vec3), inv_mass: wp.array(dtype=float), b_out: wp.array(dtype=wp.float64)
):
    """b_out = -f at free particles (the force the rest-state change must supply), 0 at pinned."""
    i = wp.tid()
    for c in range(3):
        b_out[3 * i + c] = wp.float64(0.0)
        if inv_mass[i] > 0.0:
            b_out[3 * i + c] = -wp.float64(f[i][c])


@wp.kernel
def flat_from_vec3(
    y: wp.array(dtype=wp.vec3), inv_mass: wp.array(dtype=float), scale: wp.float64, out: wp.array(dtype=wp.float64)
):
    """out = scale y at free particles, 0 at pinned (3 entries a particle)."""
    i = wp.tid()
    for c in range(3):
        out[3 * i + c] = wp.float64(0.0)
        if inv_mass[i] > 0.0:
            out[3 * i + c] = scale * wp.float64(y[i][c])


# --------------------------------------------------------------------------------------
# Deterministic reductions and vector updates (CGLS)
# --------------------------------------------------------------------------------------
@wp.kernel
def dot_partial(
    a: wp.array(dtype=wp.float64), b: wp.array(dtype=wp.float64), stride: int,
    partial_out: wp.array(dtype=wp.float64),
):
    """partial_out[t] = sum of a[i] b[i] over i = t, t + stride, t + 2 stride, ... in order
    (neighbouring threads read neighbouring entries)."""
    t = wp.tid()
    n = a.shape[0]
    acc = wp.float64(0.0)
    for i in range(t, n, stride):
        acc = acc + a[i] * b[i]
    partial_out[t] = acc


@wp.kernel
def fold_partials(partial: wp.array(dtype=wp.float64), stride: int, out: wp.array(dtype=wp.float64)):
    """out[t] = sum of partial[t], partial[t + stride], ... in order (the middle level of a dot
    product: many threads for the first level keep the GPU's loads in flight, few partials for the
    one-thread last level)."""
    t = wp.tid()
    acc = wp.float64(0.0)
    for i in range(t, partial.shape[0], stride):
        acc = acc + partial[i]
    out[t] = acc


@wp.kernel
def sum_partials(partial: wp.array(dtype=wp.float64), scalars: wp.array(dtype=wp.float64), slot: int):
    """scalars[slot] = sum of partial (one thread, in order)."""
    acc = wp.float64(0.0)
    for t in range(partial.shape[0]):
        acc = acc + partial[t]
    scalars[slot] = acc


@wp.kernel
def axpy_ratio(
    y: wp.array(dtype=wp.float64), x: wp.array(dtype=wp.float64), scalars: wp.array(dtype=wp.float64),
    num: int, den: int, sign: wp.float64,
):
    """y += sign (scalars[num] / scalars[den]) x (nothing when the denominator is 0)."""
    i = wp.tid()
    d = scalars[den]
    if d != wp.float64(0.0):
        y[i] = y[i] + sign * (scalars[num] / d) * x[i]


@wp.kernel
def cg_direction(
    p: wp.array(dtype=wp.float64), s: wp.array(dtype=wp.float64), scalars: wp.array(dtype=wp.float64),
    num: int, den: int,
):
    """p = s + (scalars[num] / scalars[den]) p."""
    i = wp.tid()
    d = scalars[den]
    beta = wp.float64(0.0)
    if d != wp.float64(0.0):
        beta = scalars[num] / d
    p[i] = s[i] + beta * p[i]


@wp.kernel
def copy_scalar(scalars: wp.array(dtype=wp.float64), src: int, dst: int):
    scalars[dst] = scalars[src]


@wp.kernel
def subtract_masked(
    b: wp.array(dtype=wp.float64), a: wp.array(dtype=wp.float64), out: wp.array(dtype=wp.float64)
):
    """out = b - a."""
    i = wp.tid()
    out[i] = b[i] - a[i]


@wp.kernel
def zero_masked(x: wp.array(dtype=wp.float64), mask: wp.array(dtype=int)):
    """x[j] = 0 where mask[j] != 0 (unknowns held at a bound or unused)."""
    j = wp.tid()
    if mask[j] != 0:
        x[j] = wp.float64(0.0)


@wp.kernel
def contacts_apply(
    contact_particle: wp.array(dtype=int),
    contact_normal: wp.array(dtype=wp.vec3d),
    scale: wp.float64,
    u: wp.array(dtype=wp.float64),
    u_offset: int,
    f_out: wp.array(dtype=wp.float64),
):
    """Adds the support force scale u[u_offset + c] n_c of contact c (a particle resting on a
    plane: one contact per particle) to its particle."""
    c = wp.tid()
    add3(f_out, contact_particle[c], (scale * u[u_offset + c]) * contact_normal[c])


@wp.kernel
def contacts_apply_transpose(
    contact_particle: wp.array(dtype=int),
    contact_normal: wp.array(dtype=wp.vec3d),
    scale: wp.float64,
    r: wp.array(dtype=wp.float64),
    u_offset: int,
    u_out: wp.array(dtype=wp.float64),
):
    """u_out[u_offset + c] = scale n_c . r[particle of c]."""
    c = wp.tid()
    u_out[u_offset + c] = scale * wp.dot(contact_normal[c], load3(r, contact_particle[c]))
