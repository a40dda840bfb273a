"""Force kernels: every force accumulates into ``f_out`` (shape (particle_count,), [N]).

Jacobian kernels add ``ck * df/dx + cd * df/dv`` for each force: per-particle diagonal blocks go
into ``diag_out``, coupling blocks between two particles are written as triplets.

Springs are summed per particle (``eval_springs_gather``, ``eval_springs_jacobian_gather``) over
the model's CSR adjacency in a fixed order, so runs are bit-reproducible on every device; the
scatter kernels with float atomics (``eval_springs``, ``eval_springs_jacobian``) remain for the
``deterministic=False`` opt-out and for differentiable runs.
The implicit integrator calls them with ``ck = -h**2`` and ``cd = -h``; tests call them with
``(1, 0)`` and ``(0, 1)`` to compare against finite differences.

Time-dependent forces read the simulation time from a device array ``time`` (shape (1,), [s])
plus a host ``time_offset`` (the stage offset inside a step), so a captured step replays
correctly as time advances.
"""

import warp as wp

wp.set_module_options({"enable_backward": False, "fuse_fp": False})  # no FMA contraction: see world_step.py
# The force kernels a differentiable run records on its wp.Tape (gravity, constant, wind, drag,
# magnets, springs) compile their adjoints too (``enable_backward=True`` per kernel); the rest of
# the module stays forward only.


@wp.func
def outer3(a: wp.vec3, b: wp.vec3) -> wp.mat33:
    return wp.outer(a, b)


# --------------------------------------------------------------------------------------
# Gravity and constant forces
# --------------------------------------------------------------------------------------
@wp.kernel(enable_backward=True)  # differentiable runs (warpsim.diff)
def eval_gravity(mass: wp.array(dtype=float), gravity: wp.vec3, f_out: wp.array(dtype=wp.vec3)):
    """f += m g for every particle (pinned particles have mass 0 and get nothing)."""
    i = wp.tid()
    f_out[i] = f_out[i] + mass[i] * gravity


@wp.kernel(enable_backward=True)  # differentiable runs (warpsim.diff)
def eval_constant_force(indices: wp.array(dtype=int), force: wp.vec3, f_out: wp.array(dtype=wp.vec3)):
    """f[indices[t]] += force."""
    t = wp.tid()
    i = indices[t]
    wp.atomic_add(f_out, i, force)


# --------------------------------------------------------------------------------------
# Wind: air velocity w(t) = speed * (1 + gust(t)) * dir(t); force = c (w(t) - v)
# --------------------------------------------------------------------------------------
@wp.func
def wind_velocity(
    t: float,
    direction: wp.vec3,
    speed: float,
    gust_amplitude: float,
    gust_frequency: float,
    gust_phase: wp.vec3,
    turn_amplitude: float,
    turn_frequency: float,
) -> wp.vec3:
    """Air velocity [m/s] at time t [s]: gusts are a sum of three incommensurate sines
    (weights 1, 0.5, 0.25; frequencies f, 2.13 f, 4.37 f; phases gust_phase), normalised to [-1, 1];
    the direction turns about +Y by turn_amplitude * sin(2 pi turn_frequency t) radians."""
    two_pi = 6.283185307179586
    g = (
        wp.sin(two_pi * gust_frequency * t + gust_phase[0])
        + 0.5 * wp.sin(two_pi * 2.13 * gust_frequency * t + gust_phase[1])
        + 0.25 * wp.sin(two_pi * 4.37 * gust_frequency * t + gust_phase[2])
    ) / 1.75
    a = turn_amplitude * wp.sin(two_pi * turn_frequency * t)
    c = wp.cos(a)
    s = wp.sin(a)
    d = wp.vec3(c * direction[0] + s * direction[2], direction[1], -s * direction[0] + c * direction[2])
    return speed * (1.0 + gust_amplitude * g) * d


@wp.kernel(enable_backward=True)  # differentiable runs (warpsim.diff)
def eval_wind(
    qd: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    time: wp.array(dtype=float),
    time_offset: float,
    direction: wp.vec3,
    speed: float,
    gust_amplitude: float,
    gust_frequency: float,
    gust_phase: wp.vec3,
    turn_amplitude: float,
    turn_frequency: float,
    coefficient: float,
    f_out: wp.array(dtype=wp.vec3),
):
    """f += c (w(t) - v) on every dynamic particle; c [kg/s]."""
    i = wp.tid()
    if inv_mass[i] == 0.0:
        return
    w = wind_velocity(
        time[0] + time_offset, direction, speed, gust_amplitude, gust_frequency, gust_phase,
        turn_amplitude, turn_frequency,
    )
    f_out[i] = f_out[i] + coefficient * (w - qd[i])


