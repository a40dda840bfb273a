"""Cloth kernels: fused explicit steps and the Baraff-Witkin implicit system assembly.

Springs: f_i = -(k (l - L) + kd dl/dt) d, d = (x_i - x_j) / l, f_j = -f_i, with Jacobians
  Jx = df_i/dx_i = -k (d d^T + g (1 - L/l) (I - d d^T)),  Jv = df_i/dv_i = -kd d d^T,
  df_i/dx_j = -Jx, df_i/dv_j = -Jv (damping's position derivative dropped, as in Baraff-Witkin).
The geometric factor g (1 - L/l) is clamped at 0 under compression (``full_geometric`` = 0) so
every block is symmetric negative semi-definite and the system matrix stays positive definite.

Implicit system (one Newton iteration = Baraff & Witkin 1998):
  A dv = b,  A = M - h D - h^2 K,  b = h f(x, v) + h^2 K w - M (v - v0)
with w = v0 on the first iteration (x = x0, v = v0: exactly BW's h (f0 + h K v0)) and w = 0 on
later Newton iterations of backward Euler. Blocks go straight into the values of a fixed-topology
``warp.sparse`` BSR matrix through precomputed slots; pinned rows and columns are filtered.
"""

from typing import Any

import warp as wp

from .forces import damped_spring_force
from .integrate import block_inverse

wp.set_module_options({"enable_backward": False})


@wp.func
def spring_force(xij: wp.vec3, vij: wp.vec3, rest: float, k: float, kd: float) -> wp.vec3:
    """Force on end i of a damped spring, xij = x_i - x_j, vij = v_i - v_j (zero for coincident
    ends; branch-free so that unrolled callers keep their loads together)."""
    l = wp.length(xij)
    d = xij * wp.where(l > 1.0e-12, 1.0 / l, 0.0)
    return -(k * (l - rest) + kd * wp.dot(vij, d)) * d


@wp.func
def spring_jacobians(xij: wp.vec3, rest: float, k: float, kd: float, full_geometric: int):
    """(Jx, Jv) = (df_i/dx_i, df_i/dv_i) of one spring (module docstring)."""
    l = wp.length(xij)
    if l < 1.0e-12:
        return wp.mat33(), wp.mat33()
    d = xij / l
    dd = wp.outer(d, d)
    g = 1.0 - rest / l
    if full_geometric == 0:
        g = wp.max(g, 0.0)
    Jx = -k * (dd + g * (wp.identity(n=3, dtype=float) - dd))
    return Jx, -kd * dd


# --------------------------------------------------------------------------------------
# Explicit (semi-implicit Euler) steps
# --------------------------------------------------------------------------------------
@wp.kernel
def integrate_cloth_particles(
    f_io: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    gravity: wp.vec3,
    h: float,
    q_io: wp.array(dtype=wp.vec3),
    qd_io: wp.array(dtype=wp.vec3),
):
    """v += h (f / m + g), x += h v on free particles (pinned ones keep their velocity); clears
    f for the next step's scatter."""
    i = wp.tid()
    v = cloth_velocity(qd_io[i], f_io[i], inv_mass[i], gravity, h)
    qd_io[i] = v
    q_io[i] = q_io[i] + h * v
    f_io[i] = wp.vec3()


@wp.func
def cloth_velocity(v: wp.vec3, f: wp.vec3, w: float, gravity: wp.vec3, h: float) -> wp.vec3:
    """v + h (w f + g) for a free particle (inverse mass w > 0); a pinned one keeps v."""
    if w > 0.0:
        return v + h * (w * f + gravity)
    return v


@wp.func
def adjacent_entry(adjacency: wp.array(dtype=wp.vec4), table: wp.array(dtype=wp.vec3), a: int):
    """Entry a of a wide adjacency list: (rest, k, kd, other end as a float, exact below 2^24) ->
    (other end, (rest, k, kd)); one 16-byte load."""
    e = adjacency[a]
    return int(e[3]), wp.vec3(e[0], e[1], e[2])


