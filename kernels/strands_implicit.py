"""Implicit (backward Euler) strand step: one thread per strand assembles and solves its own
block-banded system (``warpsim.strands.implicit.StrandImplicitEuler`` drives these kernels).

Backward Euler in velocity form, linearised about the start of the step (Baraff and Witkin,
"Large Steps in Cloth Simulation", SIGGRAPH 1998, eq. 6 and 16):

    (M + h C + h^2 K) dv = h f(x0, v0) - h^2 K v0,     v1 = v0 + dv,  x1 = x0 + h v1,

with f the full force (``StrandForce``'s exact conservative stretch and bending forces plus every
other force of the system), K = -df/dx and C = -df/dv positive semi-definite approximations:

- stretch spring (a, b): K_e = k (d d^T + max(0, 1 - L/l) (I - d d^T)) (the spring Hessian with
  its negative geometric part clamped, so K_e is PSD), C_e = k_d d d^T, coupled as [[K, -K], [-K, K]];
- bending: Gauss-Newton on the residuals r_v = b_v - F_v c_v (b the second difference, F_v the
  transported vertex frame), K = k_b J^T J with J = dr/dx *including* the frames' dependence on
  every earlier vertex (Nocedal and Wright, "Numerical Optimization", 2nd ed., sec. 10.3); J^T J
  is PSD. The frame's normal n_v moves as dn_v = -(n_v . dt_v) t_v + phi_v (t_v x n_v): its twist
  phi_v obeys the recurrence phi_v = alpha_v phi_(v-1) + a1_v . dt_(v-1) l_(v-1) + a2_v . dt_v l_v
  (projection transport differentiated), which couples the whole strand, so J^T J over the
  positions is dense. The twists are kept as a fourth unknown per vertex, coupled to the
  positions by the linearised residual dr_v = (I + Q_v P_v) dx_(v-1) - (2 I + Q_v P_v) dx_v +
  dx_(v+1) - u_v phi_v and held to their recurrence by a quadratic penalty mu_v s_v^2 (s_v the
  recurrence's residual, mu_v = TWIST_PENALTY k_b l_v^2; a penalty method, Nocedal and Wright
  sec. 17.1: the positions' Schur complement is J^T J to within 1 / TWIST_PENALTY, measured 0.1 %
  at 32 segments); so the system stays block-banded with 4x4 blocks. Without the twists (the
  vertex's own frame only) the wavy groom's steps were unstable above 2.4 ms at 32 segments:
  the banded matrix underestimated the stiffness up to 8.8x;
  C_e = k_b,d [1, -2, 1]^T [1, -2, 1] (x) I, the bending damper's exact Jacobian;
- linear air drag c I and a drag spring (k I, c I) on its particle.

Bending and the twist recurrence couple vertices v-2 .. v+1, so the matrix of a strand's
unknowns (x, y, z, phi per vertex) is symmetric positive definite and block-banded with two 4x4
blocks on each side of the diagonal. It is solved directly by a block band Cholesky
factorisation A = R^T R (Golub and Van Loan, "Matrix Computations", 4th ed., sec. 4.3.5 (band
Cholesky) and 4.5 (block tridiagonal / block band systems); no pivoting for SPD matrices, sec.
4.2), each 4x4 pivot block factored by Cholesky. The rows are assembled in a window of four
block rows (registers) and each is factored as soon as its last element is in, its Schur
complement going to the two rows after it still in the window: a row is written once, as its
factor (assembling into global scratch and factoring in a second pass cost 2x on the CPU). Cost
per strand: O(segments) 4x4 block operations, in a fixed order (bit-reproducible, no atomics).

Pinned vertices (mass 0: ghost and root) are not unknowns (identity rows and columns in their
x, y, z, dv = 0): their velocity enters through the K v0 term (the roots move with the head) and
``StrandRoots`` places them after the step; a strand whose ghost and root have mass (released)
is solved whole. Further Newton iterations (``strand_resolve``) reuse the factors: dv += A^-1 (h
f(x_k, v_k) - M dv), x_k = x0 + h (v0 + dv).

Per strand vertex slot k = s * stride + v the scratch holds the factors: pinv (R[v, v]^-1),
up1 = R[v, v + 1], up2 = R[v, v + 2] (mat44d), and rhs (vec4d).
"""

