"""Implicit (backward Euler) strand step: one thread per strand assembles and solves its own
block-banded system (``warpsim.strands.implicit.StrandImplicitEuler`` drives these kernels).

Backward Euler in velocity form, linearised about the start of the step (Baraff and Witkin,
"Large Steps in Cloth Simulation", SIGGRAPH 1998, eq. 6 and 16):

    (M + h C + h^2 K) dv = h f(x0, v0) - h^2 K v0,     v1 = v0 + dv,  x1 = x0 + h v1,

with f the full force (``StrandForce``'s exact conservative stretch and bending forces plus every
other force of the system), K = -df/dx and C = -df/dv positive semi-definite approximations:

- stretch spring (a, b): K_e = k (d d^T + max(0, 1 - L/l) (I - d d^T)) (the spring Hessian with
  its negative geometric part clamped, so K_e is PSD), C_e = k_d d d^T, coupled as [[K, -K], [-K, K]];
- bending vertex v, residual r = b - F c (b = x[v-1] - 2 x[v] + x[v+1], F the vertex frame):
  Gauss-Newton K_e = k_b J^T J with J = dr/dx = [I + G, -2 I - G, I] on (v-1, v, v+1), where
  G = d(F c)/dx[v] through the vertex's own tangent (the frame's dependence on the transported
  normal of the previous vertex is left out: it couples the whole chain); J^T J is PSD;
  C_e = k_b,d [1, -2, 1]^T [1, -2, 1] (x) I, the bending damper's exact Jacobian;
- linear air drag c I and a drag spring (k I, c I) on its particle.

Bending couples x[v-1], x[v], x[v+1], so the matrix of a strand's free vertices is symmetric
positive definite and block-banded with two 3x3 blocks on each side of the diagonal. It is
solved directly by block Gaussian elimination without pivoting restricted to the band
(Golub and Van Loan, "Matrix Computations", 4th ed., sec. 4.3.5-4.3.6 (band LU) and 4.5 (block
tridiagonal / block band systems); no pivoting is needed for SPD matrices, sec. 4.2): the
symmetric elimination keeps the Schur complement symmetric, so the sub-diagonal multipliers are
L[i, k] = U[k, i]^T U[k, k]^-1. Cost per strand: O(segments) 3x3 block operations, in a fixed
order (bit-reproducible, no atomics).

Pinned vertices (mass 0: ghost and root) are not unknowns (identity rows and columns, dv = 0):
their velocity enters through the K v0 term (the roots move with the head) and ``StrandRoots``
places them after the step; a strand whose ghost and root have mass (released) is solved whole. Further Newton
iterations (``newton_residual`` + ``strand_resolve``) reuse the factors: dv += A^-1 (h f(x_k, v_k) -
M dv), x_k = x0 + h (v0 + dv).

Per strand vertex slot k = s * stride + v the scratch holds the factors: pinv (the inverse pivot
blocks U[v, v]^-1), up1 = U[v, v + 1], up2 = U[v, v + 2] (mat33), and rhs (vec3).
"""

import warp as wp

from .strands import safe_normalize, transport_normal

wp.set_module_options({"enable_backward": False})


@wp.func
def frame_tangent_jacobian(t: wp.vec3, n_prev: wp.vec3, c: wp.vec3, inv_length: float) -> wp.mat33:
    """G = d(F c)/dx[v] [1] of the rest bending vector in world space, F = (t, n, t x n) with
    t = (x[v] - x[v-1]) / |x[v] - x[v-1]| and n the previous normal ``n_prev`` transported onto
    t (``transport_normal``), n_prev held fixed; ``inv_length`` = 1 / |x[v] - x[v-1]| [1/m]."""
    proj = wp.dot(n_prev, t)
    m = n_prev - proj * t
    ml = wp.length(m)
    eye = wp.identity(n=3, dtype=float)
    if ml < 1.0e-6:
        return wp.mat33()
    n = m / ml
    dm_dt = -(wp.outer(t, n_prev) + proj * eye)
    dn_dt = (eye - wp.outer(n, n)) * dm_dt / ml
    dw_dt = c[0] * eye + c[1] * dn_dt + c[2] * (wp.skew(t) * dn_dt - wp.skew(n))
    return dw_dt * ((eye - wp.outer(t, t)) * inv_length)


