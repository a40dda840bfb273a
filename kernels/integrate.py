"""Time-integration kernels, generic over the coordinate type.

Coordinates ``q`` and velocities ``qd`` are arrays of ``wp.vec3`` (particles) or ``float``
(angle-form systems such as the pendulum); ``f`` holds generalised forces and ``inv_mass`` the
inverse mass per coordinate (0 = pinned/kinematic: its velocity never changes).

Explicit Euler and every Runge-Kutta stage are the same update ``q0 + h v, qd0 + h w f``
(``rk_stage``); semi-implicit Euler updates the velocity first and moves with the new one.
The implicit Euler kernels (residual, filtering, block-Jacobi preconditioner) live here too.
"""

from typing import Any

import warp as wp

wp.set_module_options({"enable_backward": False, "fuse_fp": False})  # no FMA contraction: see world_step.py


@wp.kernel
def rk_stage(
    q0: wp.array(dtype=Any),
    qd0: wp.array(dtype=Any),
    v: wp.array(dtype=Any),
    f: wp.array(dtype=Any),
    inv_mass: wp.array(dtype=float),
    h: float,
    q_out: wp.array(dtype=Any),
    qd_out: wp.array(dtype=Any),
):
    """q_out = q0 + h v; qd_out = qd0 + h inv_mass f (explicit Euler when v = qd0)."""
    i = wp.tid()
    q_out[i] = q0[i] + h * v[i]
    qd_out[i] = qd0[i] + (h * inv_mass[i]) * f[i]


@wp.kernel
def step_semi_implicit_euler(
    q: wp.array(dtype=Any),
    qd: wp.array(dtype=Any),
    f: wp.array(dtype=Any),
    inv_mass: wp.array(dtype=float),
    h: float,
    q_out: wp.array(dtype=Any),
    qd_out: wp.array(dtype=Any),
):
    """qd_out = qd + h inv_mass f; q_out = q + h qd_out (symplectic Euler)."""
    i = wp.tid()
    v = qd[i] + (h * inv_mass[i]) * f[i]
    qd_out[i] = v
    q_out[i] = q[i] + h * v


@wp.kernel
def step_particles_semi_implicit(
    f_acc: wp.array(dtype=wp.vec3),
    mass: wp.array(dtype=float),
    inv_mass: wp.array(dtype=float),
    seed_gravity: wp.vec3,
    h: float,
    q_io: wp.array(dtype=wp.vec3),
    qd_io: wp.array(dtype=wp.vec3),
    f_out: wp.array(dtype=wp.vec3),
    q_prev_out: wp.array(dtype=wp.vec3),
    time_io: wp.array(dtype=float),
    check: int,
    max_speed: float,
    first_bad_out: wp.array(dtype=int),
):
    """The generic Simulator's semi-implicit Euler pass over particles, with what used to be
    separate passes folded in (results bit-identical to them):

    - q_prev_out = q (the start-of-step positions continuous colliders need; skipped when empty);
    - qd = qd + h inv_mass f, q = q + h qd (as ``step_semi_implicit_euler``);
    - f_out = f (the total force of the step; skipped when empty);
    - f_acc = 0 + mass seed_gravity: the force accumulator cleared for the next step and seeded
      with its first force when that is uniform gravity (seed_gravity = 0 otherwise);
    - time_io[0] += h (thread 0; skipped when empty);
    - check != 0: the blow-up test of ``find_blow_up`` (``blown_up``) on the new (q, qd).
    Units: f [N], mass [kg], inv_mass [1/kg], seed_gravity [m/s^2], h [s], q [m], qd [m/s]."""
    i = wp.tid()
    f = f_acc[i]
    x = q_io[i]
    if q_prev_out.shape[0] > 0:
        q_prev_out[i] = x
    v = qd_io[i] + (h * inv_mass[i]) * f
    x = x + h * v
    qd_io[i] = v
    q_io[i] = x
    if f_out.shape[0] > 0:
        f_out[i] = f
    f_acc[i] = wp.vec3() + mass[i] * seed_gravity
    if i == 0 and time_io.shape[0] > 0:
        time_io[0] = time_io[0] + h
    if check != 0:
        if blown_up(x, v, max_speed):
            wp.atomic_min(first_bad_out, 0, i)