import warp as wp

from .strands import safe_normalize, transport_normal

wp.set_module_options({"enable_backward": False})

mat34d = wp.types.matrix(shape=(3, 4), dtype=wp.float64)

TWIST_PENALTY = wp.constant(wp.float64(1.0e4))
"""mu_v / (k_b l_v^2) of the twist recurrence's penalty (module docstring)."""


@wp.func
def embed3(m: wp.mat33d) -> wp.mat44d:
    """The 4x4 block acting on (x, y, z) as ``m`` and not on the twist."""
    return wp.mat44d(m[0, 0], m[0, 1], m[0, 2], wp.float64(0.0), m[1, 0], m[1, 1], m[1, 2], wp.float64(0.0),
                     m[2, 0], m[2, 1], m[2, 2], wp.float64(0.0), wp.float64(0.0), wp.float64(0.0), wp.float64(0.0),
                     wp.float64(0.0))


@wp.func
def jac34(m: wp.mat33d, u: wp.vec3d) -> mat34d:
    """A 3x4 Jacobian block: ``m`` on (x, y, z), ``u`` on the twist."""
    j = mat34d()
    for r in range(3):
        for c in range(3):
            j[r, c] = m[r, c]
        j[r, 3] = u[r]
    return j


@wp.func
def xyz(v: wp.vec4d) -> wp.vec3d:
    return wp.vec3d(v[0], v[1], v[2])


@wp.func
def four(v: wp.vec3d, phi: wp.float64) -> wp.vec4d:
    return wp.vec4d(v[0], v[1], v[2], phi)


@wp.func
def cross_matrix(n: wp.vec3d) -> wp.mat33d:
    """[n]_x: [n]_x a = n x a."""
    z = wp.float64(0.0)
    return wp.mat33d(z, -n[2], n[1], n[2], z, -n[0], -n[1], n[0], z)


@wp.func
def stretch_element(xa: wp.vec3, xb: wp.vec3, va: wp.vec3d, vb: wp.vec3d, rest: wp.float64, ks: wp.float64,
                    ds: wp.float64, hd: wp.float64):
    """Stretch spring (a, b): (A_e, r_e) with h^2 K_e + h C_e = A_e on the blocks [[A_e, -A_e],
    [-A_e, A_e]] and h^2 K_e (v0 differences) = r_e to take from a's right-hand side and give to b's."""
    u = wp.vec3d(xb) - wp.vec3d(xa)
    l = wp.length(u)
    if l <= wp.float64(1.0e-12):
        return wp.mat44d(), wp.vec4d()
    eye = wp.identity(n=3, dtype=wp.float64)
    d = u / l
    dd = wp.outer(d, d)
    geometric = wp.max(wp.float64(0.0), wp.float64(1.0) - rest / l)
    Ks = ks * (dd + geometric * (eye - dd))
    return embed3(hd * hd * Ks + (hd * ds) * dd), four((hd * hd) * (Ks * (va - vb)), wp.float64(0.0))


@wp.func
def row_diagonal(qd: wp.array(dtype=wp.vec3), f: wp.array(dtype=wp.vec3), mass: wp.array(dtype=float), i: int,
                 air_drag: float, drag_particle: int, drag_stiffness: float, drag_damping: float, hd: wp.float64):
    """(M + h c_air (+ the drag spring's h c + h^2 k), h f (- h^2 k v0)) of particle i."""
    h2 = hd * hd
    eye = wp.identity(n=3, dtype=wp.float64)
    diag = (wp.float64(mass[i]) + hd * wp.float64(air_drag)) * eye
    r = hd * wp.vec3d(f[i])
    if i == drag_particle:
        diag = diag + (hd * wp.float64(drag_damping) + h2 * wp.float64(drag_stiffness)) * eye
        r = r - (h2 * wp.float64(drag_stiffness)) * wp.vec3d(qd[i])
    return embed3(diag), four(r, wp.float64(0.0))