# --------------------------------------------------------------------------------------
# Drag: f = -c1 v - c2 |v| v
# --------------------------------------------------------------------------------------
@wp.kernel(enable_backward=True)  # differentiable runs (warpsim.diff)
def eval_drag(
    qd: wp.array(dtype=wp.vec3), linear: float, quadratic: float, f_out: wp.array(dtype=wp.vec3)
):
    i = wp.tid()
    v = qd[i]
    f_out[i] = f_out[i] - (linear + quadratic * wp.length(v)) * v


@wp.kernel
def eval_drag_jacobian(
    qd: wp.array(dtype=wp.vec3), linear: float, quadratic: float, cd: float, diag_out: wp.array(dtype=wp.mat33)
):
    """df/dv = -c1 I - c2 (|v| I + v v^T / |v|)."""
    i = wp.tid()
    v = qd[i]
    s = wp.length(v)
    J = -(linear + quadratic * s) * wp.identity(n=3, dtype=float)
    if s > 0.0:
        J = J - quadratic * outer3(v, v) / s
    wp.atomic_add(diag_out, i, cd * J)


@wp.kernel
def eval_scaled_identity_jacobian(coefficient: float, c: float, diag_out: wp.array(dtype=wp.mat33)):
    """Adds c * coefficient * I to every diagonal block (e.g. wind's df/dv = -c_w I)."""
    i = wp.tid()
    wp.atomic_add(diag_out, i, (c * coefficient) * wp.identity(n=3, dtype=float))


# --------------------------------------------------------------------------------------
# Magnets: f = s d / (|d|^2 + eps^2)^(3/2), d = center - x; zero beyond the cutoff
# --------------------------------------------------------------------------------------
@wp.kernel(enable_backward=True)  # differentiable runs (warpsim.diff)
def eval_magnets(
    q: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    centers: wp.array(dtype=wp.vec3),
    strengths: wp.array(dtype=float),
    softening: float,
    cutoff: float,
    f_out: wp.array(dtype=wp.vec3),
):
    """Attractors (s > 0) and repellers (s < 0), s [N m^2]; cutoff <= 0 means none."""
    i = wp.tid()
    if inv_mass[i] == 0.0:
        return
    f = wp.vec3()
    for m in range(centers.shape[0]):
        d = centers[m] - q[i]
        r2 = wp.dot(d, d)
        if cutoff <= 0.0 or r2 < cutoff * cutoff:
            s2 = r2 + softening * softening
            f = f + strengths[m] * d / (s2 * wp.sqrt(s2))
    f_out[i] = f_out[i] + f


@wp.kernel
def eval_magnets_jacobian(
    q: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    centers: wp.array(dtype=wp.vec3),
    strengths: wp.array(dtype=float),
    softening: float,
    cutoff: float,
    ck: float,
    diag_out: wp.array(dtype=wp.mat33),
):
    """df/dx = -s (I / s2^(3/2) - 3 d d^T / s2^(5/2)), s2 = |d|^2 + eps^2."""
    i = wp.tid()
    if inv_mass[i] == 0.0:
        return
    J = wp.mat33()
    for m in range(centers.shape[0]):
        d = centers[m] - q[i]
        r2 = wp.dot(d, d)
        if cutoff <= 0.0 or r2 < cutoff * cutoff:
            s2 = r2 + softening * softening
            s3 = s2 * wp.sqrt(s2)
            J = J - strengths[m] * (wp.identity(n=3, dtype=float) / s3 - 3.0 * outer3(d, d) / (s3 * s2))
    wp.atomic_add(diag_out, i, ck * J)