@wp.kernel
def seed_forces(mass: wp.array(dtype=float), gravity: wp.vec3, f_out: wp.array(dtype=wp.vec3)):
    """f_out = 0 + mass gravity (the accumulator of ``step_particles_semi_implicit`` seeded)."""
    i = wp.tid()
    f_out[i] = wp.vec3() + mass[i] * gravity


@wp.kernel
def rk_accumulate(
    v: wp.array(dtype=Any),
    f: wp.array(dtype=Any),
    weight: float,
    keep: float,
    v_sum: wp.array(dtype=Any),
    f_sum: wp.array(dtype=Any),
):
    """v_sum = keep v_sum + weight v; f_sum = keep f_sum + weight f (keep = 0 starts a sum)."""
    i = wp.tid()
    v_sum[i] = keep * v_sum[i] + weight * v[i]
    f_sum[i] = keep * f_sum[i] + weight * f[i]


@wp.kernel
def implicit_residual(
    v: wp.array(dtype=Any),
    v0: wp.array(dtype=Any),
    f: wp.array(dtype=Any),
    mass: wp.array(dtype=float),
    inv_mass: wp.array(dtype=float),
    h: float,
    rhs_out: wp.array(dtype=Any),
    dv_out: wp.array(dtype=Any),
):
    """Newton right-hand side h f(x0 + h v, v) - M (v - v0), zero on pinned coordinates;
    also clears the Newton update dv_out (the CG initial guess)."""
    i = wp.tid()
    r = h * f[i] - mass[i] * (v[i] - v0[i])
    if inv_mass[i] == 0.0:
        r = r - r
    rhs_out[i] = r
    dv_out[i] = r - r


@wp.kernel
def implicit_update(
    q0: wp.array(dtype=Any),
    dv: wp.array(dtype=Any),
    h: float,
    v_io: wp.array(dtype=Any),
    q_out: wp.array(dtype=Any),
):
    """v += dv; q_out = q0 + h v."""
    i = wp.tid()
    vi = v_io[i] + dv[i]
    v_io[i] = vi
    q_out[i] = q0[i] + h * vi


@wp.func
def magnitude(x: wp.vec3) -> float:
    return wp.length(x)


@wp.func
def magnitude(x: float) -> float:
    return wp.abs(x)


@wp.func
def block_unit(x: wp.mat33) -> wp.mat33:
    return wp.identity(n=3, dtype=float)


@wp.func
def block_unit(x: float) -> float:
    return 1.0


@wp.func
def block_inverse(x: wp.mat33) -> wp.mat33:
    if wp.abs(wp.determinant(x)) > 1.0e-20:
        return wp.inverse(x)
    return wp.identity(n=3, dtype=float)


@wp.func
def block_inverse(x: float) -> float:
    if wp.abs(x) > 1.0e-20:
        return 1.0 / x
    return 1.0


@wp.kernel
def implicit_system_diagonal(
    jacobian_diag: wp.array(dtype=Any),
    mass: wp.array(dtype=float),
    inv_mass: wp.array(dtype=float),
    rows_out: wp.array(dtype=int),
    cols_out: wp.array(dtype=int),
    values_out: wp.array(dtype=Any),
    inverse_out: wp.array(dtype=Any),
):
    """Diagonal blocks of A = M - h D - h^2 K (jacobian_diag already holds -(h D + h^2 K));
    pinned coordinates get the identity (row and column filtered). Also writes the block-Jacobi
    inverse used as the CG preconditioner. Triplet slots 0..n-1."""
    i = wp.tid()
    unit = block_unit(jacobian_diag[i])
    block = mass[i] * unit + jacobian_diag[i]
    if inv_mass[i] == 0.0:
        block = unit
    rows_out[i] = i
    cols_out[i] = i
    values_out[i] = block
    inverse_out[i] = block_inverse(block)


