"""Energy balance kernels: per-world mechanical energy and the work of driving forces, summed in a
fixed order (bit-reproducible), and the per-world verdict (``warpsim.core.energy``).

Per particle i (moving ones only; pinned particles have no energy of their own):
  kinetic   m |w|^2 / 2 with w = v + (dt / 2) f / m for semi-implicit Euler (``half_dt`` = dt / 2:
            the velocity synchronised with the positions; the stored one is staggered by half a
            step; f the step's force, or m g where the stepper keeps no force: ``forces`` empty)
            and w = v otherwise (``half_dt`` = 0)
  gravity   -m g . x (g [m/s^2] of the particle's world)
  work      (f0 + f1) . (x1 - x0) / 2 of the driving forces over the frame (trapezoid rule)
Per spring s (unbroken): k (|x_i - x_j| - L)^2 / 2.

Columns of a world's sums: 0 kinetic + gravity [J], 1 spring energy [J], 2 work [J], 3 1.0 when any
value was non-finite (else 0).
"""

import warp as wp

wp.set_module_options({"enable_backward": False})

COLUMNS = wp.constant(4)


@wp.func
def particle_terms(
    x: wp.vec3, x0: wp.vec3, v: wp.vec3, f: wp.vec3, fd0: wp.vec3, fd1: wp.vec3, m: float, inv_m: float, g: wp.vec3,
    half_dt: float,
):
    """(kinetic + gravity [J], work of the driving forces over the frame [J]) of one particle."""
    if inv_m == 0.0:
        return float(0.0), float(0.0)
    w = v + (half_dt * inv_m) * f
    energy = 0.5 * m * wp.dot(w, w) - m * wp.dot(g, x)
    work = 0.5 * wp.dot(fd0 + fd1, x - x0)
    return energy, work


@wp.func
def step_force(forces: wp.array(dtype=wp.vec3), i: int, m: float, g: wp.vec3) -> wp.vec3:
    """The step's force on particle i [N], or its weight m g where none is kept."""
    if forces.shape[0] == 0:
        return m * g
    return forces[i]


@wp.func
def spring_term(x_i: wp.vec3, x_j: wp.vec3, rest: float, k: float) -> float:
    """Elastic energy [J] of a linear spring of stiffness k [N/m] and rest length [m]."""
    d = wp.length(x_i - x_j) - rest
    return 0.5 * k * d * d


@wp.func
def bad(value: float) -> float:
    """1.0 for a non-finite value, else 0.0."""
    if wp.isfinite(value):
        return 0.0
    return 1.0


@wp.kernel
def world_energy_sums(
    q: wp.array(dtype=wp.vec3),
    q_frame_start: wp.array(dtype=wp.vec3),
    qd: wp.array(dtype=wp.vec3),
    forces: wp.array(dtype=wp.vec3),
    drive_start: wp.array(dtype=wp.vec3),
    drive_end: wp.array(dtype=wp.vec3),
    mass: wp.array(dtype=float),
    inv_mass: wp.array(dtype=float),
    world_gravity: wp.array(dtype=wp.vec3),
    half_dt: float,
    world_particles: int,
    spring_indices: wp.array(dtype=int),
    spring_rest: wp.array(dtype=float),
    spring_stiffness: wp.array(dtype=float),
    spring_broken: wp.array(dtype=int),
    world_springs: int,
    out: wp.array2d(dtype=float),
):
    """One thread per world w sums its particles [w P, (w + 1) P) and springs [w S, (w + 1) S) in
    index order into out[w] (the module's columns); ``spring_broken`` may be empty (none break)."""
    w = wp.tid()
    g = world_gravity[w]
    energy = float(0.0)
    work = float(0.0)
    elastic = float(0.0)
    for i in range(w * world_particles, (w + 1) * world_particles):
        e, a = particle_terms(q[i], q_frame_start[i], qd[i], step_force(forces, i, mass[i], g), drive_start[i],
                              drive_end[i], mass[i], inv_mass[i], g, half_dt)
        energy += e
        work += a
    for s in range(w * world_springs, (w + 1) * world_springs):
        if spring_broken.shape[0] == 0 or spring_broken[s] == 0:
            elastic += spring_term(q[spring_indices[2 * s]], q[spring_indices[2 * s + 1]], spring_rest[s],
                                   spring_stiffness[s])
    out[w, 0] = energy
    out[w, 1] = elastic
    out[w, 2] = work
    out[w, 3] = wp.max(bad(energy), wp.max(bad(elastic), bad(work)))


