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
4.2), each 4x4 pivot block factored by Cholesky. Cost per strand: O(segments) 4x4 block
operations, in a fixed order (bit-reproducible, no atomics).

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
def add_block(pinv: wp.array(dtype=wp.mat44d), up1: wp.array(dtype=wp.mat44d), up2: wp.array(dtype=wp.mat44d),
              slot: int, a: int, b: int, m: wp.mat44d):
    """Adds ``m`` to the upper band's block (a, b), a <= b <= a + 2, of the strand at ``slot``."""
    if b == a:
        pinv[slot + a] = pinv[slot + a] + m
    elif b == a + 1:
        up1[slot + a] = up1[slot + a] + m
    else:
        up2[slot + a] = up2[slot + a] + m


@wp.func
def add_bending(pinv: wp.array(dtype=wp.mat44d), up1: wp.array(dtype=wp.mat44d), up2: wp.array(dtype=wp.mat44d),
                rhs: wp.array(dtype=wp.vec4d), slot: int, v: int, j0: mat34d, j1: mat34d, j2: mat34d,
                w: wp.float64, z0: wp.vec4d, z1: wp.vec4d, z2: wp.vec4d):
    """Gauss-Newton element w J^T J of bending vertex v (J = [j0, j1, j2] on vertices v-1, v, v+1)
    into the band, and -w J^T (J z) into the right-hand side (z the velocities with their twist
    rates [m/s], [1/s]; w = h^2 k_b [kg])."""
    rho = j0 * z0 + j1 * z1 + j2 * z2
    t0 = wp.transpose(j0)
    t1 = wp.transpose(j1)
    t2 = wp.transpose(j2)
    add_block(pinv, up1, up2, slot, v - 1, v - 1, w * (t0 * j0))
    add_block(pinv, up1, up2, slot, v - 1, v, w * (t0 * j1))
    add_block(pinv, up1, up2, slot, v - 1, v + 1, w * (t0 * j2))
    add_block(pinv, up1, up2, slot, v, v, w * (t1 * j1))
    add_block(pinv, up1, up2, slot, v, v + 1, w * (t1 * j2))
    add_block(pinv, up1, up2, slot, v + 1, v + 1, w * (t2 * j2))
    rhs[slot + v - 1] = rhs[slot + v - 1] - w * (t0 * rho)
    rhs[slot + v] = rhs[slot + v] - w * (t1 * rho)
    rhs[slot + v + 1] = rhs[slot + v + 1] - w * (t2 * rho)


@wp.func
def add_twist_penalty(pinv: wp.array(dtype=wp.mat44d), up1: wp.array(dtype=wp.mat44d),
                      up2: wp.array(dtype=wp.mat44d), slot: int, v: int, c0: wp.vec4d, c1: wp.vec4d, c2: wp.vec4d,
                      w: wp.float64):
    """Penalty w s^2 / 2 on the twist recurrence's residual s = c0 . z[v-2] + c1 . z[v-1] + c2 . z[v]
    (c0 unused for v = 1); its right-hand side is 0 (the twist rates satisfy the recurrence)."""
    if v >= 2:
        add_block(pinv, up1, up2, slot, v - 2, v - 2, w * wp.outer(c0, c0))
        add_block(pinv, up1, up2, slot, v - 2, v - 1, w * wp.outer(c0, c1))
        add_block(pinv, up1, up2, slot, v - 2, v, w * wp.outer(c0, c2))
    add_block(pinv, up1, up2, slot, v - 1, v - 1, w * wp.outer(c1, c1))
    add_block(pinv, up1, up2, slot, v - 1, v, w * wp.outer(c1, c2))
    add_block(pinv, up1, up2, slot, v, v, w * wp.outer(c2, c2))