@wp.func
def adjacent_entry(adjacency: wp.array(dtype=wp.uint32), table: wp.array(dtype=wp.vec3), a: int):
    """Entry a of a packed adjacency list: (other end << 8) | spring type -> (other end,
    table[type] = (rest, k, kd)); one 4-byte load plus a lookup in a small cached table."""
    e = adjacency[a]
    return int(e >> wp.uint32(8)), table[int(e & wp.uint32(255))]


@wp.func
def adjacent_forces4(
    x: wp.vec3, v: wp.vec3, q: wp.array(dtype=wp.vec3), qd: wp.array(dtype=wp.vec3),
    adjacency: wp.array(dtype=Any), table: wp.array(dtype=wp.vec3), a: int,
) -> wp.vec3:
    """Summed force on a particle at (x, v) from adjacency entries a .. a + 3; all loads are
    issued before any arithmetic so that they are in flight together."""
    j0, p0 = adjacent_entry(adjacency, table, a)
    j1, p1 = adjacent_entry(adjacency, table, a + 1)
    j2, p2 = adjacent_entry(adjacency, table, a + 2)
    j3, p3 = adjacent_entry(adjacency, table, a + 3)
    x0 = q[j0]
    x1 = q[j1]
    x2 = q[j2]
    x3 = q[j3]
    v0 = qd[j0]
    v1 = qd[j1]
    v2 = qd[j2]
    v3 = qd[j3]
    f0 = spring_force(x - x0, v - v0, p0[0], p0[1], p0[2])
    f1 = spring_force(x - x1, v - v1, p1[0], p1[1], p1[2])
    f2 = spring_force(x - x2, v - v2, p2[0], p2[1], p2[2])
    f3 = spring_force(x - x3, v - v3, p3[0], p3[1], p3[2])
    return (f0 + f1) + (f2 + f3)


@wp.kernel
def step_cloth_gather(
    q: wp.array(dtype=wp.vec3),
    qd: wp.array(dtype=wp.vec3),
    f_ext: wp.array(dtype=wp.vec3),
    use_f_ext: int,
    adjacency_offsets: wp.array(dtype=int),
    adjacency: wp.array(dtype=Any),
    table: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    gravity: wp.vec3,
    h: float,
    q_out: wp.array(dtype=wp.vec3),
    qd_out: wp.array(dtype=wp.vec3),
):
    """One semi-implicit Euler step, particle-centric: sums the forces of the springs touching
    particle i (entries adjacency_offsets[i] .. [i + 1] of ``adjacency``, packed uint32 with a
    parameter ``table`` or wide vec4, see ``adjacent_entry``) plus f_ext, then writes the new
    state to q_out / qd_out (no atomics; q, qd are read-only so the outputs must be other
    arrays). Four springs at a time, loads first."""
    i = wp.tid()
    x = q[i]
    v = qd[i]
    w = inv_mass[i]
    if w > 0.0:
        f = wp.vec3()
        if use_f_ext != 0:
            f = f_ext[i]
        a = adjacency_offsets[i]
        end = adjacency_offsets[i + 1]
        while a + 4 <= end:
            f = f + adjacent_forces4(x, v, q, qd, adjacency, table, a)
            a += 4
        while a < end:
            j, p = adjacent_entry(adjacency, table, a)
            f = f + spring_force(x - q[j], v - qd[j], p[0], p[1], p[2])
            a += 1
        v = v + h * (w * f + gravity)
    qd_out[i] = v
    q_out[i] = x + h * v


for _adjacency in (wp.array(dtype=wp.vec4), wp.array(dtype=wp.uint32)):
    _V = wp.array(dtype=wp.vec3)
    wp.overload(step_cloth_gather, [_V, _V, _V, int, wp.array(dtype=int), _adjacency, _V, wp.array(dtype=float),
                                    wp.vec3, float, _V, _V])