@wp.kernel
def energy_sums_strided(
    q: wp.array(dtype=wp.vec3),
    q_frame_start: wp.array(dtype=wp.vec3),
    qd: wp.array(dtype=wp.vec3),
    forces: wp.array(dtype=wp.vec3),
    drive_start: wp.array(dtype=wp.vec3),
    drive_end: wp.array(dtype=wp.vec3),
    mass: wp.array(dtype=float),
    inv_mass: wp.array(dtype=float),
    world_gravity: wp.array(dtype=wp.vec3),
    half_dt: float,
    spring_indices: wp.array(dtype=int),
    spring_rest: wp.array(dtype=float),
    spring_stiffness: wp.array(dtype=float),
    spring_broken: wp.array(dtype=int),
    spring_count: int,
    partial_out: wp.array2d(dtype=float),
):
    """One world, many threads: slot s sums particles s, s + S, ... and springs s, s + S, ... in
    increasing order into partial_out[s] (S = slots; folded by ``kernels/reduce.py: reduce_rows``
    with column 3 a maximum)."""
    s = wp.tid()
    stride = partial_out.shape[0]
    g = world_gravity[0]
    energy = float(0.0)
    work = float(0.0)
    elastic = float(0.0)
    i = s
    while i < q.shape[0]:
        e, a = particle_terms(q[i], q_frame_start[i], qd[i], step_force(forces, i, mass[i], g), drive_start[i],
                              drive_end[i], mass[i], inv_mass[i], g, half_dt)
        energy += e
        work += a
        i += stride
    j = s
    while j < spring_count:
        if spring_broken.shape[0] == 0 or spring_broken[j] == 0:
            elastic += spring_term(q[spring_indices[2 * j]], q[spring_indices[2 * j + 1]], spring_rest[j],
                                   spring_stiffness[j])
        j += stride
    partial_out[s, 0] = energy
    partial_out[s, 1] = elastic
    partial_out[s, 2] = work
    partial_out[s, 3] = wp.max(bad(energy), wp.max(bad(elastic), bad(work)))


@wp.kernel
def count_frame(counter: wp.array(dtype=int)):
    """counter[0] += 1 (the balance's frame number, on the device so a captured frame counts)."""
    counter[0] = counter[0] + 1


@wp.kernel
def judge_worlds(
    sums: wp.array2d(dtype=float),
    frame_counter: wp.array(dtype=int),
    margin: float,
    world_bad: wp.array(dtype=int),
    reference: wp.array(dtype=float),
    scale: wp.array(dtype=float),
    work_io: wp.array(dtype=float),
    abs_work_io: wp.array(dtype=float),
    allowance: wp.array(dtype=float),
    energy_out: wp.array(dtype=float),
    gain_io: wp.array(dtype=float),
    unstable_frame_io: wp.array(dtype=int),
):
    """Per world: E = kinetic + gravity + elastic [J]; the work W of the driving forces accumulates
    (and |W| frame by frame). gain = (E - E_ref - W) / (scale + sum |W| + allowance) is the energy that
    appeared from nowhere, relative; gain_io keeps its maximum, and a world whose gain exceeds
    ``margin`` or whose energy is non-finite is unstable from this frame (unstable_frame_io, -1
    otherwise; set once). Frozen worlds (world_bad = 1) are skipped."""
    w = wp.tid()
    if world_bad.shape[0] > 0:
        if world_bad[w] == 1:
            return
    energy = sums[w, 0] + sums[w, 1]
    work = work_io[w] + sums[w, 2]
    abs_work = abs_work_io[w] + wp.abs(sums[w, 2])
    work_io[w] = work
    abs_work_io[w] = abs_work
    energy_out[w] = energy
    gain = (energy - reference[w] - work) / (scale[w] + abs_work + allowance[w])
    if sums[w, 3] > 0.0 or not wp.isfinite(gain):
        gain = 1.0e30
    gain_io[w] = wp.max(gain_io[w], gain)
    if gain > margin and unstable_frame_io[w] < 0:
        unstable_frame_io[w] = frame_counter[0]