@wp.kernel
def filter_pinned_triplets(
    rows: wp.array(dtype=int), cols: wp.array(dtype=int), inv_mass: wp.array(dtype=float), values_io: wp.array(dtype=Any)
):
    """Zero coupling blocks that touch a pinned coordinate (keeps A symmetric positive definite)."""
    t = wp.tid()
    if inv_mass[rows[t]] == 0.0 or inv_mass[cols[t]] == 0.0:
        values_io[t] = values_io[t] - values_io[t]


@wp.kernel
def apply_block_preconditioner(
    inverse: wp.array(dtype=Any),
    x: wp.array(dtype=Any),
    y: wp.array(dtype=Any),
    alpha: Any,
    beta: Any,
    z: wp.array(dtype=Any),
):
    """z = alpha P^-1 x + beta y with block-diagonal P^-1."""
    i = wp.tid()
    z[i] = alpha * (inverse[i] * x[i]) + beta * y[i]


@wp.kernel
def advance_time(time: wp.array(dtype=float), dt: float):
    time[0] = time[0] + dt


@wp.func
def finite_zero(x: wp.vec3) -> float:
    """0 when every component of x is finite, NaN otherwise (0 * inf and 0 * NaN are NaN)."""
    return 0.0 * x[0] + 0.0 * x[1] + 0.0 * x[2]


@wp.func
def finite_zero(x: float) -> float:
    return 0.0 * x


@wp.func
def blown_up(x: Any, v: Any, max_speed: float) -> bool:
    """True when x or v has a non-finite component or |v| > max_speed, in one comparison (a NaN
    or inf sum fails "<="); wp.isfinite on two vec3 costs ~10 ns a particle on the CPU, this ~1."""
    return not (magnitude(v) + finite_zero(x) <= max_speed)


@wp.kernel
def find_blow_up(
    q: wp.array(dtype=Any),
    qd: wp.array(dtype=Any),
    max_speed: float,
    first_bad_out: wp.array(dtype=int),
):
    """first_bad_out[0] = smallest index with a non-finite coordinate or speed above max_speed."""
    i = wp.tid()
    if blown_up(q[i], qd[i], max_speed):
        wp.atomic_min(first_bad_out, 0, i)


@wp.kernel
def max_step_displacement(
    qd: wp.array(dtype=Any),
    f: wp.array(dtype=Any),
    inv_mass: wp.array(dtype=float),
    h: float,
    out: wp.array(dtype=float),
):
    """out[0] = max over coordinates of |v| h + |a| h^2 / 2 (adaptive sub-stepping)."""
    i = wp.tid()
    a = inv_mass[i] * f[i]
    d = magnitude(qd[i]) * h + 0.5 * magnitude(a) * h * h
    wp.atomic_max(out, 0, d)


@wp.kernel
def max_abs_difference(a: wp.array(dtype=Any), out: wp.array(dtype=float)):
    """out[0] = max |a_i| (Newton convergence check)."""
    i = wp.tid()
    wp.atomic_max(out, 0, magnitude(a[i]))


# Explicit instances for the two coordinate types, declared at import so nothing compiles late.
for _T, _B in ((wp.vec3, wp.mat33), (float, float)):
    _A = wp.array(dtype=_T)
    _M = wp.array(dtype=_B)
    _F = wp.array(dtype=float)
    wp.overload(rk_stage, [_A, _A, _A, _A, _F, float, _A, _A])
    wp.overload(step_semi_implicit_euler, [_A, _A, _A, _F, float, _A, _A])
    wp.overload(rk_accumulate, [_A, _A, float, float, _A, _A])
    wp.overload(implicit_residual, [_A, _A, _A, _F, _F, float, _A, _A])
    wp.overload(implicit_update, [_A, _A, float, _A, _A])
    wp.overload(implicit_system_diagonal, [_M, _F, _F, wp.array(dtype=int), wp.array(dtype=int), _M, _M])
    wp.overload(filter_pinned_triplets, [wp.array(dtype=int), wp.array(dtype=int), _F, _M])
    wp.overload(apply_block_preconditioner, [_M, _A, _A, float, float, _A])
    wp.overload(find_blow_up, [_A, _A, float, wp.array(dtype=int)])
    wp.overload(max_step_displacement, [_A, _A, _F, float, _F])
    wp.overload(max_abs_difference, [_A, _F])