@wp.func
def owned_spring_force(
    x: wp.vec3, v: wp.vec3, q: wp.array(dtype=wp.vec3), qd: wp.array(dtype=wp.vec3), e: wp.vec4i,
    rest: wp.array(dtype=float), stiffness: wp.array(dtype=float), damping: wp.array(dtype=float),
    entry_f_out: wp.array(dtype=wp.vec3),
):
    """The spring s of owned entry e = (other end j, s, the owner's CSR entry, j's CSR entry):
    its force on the owner (at x, v) and minus it written to the two entries (the arithmetic of
    ``damped_spring_force``, whose result only changes sign with the end)."""
    s = e[1]
    fs = damped_spring_force(x, q[e[0]], v, qd[e[0]], rest[s], stiffness[s], damping[s])
    entry_f_out[e[2]] = fs
    entry_f_out[e[3]] = -fs


@wp.kernel
def eval_cloth_owned_springs(
    q: wp.array(dtype=wp.vec3),
    qd: wp.array(dtype=wp.vec3),
    owned_offsets: wp.array(dtype=int),
    owned: wp.array(dtype=wp.vec4i),
    spring_rest_length: wp.array(dtype=float),
    spring_stiffness: wp.array(dtype=float),
    spring_damping: wp.array(dtype=float),
    entry_f_out: wp.array(dtype=wp.vec3),
):
    """"owner" step, pass 1: thread i evaluates once each spring it owns (i is its lower end):
    entries owned_offsets[i] .. [i + 1] of ``owned`` = (other end j, spring s, i's entry, j's
    entry in the CSR list ``particle_springs``); the force [N] on i and on j go to those entries
    of entry_f_out. Spring parameters are read from the model's arrays (rest [m], k [N/m],
    kd [N s/m]), so changes in place take effect. Each entry has one writer: no atomics. Four
    springs at a time, their entries loaded first."""
    i = wp.tid()
    x = q[i]
    v = qd[i]
    a = owned_offsets[i]
    end = owned_offsets[i + 1]
    while a + 4 <= end:
        e0 = owned[a]
        e1 = owned[a + 1]
        e2 = owned[a + 2]
        e3 = owned[a + 3]
        owned_spring_force(x, v, q, qd, e0, spring_rest_length, spring_stiffness, spring_damping, entry_f_out)
        owned_spring_force(x, v, q, qd, e1, spring_rest_length, spring_stiffness, spring_damping, entry_f_out)
        owned_spring_force(x, v, q, qd, e2, spring_rest_length, spring_stiffness, spring_damping, entry_f_out)
        owned_spring_force(x, v, q, qd, e3, spring_rest_length, spring_stiffness, spring_damping, entry_f_out)
        a += 4
    while a < end:
        owned_spring_force(x, v, q, qd, owned[a], spring_rest_length, spring_stiffness, spring_damping, entry_f_out)
        a += 1


@wp.kernel
def step_cloth_owned(
    q: wp.array(dtype=wp.vec3),
    qd: wp.array(dtype=wp.vec3),
    f_ext: wp.array(dtype=wp.vec3),
    use_f_ext: int,
    particle_spring_offsets: wp.array(dtype=int),
    entry_f: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    gravity: wp.vec3,
    h: float,
    q_out: wp.array(dtype=wp.vec3),
    qd_out: wp.array(dtype=wp.vec3),
):
    """"owner" step, pass 2: the spring forces of particle i's CSR row of entry_f summed in
    order (contiguous reads, four loads at a time), added to f_ext[i] (when used), then
    v += h (f / m + g), x += h v written to q_out / qd_out (other arrays than q, qd): the sums,
    and so the bits, of the scatter mode (``ws.Springs`` + ``integrate_cloth_particles``)."""
    i = wp.tid()
    x = q[i]
    v = qd[i]
    w = inv_mass[i]
    if w > 0.0:
        f = wp.vec3()
        a = particle_spring_offsets[i]
        end = particle_spring_offsets[i + 1]
        while a + 4 <= end:
            g0 = entry_f[a]
            g1 = entry_f[a + 1]
            g2 = entry_f[a + 2]
            g3 = entry_f[a + 3]
            f = f + g0
            f = f + g1
            f = f + g2
            f = f + g3
            a += 4
        while a < end:
            f = f + entry_f[a]
            a += 1
        if use_f_ext != 0:
            f = f_ext[i] + f
        v = cloth_velocity(v, f, w, gravity, h)
    qd_out[i] = v
    q_out[i] = x + h * v