# --------------------------------------------------------------------------------------
# Damped springs: f_i = -(k (l - L) + kd dl/dt) d_hat, f_j = -f_i
# --------------------------------------------------------------------------------------
@wp.kernel(enable_backward=True)  # differentiable runs (warpsim.diff)
def eval_springs(
    q: wp.array(dtype=wp.vec3),
    qd: wp.array(dtype=wp.vec3),
    spring_indices: wp.array(dtype=int),
    spring_rest_length: wp.array(dtype=float),
    spring_stiffness: wp.array(dtype=float),
    spring_damping: wp.array(dtype=float),
    spring_broken: wp.array(dtype=int),
    f_out: wp.array(dtype=wp.vec3),
):
    """Broken springs (spring_broken[s] != 0, see kernels/fracture.py) exert nothing."""
    s = wp.tid()
    if spring_broken[s] != 0:
        return
    i = spring_indices[2 * s]
    j = spring_indices[2 * s + 1]
    u = q[i] - q[j]
    l = wp.length(u)
    if l < 1.0e-12:
        return
    d = u / l
    dldt = wp.dot(qd[i] - qd[j], d)
    f = -(spring_stiffness[s] * (l - spring_rest_length[s]) + spring_damping[s] * dldt) * d
    wp.atomic_add(f_out, i, f)
    wp.atomic_sub(f_out, j, f)


@wp.func
def damped_spring_force(xi: wp.vec3, xj: wp.vec3, vi: wp.vec3, vj: wp.vec3, rest: float, k: float,
                        kd: float) -> wp.vec3:
    """Force [N] on end i of a damped spring (end j gets minus it); zero for coincident ends. The
    same arithmetic as ``eval_springs``, so gathers and scatters agree term by term."""
    u = xi - xj
    l = wp.length(u)
    if l < 1.0e-12:
        return wp.vec3()
    d = u / l
    dldt = wp.dot(vi - vj, d)
    return -(k * (l - rest) + kd * dldt) * d


@wp.kernel
def eval_springs_gather(
    q: wp.array(dtype=wp.vec3),
    qd: wp.array(dtype=wp.vec3),
    spring_indices: wp.array(dtype=int),
    spring_rest_length: wp.array(dtype=float),
    spring_stiffness: wp.array(dtype=float),
    spring_damping: wp.array(dtype=float),
    spring_broken: wp.array(dtype=int),
    particle_spring_offsets: wp.array(dtype=int),
    particle_springs: wp.array(dtype=int),
    f_out: wp.array(dtype=wp.vec3),
):
    """Per particle i: f_out[i] += the forces of the springs touching it, summed in the fixed
    order of its CSR row (ascending spring index): no atomics, the same bits every run.
    Spring s's force is evaluated from its end 2s (as ``eval_springs``) and negated at end 2s+1."""
    i = wp.tid()
    f = wp.vec3()
    for a in range(particle_spring_offsets[i], particle_spring_offsets[i + 1]):
        s = particle_springs[a]
        if spring_broken[s] == 0:
            si = spring_indices[2 * s]
            sj = spring_indices[2 * s + 1]
            fs = damped_spring_force(q[si], q[sj], qd[si], qd[sj], spring_rest_length[s], spring_stiffness[s],
                                     spring_damping[s])
            if si == i:
                f = f + fs
            else:
                f = f - fs
    f_out[i] = f_out[i] + f


@wp.func
def spring_block(
    u: wp.vec3, v: wp.vec3, rest: float, k: float, kd: float, ck: float, cd: float, exact: int
) -> wp.mat33:
    """ck df_i/dx_i + cd df_i/dv_i for one spring, u = x_i - x_j, v = v_i - v_j.

    exact=1: the true Jacobian (damping's position derivative included, may be indefinite and
    non-symmetric). exact=0: the solver's form, symmetric and negative semi-definite: damping's
    position derivative dropped and the geometric term (1 - L/l)(I - d d^T) clamped at 0 under
    compression."""
    l = wp.length(u)
    if l < 1.0e-12:
        return wp.mat33()
    d = u / l
    I = wp.identity(n=3, dtype=float)
    dd = outer3(d, d)
    P = (I - dd) / l
    Jx = wp.mat33()
    if exact == 1:
        s = k * (l - rest) + kd * wp.dot(v, d)
        Jx = -(k * dd + kd * outer3(d, P * v) + s * P)
    else:
        Jx = -k * (dd + wp.max(1.0 - rest / l, 0.0) * (I - dd))
    Jv = -kd * dd
    return ck * Jx + cd * Jv