@wp.func
def bend_jacobian_blocks(
    q: wp.array(dtype=wp.vec3), i: int, v: int, t: wp.vec3, n_prev: wp.vec3, c: wp.vec3
) -> wp.mat33:
    """G of bending vertex v (particle i); zero for v < 2 (the root frame does not depend on the
    free vertices)."""
    if v < 2:
        return wp.mat33()
    l = wp.length(q[i] - q[i - 1])
    if l <= 1.0e-12:
        return wp.mat33()
    return frame_tangent_jacobian(t, n_prev, c, 1.0 / l)


@wp.func
def back_substitute(
    slot: int,
    base: int,
    stride: int,
    pinv: wp.array(dtype=wp.mat33d),
    up1: wp.array(dtype=wp.mat33d),
    up2: wp.array(dtype=wp.mat33d),
    rhs: wp.array(dtype=wp.vec3d),
    x_out: wp.array(dtype=wp.vec3),
):
    """x[v] = U[v, v]^-1 (y[v] - U[v, v+1] x[v+1] - U[v, v+2] x[v+2]) from the tip down to v = 0."""
    x1 = wp.vec3d()  # x[v + 1]
    x2 = wp.vec3d()  # x[v + 2]
    for r in range(stride):
        v = stride - 1 - r
        y = rhs[slot + v]
        if v + 1 < stride:
            y = y - up1[slot + v] * x1
        if v + 2 < stride:
            y = y - up2[slot + v] * x2
        x = pinv[slot + v] * y
        x_out[base + v] = wp.vec3(x)
        x2 = x1
        x1 = x