# --------------------------------------------------------------------------------------
# Implicit system assembly
# --------------------------------------------------------------------------------------
@wp.kernel
def assemble_cloth_springs(
    q: wp.array(dtype=wp.vec3),
    qd: wp.array(dtype=wp.vec3),
    w: wp.array(dtype=wp.vec3),
    spring_indices: wp.array(dtype=int),
    spring_rest_length: wp.array(dtype=float),
    spring_stiffness: wp.array(dtype=float),
    spring_damping: wp.array(dtype=float),
    spring_broken: wp.array(dtype=int),
    spring_slots: wp.array(dtype=int),
    inv_mass: wp.array(dtype=float),
    ck: float,
    cd: float,
    cf: float,
    cw: float,
    full_geometric: int,
    rhs_io: wp.array(dtype=wp.vec3),
    diag_io: wp.array(dtype=wp.mat33),
    values_io: wp.array(dtype=wp.mat33),
):
    """Per spring: diagonal blocks (i,i), (j,j) += J = ck Jx + cd Jv into diag_io; coupling blocks
    (i,j), (j,i) += -J into the BSR values at spring_slots[2s], [2s+1] unless an end is pinned;
    rhs_i += cf f_i + cw Jx (w_i - w_j), rhs_j -= the same. Broken springs add nothing."""
    s = wp.tid()
    if spring_broken[s] != 0:
        return
    i = spring_indices[2 * s]
    j = spring_indices[2 * s + 1]
    xij = q[i] - q[j]
    rest = spring_rest_length[s]
    k = spring_stiffness[s]
    kd = spring_damping[s]
    Jx, Jv = spring_jacobians(xij, rest, k, kd, full_geometric)
    J = ck * Jx + cd * Jv
    wp.atomic_add(diag_io, i, J)
    wp.atomic_add(diag_io, j, J)
    if inv_mass[i] > 0.0 and inv_mass[j] > 0.0:
        wp.atomic_sub(values_io, spring_slots[2 * s], J)
        wp.atomic_sub(values_io, spring_slots[2 * s + 1], J)
    r = cf * spring_force(xij, qd[i] - qd[j], rest, k, kd) + cw * (Jx * (w[i] - w[j]))
    wp.atomic_add(rhs_io, i, r)
    wp.atomic_sub(rhs_io, j, r)


@wp.kernel
def assemble_cloth_springs_gather(
    q: wp.array(dtype=wp.vec3),
    qd: wp.array(dtype=wp.vec3),
    w: wp.array(dtype=wp.vec3),
    spring_indices: wp.array(dtype=int),
    spring_rest_length: wp.array(dtype=float),
    spring_stiffness: wp.array(dtype=float),
    spring_damping: wp.array(dtype=float),
    spring_broken: wp.array(dtype=int),
    spring_slots: wp.array(dtype=int),
    particle_spring_offsets: wp.array(dtype=int),
    particle_springs: wp.array(dtype=int),
    inv_mass: wp.array(dtype=float),
    ck: float,
    cd: float,
    cf: float,
    cw: float,
    full_geometric: int,
    rhs_io: wp.array(dtype=wp.vec3),
    diag_io: wp.array(dtype=wp.mat33),
    values_io: wp.array(dtype=wp.mat33),
):
    """``assemble_cloth_springs`` per particle i, without atomics: over the springs touching i in
    the fixed CSR order (ascending spring index), diag_i += J, b_i += +-r (spring s evaluated from
    its end 2s) and the coupling block of row i, (i, other end), -= J (unless an end is pinned;
    springs sharing a block are summed by this one thread, in order)."""
    i = wp.tid()
    D = wp.mat33()
    b = wp.vec3()
    for a in range(particle_spring_offsets[i], particle_spring_offsets[i + 1]):
        s = particle_springs[a]
        if spring_broken[s] == 0:
            si = spring_indices[2 * s]
            sj = spring_indices[2 * s + 1]
            xij = q[si] - q[sj]
            rest = spring_rest_length[s]
            k = spring_stiffness[s]
            kd = spring_damping[s]
            Jx, Jv = spring_jacobians(xij, rest, k, kd, full_geometric)
            J = ck * Jx + cd * Jv
            D = D + J
            r = cf * spring_force(xij, qd[si] - qd[sj], rest, k, kd) + cw * (Jx * (w[si] - w[sj]))
            slot = spring_slots[2 * s]
            if si == i:
                b = b + r
            else:
                b = b - r
                slot = spring_slots[2 * s + 1]
            if inv_mass[si] > 0.0 and inv_mass[sj] > 0.0:
                values_io[slot] = values_io[slot] - J
    diag_io[i] = diag_io[i] + D
    rhs_io[i] = rhs_io[i] + b