@wp.kernel
def eval_springs_jacobian(
    q: wp.array(dtype=wp.vec3),
    qd: wp.array(dtype=wp.vec3),
    spring_indices: wp.array(dtype=int),
    spring_rest_length: wp.array(dtype=float),
    spring_stiffness: wp.array(dtype=float),
    spring_damping: wp.array(dtype=float),
    spring_broken: wp.array(dtype=int),
    ck: float,
    cd: float,
    exact: int,
    diag_out: wp.array(dtype=wp.mat33),
    rows_out: wp.array(dtype=int),
    cols_out: wp.array(dtype=int),
    values_out: wp.array(dtype=wp.mat33),
):
    """Diagonal blocks (i,i), (j,j) += J; coupling triplets (i,j), (j,i) = -J at 2s, 2s+1. A broken
    spring leaves the Jacobian: J = 0 (its triplets stay, with zero blocks, so the sparsity
    pattern and a captured graph do not change)."""
    s = wp.tid()
    i = spring_indices[2 * s]
    j = spring_indices[2 * s + 1]
    J = wp.mat33()
    if spring_broken[s] == 0:
        J = spring_block(
            q[i] - q[j], qd[i] - qd[j], spring_rest_length[s], spring_stiffness[s], spring_damping[s], ck, cd, exact
        )
    wp.atomic_add(diag_out, i, J)
    wp.atomic_add(diag_out, j, J)
    rows_out[2 * s] = i
    cols_out[2 * s] = j
    values_out[2 * s] = -J
    rows_out[2 * s + 1] = j
    cols_out[2 * s + 1] = i
    values_out[2 * s + 1] = -J


@wp.kernel
def eval_springs_jacobian_gather(
    q: wp.array(dtype=wp.vec3),
    qd: wp.array(dtype=wp.vec3),
    spring_indices: wp.array(dtype=int),
    spring_rest_length: wp.array(dtype=float),
    spring_stiffness: wp.array(dtype=float),
    spring_damping: wp.array(dtype=float),
    spring_broken: wp.array(dtype=int),
    particle_spring_offsets: wp.array(dtype=int),
    particle_springs: wp.array(dtype=int),
    ck: float,
    cd: float,
    exact: int,
    diag_out: wp.array(dtype=wp.mat33),
    rows_out: wp.array(dtype=int),
    cols_out: wp.array(dtype=int),
    values_out: wp.array(dtype=wp.mat33),
):
    """``eval_springs_jacobian`` per particle, without atomics: diag_out[i] += the blocks J of the
    springs touching i in CSR order; spring s's triplets (2s, 2s+1) are written by the thread of
    its end 2s."""
    i = wp.tid()
    D = wp.mat33()
    for a in range(particle_spring_offsets[i], particle_spring_offsets[i + 1]):
        s = particle_springs[a]
        si = spring_indices[2 * s]
        sj = spring_indices[2 * s + 1]
        J = wp.mat33()
        if spring_broken[s] == 0:
            J = spring_block(
                q[si] - q[sj], qd[si] - qd[sj], spring_rest_length[s], spring_stiffness[s], spring_damping[s], ck,
                cd, exact
            )
        D = D + J
        if si == i:
            rows_out[2 * s] = si
            cols_out[2 * s] = sj
            values_out[2 * s] = -J
            rows_out[2 * s + 1] = sj
            cols_out[2 * s + 1] = si
            values_out[2 * s + 1] = -J
    diag_out[i] = diag_out[i] + D


@wp.kernel
def eval_spring_force_entries(
    q: wp.array(dtype=wp.vec3),
    qd: wp.array(dtype=wp.vec3),
    spring_indices: wp.array(dtype=int),
    spring_rest_length: wp.array(dtype=float),
    spring_stiffness: wp.array(dtype=float),
    spring_damping: wp.array(dtype=float),
    spring_broken: wp.array(dtype=int),
    spring_entries: wp.array(dtype=wp.vec2i),
    entry_f_out: wp.array(dtype=wp.vec3),
):
    """Per spring s: its force [N] on end 2s (zero when broken) into entry_f_out at
    spring_entries[s][0], minus it at spring_entries[s][1]: the positions of (end, s) in the CSR
    list ``particle_springs``, so that ``sum_spring_entries`` reads each particle's row
    contiguously. Each entry has one writer: no atomics."""
    s = wp.tid()
    f = wp.vec3()
    if spring_broken[s] == 0:
        i = spring_indices[2 * s]
        j = spring_indices[2 * s + 1]
        f = damped_spring_force(q[i], q[j], qd[i], qd[j], spring_rest_length[s], spring_stiffness[s],
                                spring_damping[s])
    e = spring_entries[s]
    entry_f_out[e[0]] = f
    entry_f_out[e[1]] = -f


