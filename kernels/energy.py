"""Energy balance kernels: per-world mechanical energy and the work of driving forces, summed in a
fixed order (bit-reproducible), and the per-world verdict (``warpsim.core.energy``).

For semi-implicit Euler (``half_dt`` = dt / 2) the energy is the method's modified (shadow)
energy H = K + U + (dt / 2) v . f(x), f = -grad U the conservative force at the current positions
and v the stored (half-step staggered) velocity: the method conserves it exactly for linear
springs and uniform gravity at every stable step, where K + U alone swings by up to 5x near the
stability limit (Hairer, Lubich & Wanner, Geometric Numerical Integration, IX). Other integrators
use K + U (``half_dt`` = 0).

Per particle i (moving ones only; pinned particles have no energy of their own):
  kinetic + gravity   m |v|^2 / 2 - m g . x + (dt / 2) m v . g   (g [m/s^2] of its world)
  work                (f0 + f1) . (x1 - x0) / 2 of the driving forces over the frame (trapezoid rule)
Per spring s (unbroken), d = |x_i - x_j| - L and u the unit vector from j to i:
  elastic             k d^2 / 2 - (dt / 2) k d u . (v_i - v_j)

Columns of a world's sums: 0 the plain energy K + U [J], 1 the modified energy's (dt / 2) v . f
terms [J], 2 work [J], 3 the gravity potential -sum m g . x [J], 4 1.0 when any value was non-finite
(else 0; a maximum), 5 the largest single particle's kinetic energy m |v + (dt / 2) g|^2 / 2 [J] (its
velocity synchronised for gravity; a maximum).
"""

import warp as wp

from .world_step import SharedSprings, world_value

wp.set_module_options({"enable_backward": False})

@wp.func
def particle_terms(
    x: wp.vec3, x0: wp.vec3, v: wp.vec3, fd0: wp.vec3, fd1: wp.vec3, m: float, inv_m: float, g: wp.vec3,
    half_dt: float,
):
    """(kinetic + gravity [J], the (dt / 2) v . f term [J], work of the driving forces over the frame
    [J], gravity potential [J], kinetic energy with the velocity synchronised for gravity [J]) of one
    particle."""
    if inv_m == 0.0:
        return float(0.0), float(0.0), float(0.0), float(0.0), float(0.0)
    potential = -m * wp.dot(g, x)
    work = 0.5 * wp.dot(fd0 + fd1, x - x0)
    w = v + half_dt * g
    return 0.5 * m * wp.dot(v, v) + potential, half_dt * m * wp.dot(v, g), work, potential, 0.5 * m * wp.dot(w, w)


@wp.func
def spring_term(x_i: wp.vec3, x_j: wp.vec3, v_i: wp.vec3, v_j: wp.vec3, rest: float, k: float, half_dt: float):
    """(Elastic energy [J], its (dt / 2) v . f term [J]) of a linear spring of stiffness k [N/m]
    and rest length [m]."""
    delta = x_i - x_j
    length = wp.length(delta)
    d = length - rest
    correction = float(0.0)
    if length > 0.0:
        correction = -half_dt * k * d * wp.dot(delta, v_i - v_j) / length
    return 0.5 * k * d * d, correction


@wp.func
def bad(value: float) -> float:
    """1.0 for a non-finite value, else 0.0."""
    if wp.isfinite(value):
        return 0.0
    return 1.0


@wp.struct
class EnergyInputs:
    """What the sums read: positions now and at the frame's start [m], velocities [m/s], the driving
    forces at the frame's start and end [N] (empty arrays of length 0 are not allowed: zeros when
    nothing drives), masses [kg], inverse masses [1/kg], gravity per world [m/s^2] and dt / 2 per world [s]
    (each world's own step; 0 for integrators other than semi-implicit Euler)."""

    q: wp.array(dtype=wp.vec3)
    q_frame_start: wp.array(dtype=wp.vec3)
    qd: wp.array(dtype=wp.vec3)
    drive_start: wp.array(dtype=wp.vec3)
    drive_end: wp.array(dtype=wp.vec3)
    mass: wp.array(dtype=float)
    inv_mass: wp.array(dtype=float)
    world_gravity: wp.array(dtype=wp.vec3)
    half_dt: wp.array(dtype=float)