@wp.kernel
def strand_implicit_solve(
    q: wp.array(dtype=wp.vec3),
    qd: wp.array(dtype=wp.vec3),
    f: wp.array(dtype=wp.vec3),
    mass: wp.array(dtype=float),
    first: int,
    stride: int,
    rest_length: wp.array(dtype=float),
    bend_rest: wp.array(dtype=wp.vec3),
    stretch_stiffness: wp.array(dtype=float),
    bend_stiffness: wp.array(dtype=float),
    stretch_damping: wp.array(dtype=float),
    bend_damping: wp.array(dtype=float),
    root_normal: wp.array(dtype=wp.vec3),
    air_drag: float,
    drag_particle: int,
    drag_stiffness: float,
    drag_damping: float,
    h: float,
    pinv: wp.array(dtype=wp.mat33d),
    up1: wp.array(dtype=wp.mat33d),
    up2: wp.array(dtype=wp.mat33d),
    rhs: wp.array(dtype=wp.vec3d),
    factor: int,
    dv_out: wp.array(dtype=wp.vec3),
):
    """Assemble (M + h C + h^2 K) and h f - h^2 K v0 of strand ``s`` at (q, qd) (module
    docstring), factor it in place (pinv, up1, up2) and write the velocity change of its free
    vertices to dv_out [m/s] (``factor`` = 0: assemble only, pinv holding the diagonal blocks).
    f: the full force at (q, qd) [N]; mass [kg] per particle; air_drag: linear drag [kg/s] on
    every free vertex; drag_particle (-1: none) held by a spring of drag_stiffness [N/m] and
    drag_damping [N s/m]; h [s]. The matrix is assembled and factored in float64 (its condition
    number reaches 1e5-1e6 at 32 segments and a frame step: float32 elimination feeds rounding
    errors of the stiff modes into the soft ones, measured as a growing tip oscillation)."""
    s = wp.tid()
    base = first + s * stride
    slot = s * stride
    ks = wp.float64(stretch_stiffness[s])
    kb = wp.float64(bend_stiffness[s])
    ds = wp.float64(stretch_damping[s])
    db = wp.float64(bend_damping[s])
    hd = wp.float64(h)
    h2 = hd * hd
    two = wp.float64(2.0)
    eye = wp.identity(n=3, dtype=wp.float64)
    for v in range(stride):
        i = base + v
        diag = (wp.float64(mass[i]) + hd * wp.float64(air_drag)) * eye
        r = hd * wp.vec3d(f[i])
        if i == drag_particle:
            diag = diag + (hd * wp.float64(drag_damping) + h2 * wp.float64(drag_stiffness)) * eye
            r = r - (h2 * wp.float64(drag_stiffness)) * wp.vec3d(qd[i])
        rhs[slot + v] = r
        pinv[slot + v] = diag  # the diagonal until factored
        up1[slot + v] = wp.mat33d()
        up2[slot + v] = wp.mat33d()
    # assembly, element by element: bending vertex v couples (v-1, v, v+1), stretch (v, v+1)
    t = safe_normalize(q[base + 1] - q[base])
    n = transport_normal(root_normal[s], t)
    for v in range(1, stride - 1):
        i = base + v
        n_prev = n
        if v >= 2:
            t = safe_normalize(q[i] - q[i - 1])
            n = transport_normal(n_prev, t)
        G = wp.mat33d(bend_jacobian_blocks(q, i, v, t, n_prev, bend_rest[slot + v]))
        J0 = eye + G
        J1 = -two * eye - G
        K00 = kb * wp.transpose(J0) * J0
        K01 = kb * wp.transpose(J0) * J1
        K02 = kb * wp.transpose(J0)
        K11 = kb * wp.transpose(J1) * J1
        K12 = kb * wp.transpose(J1)
        K22 = kb * eye
        va = wp.vec3d(qd[i - 1])
        vb = wp.vec3d(qd[i])
        vc = wp.vec3d(qd[i + 1])
        hdb = hd * db
        pinv[slot + v - 1] = pinv[slot + v - 1] + h2 * K00 + hdb * eye
        up1[slot + v - 1] = up1[slot + v - 1] + h2 * K01 - (two * hdb) * eye
        up2[slot + v - 1] = up2[slot + v - 1] + h2 * K02 + hdb * eye
        pinv[slot + v] = pinv[slot + v] + h2 * K11 + (two * two * hdb) * eye
        up1[slot + v] = up1[slot + v] + h2 * K12 - (two * hdb) * eye
        pinv[slot + v + 1] = pinv[slot + v + 1] + h2 * K22 + hdb * eye
        rhs[slot + v - 1] = rhs[slot + v - 1] - h2 * (K00 * va + K01 * vb + K02 * vc)
        rhs[slot + v] = rhs[slot + v] - h2 * (wp.transpose(K01) * va + K11 * vb + K12 * vc)
        rhs[slot + v + 1] = rhs[slot + v + 1] - h2 * (wp.transpose(K02) * va + wp.transpose(K12) * vb + K22 * vc)
        # stretch spring (v, v + 1)
        u = wp.vec3d(q[i + 1]) - wp.vec3d(q[i])
        l = wp.length(u)
        if l > wp.float64(1.0e-12):
            d = u / l
            dd = wp.outer(d, d)
            geometric = wp.max(wp.float64(0.0), wp.float64(1.0) - wp.float64(rest_length[slot + v]) / l)
            Ks = ks * (dd + geometric * (eye - dd))
            Ae = h2 * Ks + (hd * ds) * dd
            pinv[slot + v] = pinv[slot + v] + Ae
            pinv[slot + v + 1] = pinv[slot + v + 1] + Ae
            up1[slot + v] = up1[slot + v] - Ae
            kv = h2 * (Ks * (vb - vc))
            rhs[slot + v] = rhs[slot + v] - kv
            rhs[slot + v + 1] = rhs[slot + v + 1] + kv
    # pinned vertices (mass 0: ghost and root, or any other) are not unknowns: identity rows and
    # columns, right-hand side 0 (their velocity entered above through K v0)
    zero = wp.mat33d()
    for v in range(stride):
        if mass[base + v] <= 0.0:
            pinv[slot + v] = eye
            rhs[slot + v] = wp.vec3d()
            up1[slot + v] = zero
            up2[slot + v] = zero
            if v >= 1:
                up1[slot + v - 1] = zero
            if v >= 2:
                up2[slot + v - 2] = zero
    if factor == 0:  # assembly only (tests read the matrix)
        return
    # factor the band and eliminate the right-hand side
    for v in range(stride):
        P = wp.inverse(pinv[slot + v])
        pinv[slot + v] = P
        y = rhs[slot + v]
        if v + 1 < stride:
            E = up1[slot + v]
            L1 = wp.transpose(E) * P
            pinv[slot + v + 1] = pinv[slot + v + 1] - L1 * E
            rhs[slot + v + 1] = rhs[slot + v + 1] - L1 * y
            if v + 2 < stride:
                F = up2[slot + v]
                up1[slot + v + 1] = up1[slot + v + 1] - L1 * F
                L2 = wp.transpose(F) * P
                pinv[slot + v + 2] = pinv[slot + v + 2] - L2 * F
                rhs[slot + v + 2] = rhs[slot + v + 2] - L2 * y
    back_substitute(slot, base, stride, pinv, up1, up2, rhs, dv_out)