@wp.func
def add_stretch(pinv: wp.array(dtype=wp.mat44d), up1: wp.array(dtype=wp.mat44d), rhs: wp.array(dtype=wp.vec4d),
                slot: int, v: int, xa: wp.vec3, xb: wp.vec3, va: wp.vec3d, vb: wp.vec3d, rest: wp.float64,
                ks: wp.float64, ds: wp.float64, hd: wp.float64):
    """Stretch spring (v, v + 1): h^2 K_e + h C_e into the band, -h^2 K_e (v0 differences) into the
    right-hand side."""
    u = wp.vec3d(xb) - wp.vec3d(xa)
    l = wp.length(u)
    if l > wp.float64(1.0e-12):
        eye = wp.identity(n=3, dtype=wp.float64)
        d = u / l
        dd = wp.outer(d, d)
        geometric = wp.max(wp.float64(0.0), wp.float64(1.0) - rest / l)
        Ks = ks * (dd + geometric * (eye - dd))
        Ae = embed3(hd * hd * Ks + (hd * ds) * dd)
        pinv[slot + v] = pinv[slot + v] + Ae
        pinv[slot + v + 1] = pinv[slot + v + 1] + Ae
        up1[slot + v] = up1[slot + v] - Ae
        kv = four((hd * hd) * (Ks * (va - vb)), wp.float64(0.0))
        rhs[slot + v] = rhs[slot + v] - kv
        rhs[slot + v + 1] = rhs[slot + v + 1] + kv


@wp.func
def add_bend_damping(pinv: wp.array(dtype=wp.mat44d), up1: wp.array(dtype=wp.mat44d),
                     up2: wp.array(dtype=wp.mat44d), slot: int, v: int, hdb: wp.float64):
    """h C_e of the bending damper of vertex v: h k_b,d [1, -2, 1]^T [1, -2, 1] (x) I."""
    e = embed3(hdb * wp.identity(n=3, dtype=wp.float64))
    two = wp.float64(2.0)
    pinv[slot + v - 1] = pinv[slot + v - 1] + e
    up1[slot + v - 1] = up1[slot + v - 1] - two * e
    up2[slot + v - 1] = up2[slot + v - 1] + e
    pinv[slot + v] = pinv[slot + v] + (two * two) * e
    up1[slot + v] = up1[slot + v] - two * e
    pinv[slot + v + 1] = pinv[slot + v + 1] + e