@wp.func
def store_row(pinv: wp.array(dtype=wp.mat44d), up1: wp.array(dtype=wp.mat44d), up2: wp.array(dtype=wp.mat44d),
              rhs: wp.array(dtype=wp.vec4d), k: int, P: wp.mat44d, E: wp.mat44d, F: wp.mat44d, y: wp.vec4d):
    pinv[k] = P
    up1[k] = E
    up2[k] = F
    rhs[k] = y


@wp.func
def finish_row(mass: wp.array(dtype=float), base: int, stride: int, r: int, P: wp.mat44d, E: wp.mat44d, F: wp.mat44d,
               y: wp.vec4d):
    """Row r of a strand, assembled: pinned vertices (mass 0) are not unknowns in x, y, z (identity
    rows and columns there, right-hand side 0: their velocity entered through K v0); their twist
    stays an unknown. Twists that no element touches (the ghost's, the tip's) get a unit diagonal."""
    keep = wp.mat44d()
    keep[3, 3] = wp.float64(1.0)
    if r == 0 or r == stride - 1:
        P = P + keep
    if mass[base + r] <= 0.0:
        P = keep * P * keep + embed3(wp.identity(n=3, dtype=wp.float64))
        y = keep * y
        E = keep * E
        F = keep * F
    # nested, not `and`: the mass of the next strand's particles (or past the array) is not read
    if r + 1 < stride:  # noqa: SIM102
        if mass[base + r + 1] <= 0.0:
            E = E * keep
    if r + 2 < stride:  # noqa: SIM102
        if mass[base + r + 2] <= 0.0:
            F = F * keep
    return P, E, F, y


@wp.func
def cholesky_inverse(a: wp.mat44d) -> wp.mat44d:
    """R^-1 of the Cholesky factor of the SPD block ``a`` = R^T R (R upper triangular; Golub and
    Van Loan, alg. 4.2.1), by inverting L = R^T by forward substitution."""
    low = wp.mat44d()
    for j in range(4):
        d = a[j, j]
        for k in range(j):
            d = d - low[j, k] * low[j, k]
        d = wp.sqrt(wp.max(d, wp.float64(1.0e-300)))
        low[j, j] = d
        for i in range(j + 1, 4):
            e = a[i, j]
            for k in range(j):
                e = e - low[i, k] * low[j, k]
            low[i, j] = e / d
    inv = wp.mat44d()
    for j in range(4):
        inv[j, j] = wp.float64(1.0) / low[j, j]
        for i in range(j + 1, 4):
            e = wp.float64(0.0)
            for k in range(j, i):
                e = e - low[i, k] * inv[k, j]
            inv[i, j] = e / low[i, i]
    return wp.transpose(inv)


@wp.func
def complete_row(mass: wp.array(dtype=float), base: int, slot: int, stride: int, r: int, factor: int,
                 pinv: wp.array(dtype=wp.mat44d), up1: wp.array(dtype=wp.mat44d), up2: wp.array(dtype=wp.mat44d),
                 rhs: wp.array(dtype=wp.vec4d), P: wp.mat44d, E: wp.mat44d, F: wp.mat44d, y: wp.vec4d):
    """Row r assembled (and, with ``factor``, its pivot already reduced by the rows before it):
    ``finish_row``, then one step of the block band Cholesky A = R^T R: R[r, r]^-1, R[r, r+1] =
    R[r, r]^-T E, R[r, r+2] = R[r, r]^-T F and the eliminated right-hand side R[r, r]^-T y are
    stored (``factor`` = 0: the assembled row itself) and (R[r, r+1], R[r, r+2], R^-T y) returned
    for the Schur complement of the two rows after it."""
    P, E, F, y = finish_row(mass, base, stride, r, P, E, F, y)
    if factor == 0:
        store_row(pinv, up1, up2, rhs, slot + r, P, E, F, y)
        return wp.mat44d(), wp.mat44d(), wp.vec4d()
    Ri = cholesky_inverse(P)
    RiT = wp.transpose(Ri)
    E = RiT * E
    F = RiT * F
    y = RiT * y
    store_row(pinv, up1, up2, rhs, slot + r, Ri, E, F, y)
    return E, F, y