@wp.kernel
def finish_cloth_system(
    diag: wp.array(dtype=wp.mat33),
    position_diag: wp.array(dtype=wp.mat33),
    f_other: wp.array(dtype=wp.vec3),
    mass: wp.array(dtype=float),
    inv_mass: wp.array(dtype=float),
    diagonal_slots: wp.array(dtype=int),
    qd: wp.array(dtype=wp.vec3),
    v0: wp.array(dtype=wp.vec3),
    w: wp.array(dtype=wp.vec3),
    mass_scale: float,
    cf: float,
    cw: float,
    rhs_io: wp.array(dtype=wp.vec3),
    values_io: wp.array(dtype=wp.mat33),
    inverse_out: wp.array(dtype=wp.mat33),
    dv_out: wp.array(dtype=wp.vec3),
):
    """Per particle: A_ii = mass_scale m I + diag (identity when pinned) into the BSR values and
    its inverse (block-Jacobi preconditioner); b_i += cf f_other_i + cw position_diag_i w_i
    - mass_scale m_i (v_i - v0_i) (0 when pinned); clears dv (the CG initial guess)."""
    i = wp.tid()
    I = wp.identity(n=3, dtype=float)
    block = (mass_scale * mass[i]) * I + diag[i]
    b = rhs_io[i] + cf * f_other[i] + cw * (position_diag[i] * w[i]) - (mass_scale * mass[i]) * (qd[i] - v0[i])
    if inv_mass[i] == 0.0:
        block = I
        b = wp.vec3()
    values_io[diagonal_slots[i]] = block
    inverse_out[i] = block_inverse(block)
    rhs_io[i] = b
    dv_out[i] = wp.vec3()


@wp.kernel
def newton_continue(
    max_dv: wp.array(dtype=float),
    tol: float,
    max_iterations: int,
    first: int,
    count_io: wp.array(dtype=int),
    condition_out: wp.array(dtype=wp.int32),
):
    """After a Newton iteration: count = 1 (first) or count + 1; condition = 1 while max |dv| [m/s]
    is above tol and fewer than max_iterations ran (the loop of ``wp.capture_while``)."""
    c = count_io[0] + 1
    if first != 0:
        c = 1
    count_io[0] = c
    go = wp.int32(0)
    if max_dv[0] > tol and c < max_iterations:
        go = wp.int32(1)
    condition_out[0] = go


@wp.kernel
def eval_cloth_spring_energy(
    q: wp.array(dtype=wp.vec3),
    spring_indices: wp.array(dtype=int),
    spring_rest_length: wp.array(dtype=float),
    spring_stiffness: wp.array(dtype=float),
    spring_broken: wp.array(dtype=int),
    energy_out: wp.array(dtype=float),
):
    """energy_out[0] += k (l - L)^2 / 2 summed over intact springs [J]."""
    s = wp.tid()
    if spring_broken[s] != 0:
        return
    l = wp.length(q[spring_indices[2 * s]] - q[spring_indices[2 * s + 1]])
    e = l - spring_rest_length[s]
    wp.atomic_add(energy_out, 0, 0.5 * spring_stiffness[s] * e * e)


@wp.kernel
def eval_kinetic_energy(
    qd: wp.array(dtype=wp.vec3), mass: wp.array(dtype=float), energy_out: wp.array(dtype=float)
):
    """energy_out[0] += m |v|^2 / 2 summed over particles [J]."""
    i = wp.tid()
    wp.atomic_add(energy_out, 0, 0.5 * mass[i] * wp.dot(qd[i], qd[i]))