@wp.func
def pin_vertices(mass: wp.array(dtype=float), base: int, slot: int, stride: int,
                 pinv: wp.array(dtype=wp.mat44d), up1: wp.array(dtype=wp.mat44d), up2: wp.array(dtype=wp.mat44d),
                 rhs: wp.array(dtype=wp.vec4d)):
    """Pinned vertices (mass 0) are not unknowns in x, y, z: identity rows and columns there,
    right-hand side 0 (their velocity entered through K v0); their twist stays an unknown. Twists
    that no element touches (the ghost's, the tip's) get a unit diagonal."""
    keep = wp.mat44d()
    keep[3, 3] = wp.float64(1.0)
    eye3 = embed3(wp.identity(n=3, dtype=wp.float64))
    for v in range(stride):
        if v == 0 or v == stride - 1:
            pinv[slot + v] = pinv[slot + v] + keep
        if mass[base + v] <= 0.0:
            pinv[slot + v] = keep * pinv[slot + v] * keep + eye3
            rhs[slot + v] = keep * rhs[slot + v]
            up1[slot + v] = keep * up1[slot + v]
            up2[slot + v] = keep * up2[slot + v]
            if v >= 1:
                up1[slot + v - 1] = up1[slot + v - 1] * keep
            if v >= 2:
                up2[slot + v - 2] = up2[slot + v - 2] * keep


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
def factor_band(slot: int, stride: int, pinv: wp.array(dtype=wp.mat44d), up1: wp.array(dtype=wp.mat44d),
                up2: wp.array(dtype=wp.mat44d), rhs: wp.array(dtype=wp.vec4d)):
    """Block band Cholesky in place (A = R^T R; pinv := R[v, v]^-1, up1 := R[v, v+1], up2 :=
    R[v, v+2]), solving R^T y = rhs with it. (The block LU with explicit inverses of the pivot
    blocks lost 0.4 % of the residual on a curly 32-segment strand, condition number 2e9; the
    Cholesky factors keep it at 1e-17.)"""
    for v in range(stride):
        Ri = cholesky_inverse(pinv[slot + v])
        pinv[slot + v] = Ri
        RiT = wp.transpose(Ri)
        y = RiT * rhs[slot + v]
        rhs[slot + v] = y
        if v + 1 < stride:
            E = RiT * up1[slot + v]
            up1[slot + v] = E
            ET = wp.transpose(E)
            pinv[slot + v + 1] = pinv[slot + v + 1] - ET * E
            rhs[slot + v + 1] = rhs[slot + v + 1] - ET * y
            if v + 2 < stride:
                F = RiT * up2[slot + v]
                up2[slot + v] = F
                up1[slot + v + 1] = up1[slot + v + 1] - ET * F
                pinv[slot + v + 2] = pinv[slot + v + 2] - wp.transpose(F) * F
                rhs[slot + v + 2] = rhs[slot + v + 2] - wp.transpose(F) * y


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
def init_diagonal(q: wp.array(dtype=wp.vec3), qd: wp.array(dtype=wp.vec3), f: wp.array(dtype=wp.vec3),
                  mass: wp.array(dtype=float), base: int, slot: int, stride: int, air_drag: float,
                  drag_particle: int, drag_stiffness: float, drag_damping: float, hd: wp.float64,
                  pinv: wp.array(dtype=wp.mat44d), up1: wp.array(dtype=wp.mat44d), up2: wp.array(dtype=wp.mat44d),
                  rhs: wp.array(dtype=wp.vec4d)):
    """M + h c_air (+ the drag spring's h c + h^2 k) on the diagonal, h f (- h^2 k v0) on the right."""
    h2 = hd * hd
    eye = wp.identity(n=3, dtype=wp.float64)
    for v in range(stride):
        i = base + v
        diag = (wp.float64(mass[i]) + hd * wp.float64(air_drag)) * eye
        r = hd * wp.vec3d(f[i])
        if i == drag_particle:
            diag = diag + (hd * wp.float64(drag_damping) + h2 * wp.float64(drag_stiffness)) * eye
            r = r - (h2 * wp.float64(drag_stiffness)) * wp.vec3d(qd[i])
        rhs[slot + v] = four(r, wp.float64(0.0))
        pinv[slot + v] = embed3(diag)  # the diagonal until factored
        up1[slot + v] = wp.mat44d()
        up2[slot + v] = wp.mat44d()


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
    and twists (module docstring), factor it in place (pinv, up1, up2) and write the velocity
    change of its free vertices to dv_out [m/s] (``factor`` = 0: assemble only, pinv holding the
    diagonal blocks). f: the full force at (q, qd) [N]; mass [kg] per particle; air_drag: linear
    drag [kg/s] on every free vertex; drag_particle (-1: none) held by a spring of drag_stiffness
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
    init_diagonal(q, qd, f, mass, base, slot, stride, air_drag, drag_particle, drag_stiffness, drag_damping, hd,
                  pinv, up1, up2, rhs)
    t = wp.vec3d(safe_normalize(q[base + 1] - q[base]))
    n_prev = wp.vec3d(root_normal[s])
    n = wp.vec3d(transport_normal(root_normal[s], wp.vec3(t)))
    t_prev = t
    b_prev = wp.cross(t, n)
    inv_l_prev = one
    phi_prev = wp.float64(0.0)  # twist rate of the previous frame at v0 [1/s]
    for v in range(1, stride - 1):
        i = base + v
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
        vpp = wp.vec3d()
        if v >= 2:
            vpp = wp.vec3d(qd[i - 2])
            phi = phi + wp.dot(a1, va - vpp)
        # linearised residual dr_v = (I + QP) dx_(v-1) - (2 I + QP) dx_v + dx_(v+1) - u phi_v
        QP = (c[0] * eye - c[1] * wp.outer(t, n) - c[2] * cross_matrix(n)) * ((eye - wp.outer(t, t)) * inv_l)
        u = tw[3] * (c[1] * b - c[2] * n)
        add_bending(pinv, up1, up2, rhs, slot, v, jac34(eye + QP, wp.vec3d()), jac34(-two * eye - QP, -u),
                    jac34(eye, wp.vec3d()), h2 * kb, four(va, phi_prev), four(vb, phi), four(vc, wp.float64(0.0)))
        penalty = h2 * TWIST_PENALTY * kb * l * l
        add_twist_penalty(pinv, up1, up2, slot, v, four(a1, wp.float64(0.0)), four(a2 - a1, -tw[0]),
                          four(-a2, one), penalty)
        add_bend_damping(pinv, up1, up2, slot, v, hd * wp.float64(bend_damping[s]))
        add_stretch(pinv, up1, rhs, slot, v, q[i], q[i + 1], vb, vc, wp.float64(rest_length[slot + v]),
                    wp.float64(stretch_stiffness[s]), wp.float64(stretch_damping[s]), hd)
        phi_prev = phi
        inv_l_prev = inv_l
    pin_vertices(mass, base, slot, stride, pinv, up1, up2, rhs)
    if factor == 0:  # assembly only (tests read the matrix)
        return
    factor_band(slot, stride, pinv, up1, up2, rhs)
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