@wp.func
def eliminate_rhs(slot: int, stride: int, pinv: wp.array(dtype=wp.mat44d), up1: wp.array(dtype=wp.mat44d),
                  up2: wp.array(dtype=wp.mat44d), rhs: wp.array(dtype=wp.vec4d)):
    """R^T y = rhs for a new right-hand side with the stored factors."""
    for v in range(stride):
        y = wp.transpose(pinv[slot + v]) * rhs[slot + v]
        rhs[slot + v] = y
        if v + 1 < stride:
            rhs[slot + v + 1] = rhs[slot + v + 1] - wp.transpose(up1[slot + v]) * y
        if v + 2 < stride:
            rhs[slot + v + 2] = rhs[slot + v + 2] - wp.transpose(up2[slot + v]) * y


@wp.func
def back_substitute(
    slot: int,
    base: int,
    stride: int,
    pinv: wp.array(dtype=wp.mat44d),
    up1: wp.array(dtype=wp.mat44d),
    up2: wp.array(dtype=wp.mat44d),
    rhs: wp.array(dtype=wp.vec4d),
    x_out: wp.array(dtype=wp.vec3),
):
    """R x = y: x[v] = R[v, v]^-1 (y[v] - R[v, v+1] x[v+1] - R[v, v+2] x[v+2]) from the tip down to
    v = 0; the x, y, z parts go to x_out (float32)."""
    x1 = wp.vec4d()  # x[v + 1]
    x2 = wp.vec4d()  # x[v + 2]
    for r in range(stride):
        v = stride - 1 - r
        y = rhs[slot + v]
        if v + 1 < stride:
            y = y - up1[slot + v] * x1
        if v + 2 < stride:
            y = y - up2[slot + v] * x2
        x = pinv[slot + v] * y
        x_out[base + v] = wp.vec3(xyz(x))
        x2 = x1
        x1 = x