@wp.kernel
def sum_spring_entries(
    particle_spring_offsets: wp.array(dtype=int),
    entry_f: wp.array(dtype=wp.vec3),
    f_out: wp.array(dtype=wp.vec3),
):
    """Per particle i: f_out[i] += its CSR row of entry_f summed in order: the same bits as
    ``eval_springs_gather`` (f - x is f + (-x); a broken spring's +0 never changes a sum that
    starts at +0), with each spring evaluated once (``eval_spring_force_entries``) and the row
    read contiguously."""
    i = wp.tid()
    f = wp.vec3()
    for a in range(particle_spring_offsets[i], particle_spring_offsets[i + 1]):
        f = f + entry_f[a]
    f_out[i] = f_out[i] + f


# --------------------------------------------------------------------------------------
# User force fields: f = field(x, v, t), a @wp.func of (wp.vec3, wp.vec3, float) -> wp.vec3
# --------------------------------------------------------------------------------------
_field_kernels = {}


def force_field_kernels(field):
    """(eval kernel, jacobian kernel) for a user @wp.func, built once per function (cached).

    The Jacobian is taken by central differences with step ``eps`` [m or m/s] and symmetrised,
    since the implicit solve needs a symmetric matrix."""
    if field in _field_kernels:
        return _field_kernels[field]

    def eval_force_field(
        q: wp.array(dtype=wp.vec3),
        qd: wp.array(dtype=wp.vec3),
        inv_mass: wp.array(dtype=float),
        time: wp.array(dtype=float),
        time_offset: float,
        f_out: wp.array(dtype=wp.vec3),
    ):
        i = wp.tid()
        if inv_mass[i] == 0.0:
            return
        f_out[i] = f_out[i] + field(q[i], qd[i], time[0] + time_offset)

    def eval_force_field_jacobian(
        q: wp.array(dtype=wp.vec3),
        qd: wp.array(dtype=wp.vec3),
        inv_mass: wp.array(dtype=float),
        time: wp.array(dtype=float),
        time_offset: float,
        eps: float,
        ck: float,
        cd: float,
        diag_out: wp.array(dtype=wp.mat33),
    ):
        i = wp.tid()
        if inv_mass[i] == 0.0:
            return
        t = time[0] + time_offset
        x = q[i]
        v = qd[i]
        Jx = wp.mat33()
        Jv = wp.mat33()
        for c in range(3):
            e = wp.vec3()
            e[c] = eps
            dfx = (field(x + e, v, t) - field(x - e, v, t)) / (2.0 * eps)
            dfv = (field(x, v + e, t) - field(x, v - e, t)) / (2.0 * eps)
            for r in range(3):
                Jx[r, c] = dfx[r]
                Jv[r, c] = dfv[r]
        J = ck * Jx + cd * Jv
        wp.atomic_add(diag_out, i, 0.5 * (J + wp.transpose(J)))

    kernels = (
        wp.kernel(eval_force_field, enable_backward=False, module="unique"),
        wp.kernel(eval_force_field_jacobian, enable_backward=False, module="unique"),
    )
    _field_kernels[field] = kernels
    return kernels


# --------------------------------------------------------------------------------------
# Angle-form pendulum: q'' = -(g / l) sin q  (unit generalised mass, f = angular acceleration)
# --------------------------------------------------------------------------------------
@wp.kernel
def eval_pendulum(q: wp.array(dtype=float), g_over_l: wp.array(dtype=float), f_out: wp.array(dtype=float)):
    i = wp.tid()
    f_out[i] = f_out[i] - g_over_l[i] * wp.sin(q[i])


@wp.kernel
def eval_pendulum_jacobian(
    q: wp.array(dtype=float), g_over_l: wp.array(dtype=float), ck: float, diag_out: wp.array(dtype=float)
):
    """df/dq = -(g / l) cos q."""
    i = wp.tid()
    diag_out[i] = diag_out[i] - ck * g_over_l[i] * wp.cos(q[i])


@wp.kernel
def eval_pendulum_energy(
    q: wp.array(dtype=float),
    qd: wp.array(dtype=float),
    mass: wp.array(dtype=float),
    length: wp.array(dtype=float),
    gravity: float,
    kinetic_out: wp.array(dtype=float),
    potential_out: wp.array(dtype=float),
):
    """Kinetic m l^2 qd^2 / 2 and potential m g l (1 - cos q) energy [J] per pendulum."""
    i = wp.tid()
    l = length[i]
    kinetic_out[i] = 0.5 * mass[i] * l * l * qd[i] * qd[i]
    potential_out[i] = mass[i] * gravity * l * (1.0 - wp.cos(q[i]))