@wp.func
def add_particle(p: EnergyInputs, i: int, g: wp.vec3, half_dt: float, energy: float, correction: float,
                 work: float, gravity: float, peak: float):
    """The running (energy, correction, work, gravity, peak) with particle i added (``half_dt``: its
    world's dt / 2 [s])."""
    e, c, a, u, k = particle_terms(p.q[i], p.q_frame_start[i], p.qd[i], p.drive_start[i], p.drive_end[i],
                                   p.mass[i], p.inv_mass[i], g, half_dt)
    return energy + e, correction + c, work + a, gravity + u, wp.max(peak, k)


@wp.func
def add_spring(p: EnergyInputs, i: int, j: int, rest: float, k: float, half_dt: float, energy: float,
               correction: float):
    """The running (energy, correction) with the spring joining particles i and j added."""
    e, c = spring_term(p.q[i], p.q[j], p.qd[i], p.qd[j], rest, k, half_dt)
    return energy + e, correction + c


@wp.func
def write_row(out: wp.array2d(dtype=float), r: int, energy: float, correction: float, work: float,
              gravity: float, peak: float):
    """Row r of the sums (the module's columns)."""
    out[r, 0] = energy
    out[r, 1] = correction
    out[r, 2] = work
    out[r, 3] = gravity
    out[r, 4] = wp.max(bad(energy), wp.max(bad(correction), wp.max(bad(work), bad(peak))))
    out[r, 5] = peak