@wp.func
def twist_terms(n_prev: wp.vec3d, t: wp.vec3d, b: wp.vec3d, t_prev: wp.vec3d, b_prev: wp.vec3d,
                inv_l: wp.float64, inv_l_prev: wp.float64, v: int) -> wp.vec4d:
    """(alpha, beta1, beta2, ok) of the twist recurrence phi_v = alpha phi_(v-1) + beta1 n_prev .
    (dx_(v-1) - dx_(v-2)) + beta2 b . (dx_v - dx_(v-1)) (projection transport of n_prev onto t,
    differentiated; v = 1: the root normal is fixed, alpha = beta1 = 0); ok = 0 where the
    transport degenerates (the kernels then pick an unrelated normal: no twist coupling)."""
    proj = wp.dot(n_prev, t)
    m2 = wp.float64(1.0) - proj * proj
    z = wp.float64(0.0)
    if m2 < wp.float64(1.0e-12):
        return wp.vec4d(z, z, z, z)
    inv_m = wp.float64(1.0) / wp.sqrt(m2)
    beta2 = -proj * inv_m * inv_l
    if v < 2:
        return wp.vec4d(z, z, beta2, wp.float64(1.0))
    return wp.vec4d(wp.dot(b, b_prev) * inv_m, -wp.dot(b, t_prev) * inv_m * inv_l_prev, beta2, wp.float64(1.0))


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
    pinv: wp.array(dtype=wp.mat44d),
    up1: wp.array(dtype=wp.mat44d),
    up2: wp.array(dtype=wp.mat44d),
    rhs: wp.array(dtype=wp.vec4d),
    factor: int,
    dv_out: wp.array(dtype=wp.vec3),
):
    """Assemble (M + h C + h^2 K) and h f - h^2 K v0 of strand ``s`` at (q, qd) over its positions
    and twists (module docstring), factor it row by row into (pinv, up1, up2, rhs) and write the
    velocity change of its free vertices to dv_out [m/s] (``factor`` = 0: assemble only, the
    blocks of the upper band in pinv, up1, up2). f: the full force at (q, qd) [N]; mass [kg] per
    particle; air_drag: linear drag [kg/s] on every free vertex; drag_particle (-1: none) held by a spring of drag_stiffness
    [N/m] and drag_damping [N s/m]; h [s]. The matrix is assembled and factored in float64 (its
    condition number reaches 1e5-1e6 at 32 segments and a frame step: float32 elimination feeds
    rounding errors of the stiff modes into the soft ones, measured as a growing tip oscillation)."""
    s = wp.tid()
    base = first + s * stride
    slot = s * stride
    kb = wp.float64(bend_stiffness[s])
    hd = wp.float64(h)
    h2 = hd * hd
    one = wp.float64(1.0)
    two = wp.float64(2.0)
    eye = wp.identity(n=3, dtype=wp.float64)
    damp = embed3((hd * wp.float64(bend_damping[s])) * eye)  # h k_b,d [1, -2, 1]^T [1, -2, 1] (x) I
    zero = wp.mat44d()
    # rows are assembled in a window and each written once: at vertex v the elements touch rows
    # v-2 (A, the twist penalty), v-1 (B), v (C) and v+1 (D, started here); row A is then complete
    PA = zero
    EA = zero
    FA = zero
    yA = wp.vec4d()
    PB, yB = row_diagonal(qd, f, mass, base, air_drag, drag_particle, drag_stiffness, drag_damping, hd)
    EB = zero
    FB = zero
    PC, yC = row_diagonal(qd, f, mass, base + 1, air_drag, drag_particle, drag_stiffness, drag_damping, hd)
    EC = zero
    FC = zero
    t = wp.vec3d(safe_normalize(q[base + 1] - q[base]))
    n_prev = wp.vec3d(root_normal[s])
    n = wp.vec3d(transport_normal(root_normal[s], wp.vec3(t)))
    t_prev = t
    b_prev = wp.cross(t, n)
    inv_l_prev = one
    phi_prev = wp.float64(0.0)  # twist rate of the previous frame at v0 [1/s]
    for v in range(1, stride - 1):
        i = base + v
        PD, yD = row_diagonal(qd, f, mass, i + 1, air_drag, drag_particle, drag_stiffness, drag_damping, hd)
        ED = zero
        FD = zero
        l = wp.length(wp.vec3d(q[i]) - wp.vec3d(q[i - 1]))
        inv_l = one / wp.max(l, wp.float64(1.0e-12))
        if v >= 2:
            t_prev = t
            b_prev = wp.cross(t, n)
            n_prev = n
            t = wp.vec3d(safe_normalize(q[i] - q[i - 1]))
            n = wp.vec3d(transport_normal(wp.vec3(n_prev), wp.vec3(t)))
        b = wp.cross(t, n)
        c = wp.vec3d(bend_rest[slot + v])
        tw = twist_terms(n_prev, t, b, t_prev, b_prev, inv_l, inv_l_prev, v)
        # twist recurrence phi_v = alpha phi_(v-1) + a1 . (dx_(v-1) - dx_(v-2)) + a2 . (dx_v - dx_(v-1))
        a1 = tw[1] * n_prev
        a2 = tw[2] * b
        va = wp.vec3d(qd[i - 1])
        vb = wp.vec3d(qd[i])
        vc = wp.vec3d(qd[i + 1])
        phi = tw[0] * phi_prev + wp.dot(a2, vb - va)
        if v >= 2:
            phi = phi + wp.dot(a1, va - wp.vec3d(qd[i - 2]))
        # bending, Gauss-Newton: dr_v = (I + QP) dx_(v-1) - (2 I + QP) dx_v + dx_(v+1) - u phi_v on
        # rows B, C, D (h^2 k_b J^T J, and -h^2 k_b J^T J z0 on the right), and its damper
        QP = (c[0] * eye - c[1] * wp.outer(t, n) - c[2] * cross_matrix(n)) * ((eye - wp.outer(t, t)) * inv_l)
        u = tw[3] * (c[1] * b - c[2] * n)
        j0 = jac34(eye + QP, wp.vec3d())
        j1 = jac34(-two * eye - QP, -u)
        j2 = jac34(eye, wp.vec3d())
        w = h2 * kb
        rho = j0 * four(va, phi_prev) + j1 * four(vb, phi) + j2 * four(vc, wp.float64(0.0))
        t0 = wp.transpose(j0)
        t1 = wp.transpose(j1)
        t2 = wp.transpose(j2)
        PB = PB + w * (t0 * j0) + damp
        EB = EB + w * (t0 * j1) - two * damp
        FB = FB + w * (t0 * j2) + damp
        PC = PC + w * (t1 * j1) + (two * two) * damp
        EC = EC + w * (t1 * j2) - two * damp
        PD = PD + w * (t2 * j2) + damp
        yB = yB - w * (t0 * rho)
        yC = yC - w * (t1 * rho)
        yD = yD - w * (t2 * rho)
        # the twist recurrence's penalty on rows A, B, C (its right-hand side is 0: z0 satisfies it)
        pw = h2 * TWIST_PENALTY * kb * l * l
        c0 = four(a1, wp.float64(0.0))
        c1 = four(a2 - a1, -tw[0])
        c2 = four(-a2, one)
        if v >= 2:
            PA = PA + pw * wp.outer(c0, c0)
            EA = EA + pw * wp.outer(c0, c1)
            FA = FA + pw * wp.outer(c0, c2)
        PB = PB + pw * wp.outer(c1, c1)
        EB = EB + pw * wp.outer(c1, c2)
        PC = PC + pw * wp.outer(c2, c2)
        # stretch spring (v, v + 1) on rows C, D
        Ae, kv = stretch_element(q[i], q[i + 1], vb, vc, wp.float64(rest_length[slot + v]),
                                 wp.float64(stretch_stiffness[s]), wp.float64(stretch_damping[s]), hd)
        PC = PC + Ae
        PD = PD + Ae
        EC = EC - Ae
        yC = yC - kv
        yD = yD + kv
        if v >= 2:  # row A is complete: factor it, its Schur complement goes to rows B and C
            E2, F2, y2 = complete_row(mass, base, slot, stride, v - 2, factor, pinv, up1, up2, rhs, PA, EA, FA, yA)
            E2T = wp.transpose(E2)
            F2T = wp.transpose(F2)
            PB = PB - E2T * E2
            EB = EB - E2T * F2
            yB = yB - E2T * y2
            PC = PC - F2T * F2
            yC = yC - F2T * y2
        PA = PB
        EA = EB
        FA = FB
        yA = yB
        PB = PC
        EB = EC
        FB = FC
        yB = yC
        PC = PD
        EC = ED
        FC = FD
        yC = yD
        phi_prev = phi
        inv_l_prev = inv_l
    E2, F2, y2 = complete_row(mass, base, slot, stride, stride - 3, factor, pinv, up1, up2, rhs, PA, EA, FA, yA)
    E2T = wp.transpose(E2)
    PB = PB - E2T * E2
    EB = EB - E2T * F2
    yB = yB - E2T * y2
    PC = PC - wp.transpose(F2) * F2
    yC = yC - wp.transpose(F2) * y2
    E2, F2, y2 = complete_row(mass, base, slot, stride, stride - 2, factor, pinv, up1, up2, rhs, PB, EB, FB, yB)
    PC = PC - wp.transpose(E2) * E2
    yC = yC - wp.transpose(E2) * y2
    E2, F2, y2 = complete_row(mass, base, slot, stride, stride - 1, factor, pinv, up1, up2, rhs, PC, EC, FC, yC)
    if factor == 0:  # assembly only (tests read the matrix)
        return
    back_substitute(slot, base, stride, pinv, up1, up2, rhs, dv_out)


@wp.kernel
def strand_resolve(
    f: wp.array(dtype=wp.vec3),
    mass: wp.array(dtype=float),
    first: int,
    stride: int,
    h: float,
    pinv: wp.array(dtype=wp.mat44d),
    up1: wp.array(dtype=wp.mat44d),
    up2: wp.array(dtype=wp.mat44d),
    rhs: wp.array(dtype=wp.vec4d),
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
        rhs[slot + v] = four(r, wp.float64(0.0))
    eliminate_rhs(slot, stride, pinv, up1, up2, rhs)
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
