"""Stability-limit kernels: the stiffness operator of a model's springs applied per particle
(a gather over a CSR adjacency, fixed order, no atomics on sums), power-iteration
normalisation per world and Gershgorin row bounds. Driven by ``warpsim.core.stability``.

The operator is the linearised spring force about the current positions: spring s between
particles i and j with direction d (unit) and length l contributes the 3x3 block
``B_s = c_s (d d^T + g_s (I - d d^T))`` with ``g_s = max(0, 1 - L_s / l)`` (the clamped
geometric term, 0 for damping) so that ``(A v)_i = diag_i v_i + sum_s B_s (v_i - v_j)``.
With ``c = stiffness`` this is K (the negated force Jacobian), with ``c = damping`` it is D.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.func
def spring_block_apply(xi: wp.vec3, xj: wp.vec3, rest: float, coefficient: float, geometric: int, u: wp.vec3):
    """B_s u for the spring block defined above (isotropic c u for a zero-length spring)."""
    d = xj - xi
    length = wp.length(d)
    if length < 1.0e-12:
        return coefficient * u
    n = d / length
    axial = wp.dot(n, u) * n
    g = float(0.0)
    if geometric != 0:
        g = wp.max(0.0, 1.0 - rest / length)
    return coefficient * (axial + g * (u - axial))


@wp.kernel
def apply_spring_operator(
    v: wp.array(dtype=wp.vec3),
    q: wp.array(dtype=wp.vec3),
    offsets: wp.array(dtype=int),
    adjacent_spring: wp.array(dtype=int),
    adjacent_particle: wp.array(dtype=int),
    rest_length: wp.array(dtype=float),
    coefficient: wp.array(dtype=float),
    broken: wp.array(dtype=int),
    geometric: int,
    diag: wp.array(dtype=float),
    out: wp.array(dtype=wp.vec3),
):
    """out_i = diag_i v_i + sum over particle i's springs (CSR order) of B_s (v_i - v_j)."""
    i = wp.tid()
    acc = diag[i] * v[i]
    for a in range(offsets[i], offsets[i + 1]):
        s = adjacent_spring[a]
        if broken[s] == 0:
            j = adjacent_particle[a]
            acc = acc + spring_block_apply(q[i], q[j], rest_length[s], coefficient[s], geometric, v[i] - v[j])
    out[i] = acc


@wp.kernel
def scale_and_world_max(
    y: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    particle_world: wp.array(dtype=int),
    y_out: wp.array(dtype=wp.vec3),
    world_max_out: wp.array(dtype=float),
):
    """y_out_i = inv_mass_i y_i (M^-1 K v; pinned rows vanish); world_max_out[w] = max |y_out| component
    over the world's particles (atomic max: order independent)."""
    i = wp.tid()
    z = inv_mass[i] * y[i]
    y_out[i] = z
    m = wp.max(wp.abs(z[0]), wp.max(wp.abs(z[1]), wp.abs(z[2])))
    wp.atomic_max(world_max_out, particle_world[i], m)


@wp.kernel
def normalize_per_world(
    y: wp.array(dtype=wp.vec3),
    particle_world: wp.array(dtype=int),
    world_max: wp.array(dtype=float),
    v_out: wp.array(dtype=wp.vec3),
):
    """v_out_i = y_i / world_max[w] (0 where the world's vector vanished)."""
    i = wp.tid()
    m = world_max[particle_world[i]]
    if m > 0.0:
        v_out[i] = y[i] / m
    else:
        v_out[i] = wp.vec3(0.0)


@wp.kernel
def gershgorin_rows(
    offsets: wp.array(dtype=int),
    adjacent_spring: wp.array(dtype=int),
    adjacent_particle: wp.array(dtype=int),
    stiffness: wp.array(dtype=float),
    broken: wp.array(dtype=int),
    inv_mass: wp.array(dtype=float),
    diag: wp.array(dtype=float),
    out: wp.array(dtype=float),
):
    """out_i = inv_m_i (diag_i + sum_s k_s) + sum_s k_s sqrt(inv_m_i inv_m_j): block-Gershgorin
    row bound of M^-1/2 K M^-1/2 (spectral norm of every block <= k_s), an upper bound of
    omega^2 [1/s^2] of every mode touching particle i; 0 for pinned particles."""
    i = wp.tid()
    wi = inv_mass[i]
    total = diag[i] * wi
    for a in range(offsets[i], offsets[i + 1]):
        s = adjacent_spring[a]
        if broken[s] == 0:
            k = stiffness[s]
            total = total + k * (wi + wp.sqrt(wi * inv_mass[adjacent_particle[a]]))
    out[i] = total


@wp.kernel
def frame_motion(
    q: wp.array(dtype=wp.vec3),
    q_frame_start: wp.array(dtype=wp.vec3),
    qd: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    particle_world: wp.array(dtype=int),
    inv_frame_dt: float,
    speed_out: wp.array(dtype=float),
    motion_out: wp.array(dtype=float),
):
    """Per world: speed_out[w] = max |v| [m/s] and motion_out[w] = max |q - q_frame_start| / frame_dt
    [m/s] over its moving particles (atomic max: order independent); non-finite values count as inf."""
    i = wp.tid()
    if inv_mass[i] == 0.0:
        return
    w = particle_world[i]
    s = wp.length(qd[i])
    m = wp.length(q[i] - q_frame_start[i]) * inv_frame_dt
    if not wp.isfinite(s):
        s = 1.0e30
    if not wp.isfinite(m):
        m = 1.0e30
    wp.atomic_max(speed_out, w, s)
    wp.atomic_max(motion_out, w, m)


@wp.kernel
def flag_incoherent_worlds(
    speed: wp.array(dtype=float),
    motion: wp.array(dtype=float),
    ratio: float,
    min_speed: float,
    frames: int,
    frame_counter: wp.array(dtype=int),
    streak: wp.array(dtype=int),
    unstable_frame_out: wp.array(dtype=int),
):
    """A world whose fastest particle is ``ratio`` x faster than any particle moved over the frame
    (and above ``min_speed`` [m/s]) for ``frames`` frames in a row is unstable: unstable_frame_out[w]
    gets the frame (kept at -1 otherwise); frame 0 (no motion yet) is skipped."""
    w = wp.tid()
    if frame_counter[0] < 1:
        return
    if speed[w] > ratio * motion[w] and speed[w] > min_speed:
        streak[w] = streak[w] + 1
    else:
        streak[w] = 0
    if streak[w] >= frames and unstable_frame_out[w] < 0:
        unstable_frame_out[w] = frame_counter[0]


@wp.kernel
def other_ends(offsets: wp.array(dtype=int), springs: wp.array(dtype=int), spring_indices: wp.array(dtype=int),
               other: wp.array(dtype=int)):
    """Per particle i (one thread), for each CSR entry e of its springs: the spring's other end
    (i itself for a spring from i to i)."""
    i = wp.tid()
    for e in range(offsets[i], offsets[i + 1]):
        s = springs[e]
        a = spring_indices[2 * s]
        b = spring_indices[2 * s + 1]
        if a == i:
            other[e] = b
        else:
            other[e] = a