@wp.kernel
def strand_resolve(
    f: wp.array(dtype=wp.vec3),
    mass: wp.array(dtype=float),
    first: int,
    stride: int,
    h: float,
    pinv: wp.array(dtype=wp.mat33d),
    up1: wp.array(dtype=wp.mat33d),
    up2: wp.array(dtype=wp.mat33d),
    rhs: wp.array(dtype=wp.vec3d),
    dv: wp.array(dtype=wp.vec3),
    delta: wp.array(dtype=wp.vec3),
):
    """A later Newton iteration of strand ``s`` with the stored factors: solve A delta = h f -
    M dv (f the force at the trial state [N]) and add delta to dv [m/s]."""
    s = wp.tid()
    base = first + s * stride
    slot = s * stride
    hd = wp.float64(h)
    for v in range(stride):
        i = base + v
        r = wp.vec3d()
        if mass[i] > 0.0:
            r = hd * wp.vec3d(f[i]) - wp.float64(mass[i]) * wp.vec3d(dv[i])
        rhs[slot + v] = r
    for v in range(stride):
        P = pinv[slot + v]
        y = rhs[slot + v]
        if v + 1 < stride:
            rhs[slot + v + 1] = rhs[slot + v + 1] - (wp.transpose(up1[slot + v]) * P) * y
        if v + 2 < stride:
            rhs[slot + v + 2] = rhs[slot + v + 2] - (wp.transpose(up2[slot + v]) * P) * y
    back_substitute(slot, base, stride, pinv, up1, up2, rhs, delta)
    for v in range(stride):
        dv[base + v] = dv[base + v] + delta[base + v]


@wp.kernel
def explicit_velocity_change(
    f: wp.array(dtype=wp.vec3), inv_mass: wp.array(dtype=float), h: float, dv_out: wp.array(dtype=wp.vec3)
):
    """dv = h f / m for every particle (the strands' free vertices are then overwritten by the
    implicit solve; other particles step semi-implicitly)."""
    i = wp.tid()
    dv_out[i] = (h * inv_mass[i]) * f[i]


@wp.kernel
def apply_velocity_change(
    q0: wp.array(dtype=wp.vec3),
    v0: wp.array(dtype=wp.vec3),
    dv: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    h: float,
    q_out: wp.array(dtype=wp.vec3),
    qd_out: wp.array(dtype=wp.vec3),
):
    """v = v0 + dv (free particles; pinned keep v0), x = x0 + h v [m]."""
    i = wp.tid()
    v = v0[i]
    if inv_mass[i] > 0.0:
        v = v + dv[i]
    qd_out[i] = v
    q_out[i] = q0[i] + h * v