@wp.kernel
def world_energy_sums(
    p: EnergyInputs,
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
    g = p.world_gravity[w]
    h2 = p.half_dt[w]
    energy = float(0.0)
    correction = float(0.0)
    work = float(0.0)
    gravity = float(0.0)
    peak = float(0.0)
    for i in range(w * world_particles, (w + 1) * world_particles):
        energy, correction, work, gravity, peak = add_particle(p, i, g, h2, energy, correction, work, gravity, peak)
    for s in range(w * world_springs, (w + 1) * world_springs):
        if spring_broken.shape[0] == 0 or spring_broken[s] == 0:
            energy, correction = add_spring(p, spring_indices[2 * s], spring_indices[2 * s + 1], spring_rest[s],
                                            spring_stiffness[s], h2, energy, correction)
    write_row(out, w, energy, correction, work, gravity, peak)


@wp.kernel
def world_energy_sums_shared(p: EnergyInputs, world_particles: int, springs: SharedSprings,
                             out: wp.array2d(dtype=float)):
    """``world_energy_sums`` for batches whose springs are stored once (``kernels/world_step.py``):
    world w's springs are read from the shared adjacency with its own parameters, each from its
    first end, in the order the step sums them."""
    w = wp.tid()
    g = p.world_gravity[w]
    h2 = p.half_dt[w]
    first = w * world_particles
    energy = float(0.0)
    correction = float(0.0)
    work = float(0.0)
    gravity = float(0.0)
    peak = float(0.0)
    for local in range(world_particles):
        i = first + local
        energy, correction, work, gravity, peak = add_particle(p, i, g, h2, energy, correction, work, gravity, peak)
        for s in range(springs.offsets[local], springs.offsets[local + 1]):
            entry = springs.entries[s]
            code = int(entry[3])
            if code % 2 == 0:
                packed = springs.keys[s]
                rest = world_value(entry[0], (packed & 1023) - 1, springs.world_values, springs.key_count, w)
                stiff = world_value(entry[1], ((packed >> 10) & 1023) - 1, springs.world_values, springs.key_count, w)
                energy, correction = add_spring(p, i, first + code / 2, rest, stiff, h2, energy, correction)
    write_row(out, w, energy, correction, work, gravity, peak)


@wp.kernel
def energy_sums_strided(
    p: EnergyInputs,
    spring_indices: wp.array(dtype=int),
    spring_rest: wp.array(dtype=float),
    spring_stiffness: wp.array(dtype=float),
    spring_broken: wp.array(dtype=int),
    spring_count: int,
    partial_out: wp.array2d(dtype=float),
):
    """One world, many threads: slot s sums particles s, s + S, ... and springs s, s + S, ... in
    increasing order into partial_out[s] (S = slots; folded by ``kernels/reduce.py: reduce_rows``
    with columns 4 and 5 maxima)."""
    s = wp.tid()
    stride = partial_out.shape[0]
    g = p.world_gravity[0]
    h2 = p.half_dt[0]
    energy = float(0.0)
    correction = float(0.0)
    work = float(0.0)
    gravity = float(0.0)
    peak = float(0.0)
    i = s
    while i < p.q.shape[0]:
        energy, correction, work, gravity, peak = add_particle(p, i, g, h2, energy, correction, work, gravity, peak)
        i += stride
    j = s
    while j < spring_count:
        if spring_broken.shape[0] == 0 or spring_broken[j] == 0:
            energy, correction = add_spring(p, spring_indices[2 * j], spring_indices[2 * j + 1], spring_rest[j],
                                            spring_stiffness[j], h2, energy, correction)
        j += stride
    write_row(partial_out, s, energy, correction, work, gravity, peak)


@wp.kernel
def count_frame(counter: wp.array(dtype=int)):
    """counter[0] += 1 (the balance's frame number, on the device so a captured frame counts)."""
    counter[0] = counter[0] + 1


@wp.kernel
def judge_worlds(
    sums: wp.array2d(dtype=float),
    frame_counter: wp.array(dtype=int),
    margin: float,
    runaway: wp.array(dtype=float),
    world_bad: wp.array(dtype=int),
    reference: wp.array2d(dtype=float),
    scale: wp.array(dtype=float),
    motion: wp.array(dtype=float),
    work_io: wp.array(dtype=float),
    abs_work_io: wp.array(dtype=float),
    released_io: wp.array(dtype=float),
    allowance: wp.array(dtype=float),
    energy_out: wp.array(dtype=float),
    gain_io: wp.array(dtype=float),
    plain_gain_io: wp.array(dtype=float),
    unstable_frame_io: wp.array(dtype=int),
):
    """Per world: the modified energy E = sums[w, 0] + sums[w, 1] [J]; the work W of the driving forces
    accumulates (and |W| frame by frame), and released_io keeps the most gravity energy released since
    frame 0 (reference[w, 2] - sums[w, 3] [J]). The run's energy scale is the larger of ``scale[w]``
    (frame 0's kinetic and elastic energy plus the potential above the floor or lowest particle) and
    ``motion[w]`` (frame 0's kinetic and elastic energy) plus that released energy: the most energy the
    world has had in motion, so a chain released horizontally with no floor under it is judged against
    the energy its fall put into its swing, not against the 1 mm floor of the scale.
    gain = (E - E_ref - W) / (energy scale + sum |W| + allowance) is the energy that appeared from
    nowhere, relative; gain_io keeps its maximum. A world is unstable from this frame (unstable_frame_io,
    set once; -1 otherwise) when gain > ``margin``, when the plain energy K + U (reference[w, 1]) grew by
    more than ``runaway[w]`` x that budget (past the stability limit the modified energy stays put or
    falls while the motion grows), when one particle alone holds more kinetic energy than
    max(runaway[w], 1) x the world's budget plus the gravity energy released by now (a local blow-up that
    losses elsewhere hide), or when a value is non-finite. A world keeps the figures of the frame it was
    flagged at (where a lone run stops), and frozen worlds (world_bad = 1) are skipped."""
    w = wp.tid()
    if world_bad.shape[0] > 0:  # nested: no read of world_bad[w] when it is empty
        if world_bad[w] == 1:
            return
    if unstable_frame_io[w] >= 0:
        return
    energy = sums[w, 0] + sums[w, 1]
    work = work_io[w] + sums[w, 2]
    abs_work = abs_work_io[w] + wp.abs(sums[w, 2])
    released_now = reference[w, 2] - sums[w, 3]
    released = released_io[w]
    if released_now > released:  # NaN-safe: a non-finite sum leaves the kept maximum
        released = released_now
    work_io[w] = work
    abs_work_io[w] = abs_work
    released_io[w] = released
    energy_out[w] = energy
    budget = wp.max(scale[w], motion[w] + released) + abs_work + allowance[w]
    gain = (energy - reference[w, 0] - work) / budget
    plain = (sums[w, 0] - reference[w, 1] - work) / budget
    local = sums[w, 5] / (budget + wp.max(released_now, 0.0))
    if sums[w, 4] > 0.0 or not wp.isfinite(gain) or not wp.isfinite(plain) or not wp.isfinite(local):
        gain = 1.0e30
        plain = 1.0e30
    plain = wp.max(plain, local / wp.max(runaway[w], 1.0) * runaway[w])
    gain_io[w] = wp.max(gain_io[w], gain)
    plain_gain_io[w] = wp.max(plain_gain_io[w], plain)
    if (gain > margin or plain > runaway[w]) and unstable_frame_io[w] < 0:
        unstable_frame_io[w] = frame_counter[0]
