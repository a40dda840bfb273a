"""Batched-world kernels: tiling one world's arrays into N worlds, per-world forces, blow-up
flags and freezing, and per-world metrics.

Layout: world w owns particles ``w * P .. (w + 1) * P - 1`` and springs ``w * S .. (w + 1) * S - 1``
(P, S: one world's counts); ``particle_world[i] = i // P``. Per-world parameters are arrays of
shape (world_count,) (or (world_count * K,) for K parameters per world) read through that index,
so one launch per stage steps every world and a captured graph replays with any values.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})


# --------------------------------------------------------------------------------------
# World keys: neighbour grids of batched worlds
# --------------------------------------------------------------------------------------
@wp.func
def world_key(world: int, stride: float, side: int) -> wp.vec3:
    """Offset [m] of a world's copy of space in a neighbour grid: world w sits at
    stride * (w % side, (w / side) % side, w / side^2), so worlds fill a cube of side ``side``
    (small offsets keep float32 positions precise) and a query meets its own world's cells."""
    if stride == 0.0:
        return wp.vec3(0.0)
    return stride * wp.vec3(float(world % side), float((world / side) % side), float(world / (side * side)))


@wp.kernel
def key_world_points(
    x: wp.array(dtype=wp.vec3), world: wp.array(dtype=int), stride: float, side: int,
    keyed_out: wp.array(dtype=wp.vec3),
):
    """Grid points of batched worlds: x + world_key(world[i])."""
    i = wp.tid()
    keyed_out[i] = x[i] + world_key(world[i], stride, side)


# --------------------------------------------------------------------------------------
# Tiling (one world -> N worlds, on the device)
# --------------------------------------------------------------------------------------
@wp.kernel
def tile_world_index(per_world: int, world_out: wp.array(dtype=int)):
    """world_out[t] = t // per_world (the world of element t)."""
    t = wp.tid()
    world_out[t] = t / per_world


@wp.kernel
def tile_vec3(
    base: wp.array(dtype=wp.vec3),
    mask: wp.array(dtype=float),
    world_shift: wp.array(dtype=wp.vec3),
    out: wp.array(dtype=wp.vec3),
):
    """out[w P + e] = base[e] + mask[e] shift[w]; P = base.shape[0], mask 0 or 1 per element."""
    t = wp.tid()
    p = base.shape[0]
    e = t % p
    w = t / p
    out[t] = base[e] + mask[e] * world_shift[w]


@wp.kernel
def tile_float(
    base: wp.array(dtype=float),
    key: wp.array(dtype=int),
    coefficient: wp.array(dtype=float),
    world_values: wp.array(dtype=float),
    key_count: int,
    out: wp.array(dtype=float),
):
    """out[w P + e] = base[e] where key[e] < 0, else coefficient[e] * world_values[w K + key[e]]
    (element e scales linearly with varied parameter key[e] of world w)."""
    t = wp.tid()
    p = base.shape[0]
    e = t % p
    w = t / p
    k = key[e]
    if k < 0:
        out[t] = base[e]
    else:
        out[t] = coefficient[e] * world_values[w * key_count + k]


@wp.kernel
def tile_int(base: wp.array(dtype=int), out: wp.array(dtype=int)):
    """out[w P + e] = base[e] (per-element flags repeated in every world)."""
    t = wp.tid()
    out[t] = base[t % base.shape[0]]


@wp.kernel
def tile_spring_indices(base: wp.array(dtype=int), particle_count: int, out: wp.array(dtype=int)):
    """Spring end indices of world w = one world's indices + w P (base has 2 S entries); also any
    index array repeated per world with a per-world offset (CSR adjacency rows and springs)."""
    t = wp.tid()
    n = base.shape[0]
    out[t] = base[t % n] + (t / n) * particle_count


@wp.kernel
def inverse_masses(mass: wp.array(dtype=float), inv_mass_out: wp.array(dtype=float)):
    """1 / m, 0 for pinned particles (m = 0), as ModelBuilder.finalize computes it."""
    i = wp.tid()
    m = mass[i]
    if m > 0.0:
        inv_mass_out[i] = 1.0 / m
    else:
        inv_mass_out[i] = 0.0


# --------------------------------------------------------------------------------------
# Per-world forces
# --------------------------------------------------------------------------------------
@wp.kernel
def eval_gravity_worlds(
    mass: wp.array(dtype=float),
    particle_world: wp.array(dtype=int),
    world_gravity: wp.array(dtype=wp.vec3),
    f_out: wp.array(dtype=wp.vec3),
):
    """f += m g_w with the gravity [m/s^2] of the particle's world."""
    i = wp.tid()
    f_out[i] = f_out[i] + mass[i] * world_gravity[particle_world[i]]


# --------------------------------------------------------------------------------------
# Per-world step counts on paths without a masked step kernel: one pass per distinct count
# --------------------------------------------------------------------------------------
@wp.kernel
def keep_worlds_of_count(
    q: wp.array(dtype=wp.vec3),
    qd: wp.array(dtype=wp.vec3),
    particle_world: wp.array(dtype=int),
    world_steps: wp.array(dtype=int),
    count: int,
    q_out: wp.array(dtype=wp.vec3),
    qd_out: wp.array(dtype=wp.vec3),
):
    """(q_out, qd_out)[i] = (q, qd)[i] for the particles of worlds that take ``count`` steps a frame."""
    i = wp.tid()
    if world_steps[particle_world[i]] == count:
        q_out[i] = q[i]
        qd_out[i] = qd[i]


# --------------------------------------------------------------------------------------
# Faults stay local: flag a world that blew up, freeze it at its last good frame
# --------------------------------------------------------------------------------------
@wp.kernel
def flag_blown_worlds(
    q: wp.array(dtype=wp.vec3),
    qd: wp.array(dtype=wp.vec3),
    particle_world: wp.array(dtype=int),
    max_speed: float,
    world_bad_out: wp.array(dtype=int),
):
    """world_bad_out[w] = 1 when a particle of world w has a non-finite state or |v| > max_speed."""
    i = wp.tid()
    x = q[i]
    v = qd[i]
    if not wp.isfinite(x) or not wp.isfinite(v) or wp.length(v) > max_speed:
        world_bad_out[particle_world[i]] = 1


@wp.kernel
def record_blow_ups(world_bad: wp.array(dtype=int), frame: wp.array(dtype=int),
                    world_blown_frame: wp.array(dtype=int)):
    """The first frame (``frame[0]``, a device counter) at which each world was flagged (-1: never)."""
    w = wp.tid()
    if world_bad[w] == 1 and world_blown_frame[w] < 0:
        world_blown_frame[w] = frame[0]


@wp.kernel
def count_frame(frame: wp.array(dtype=int)):
    """frame[0] += 1 (a frame counter that a captured graph advances)."""
    frame[0] = frame[0] + 1


@wp.kernel
def freeze_blown_worlds(
    particle_world: wp.array(dtype=int),
    world_bad: wp.array(dtype=int),
    q_good: wp.array(dtype=wp.vec3),
    q: wp.array(dtype=wp.vec3),
    qd: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
):
    """Flagged worlds go back to their last good positions, at rest, with inverse mass 0 (no
    integrator or collider moves them again); the others save their positions as the last good."""
    i = wp.tid()
    if world_bad[particle_world[i]] == 1:
        q[i] = q_good[i]
        qd[i] = wp.vec3(0.0)
        inv_mass[i] = 0.0
    else:
        q_good[i] = q[i]


# --------------------------------------------------------------------------------------
# Metrics, accumulated on the device once per frame
# --------------------------------------------------------------------------------------
@wp.func
def first_of_world(i: int, particle_world: wp.array(dtype=int)) -> bool:
    """Whether particle i is the first of its world (worlds own contiguous ranges)."""
    return i == 0 or particle_world[i - 1] != particle_world[i]


@wp.kernel
def accumulate_world_sums(
    q: wp.array(dtype=wp.vec3),
    qd: wp.array(dtype=wp.vec3),
    mass: wp.array(dtype=float),
    particle_world: wp.array(dtype=int),
    world_bad: wp.array(dtype=int),
    moment_out: wp.array(dtype=wp.vec3),
    mass_out: wp.array(dtype=float),
    kinetic_out: wp.array(dtype=float),
    peak_speed_io: wp.array(dtype=float),
):
    """Per world: sum m x [kg m], sum m [kg], kinetic energy sum m |v|^2 / 2 [J] of this frame and
    the peak particle speed [m/s] so far (frozen worlds are skipped). Launched over particles; the
    first particle's thread of each world sums its world's particles in index order (no float
    atomics: the same bits every run), the others return."""
    i = wp.tid()
    if not first_of_world(i, particle_world):
        return
    w = particle_world[i]
    if world_bad[w] == 1:
        return
    moment = wp.vec3()
    total = float(0.0)  # noqa: UP018 (mutable loop variables in Warp)
    kinetic = float(0.0)  # noqa: UP018
    peak = peak_speed_io[w]
    j = i
    while j < q.shape[0] and particle_world[j] == w:
        m = mass[j]
        v = qd[j]
        moment += m * q[j]
        total += m
        kinetic += 0.5 * m * wp.dot(v, v)
        peak = wp.max(peak, wp.length(v))
        j += 1
    moment_out[w] = moment_out[w] + moment
    mass_out[w] = mass_out[w] + total
    kinetic_out[w] = kinetic_out[w] + kinetic
    peak_speed_io[w] = peak


@wp.kernel
def finish_world_frame(
    world_bad: wp.array(dtype=int),
    moment: wp.array(dtype=wp.vec3),
    mass_sum: wp.array(dtype=float),
    kinetic: wp.array(dtype=float),
    center_out: wp.array(dtype=wp.vec3),
    peak_center_io: wp.array(dtype=wp.vec3),
    final_kinetic_out: wp.array(dtype=float),
):
    """Centre of mass [m] of this frame, its component-wise peak so far, and the kinetic energy
    [J] (kept from the last good frame for frozen worlds)."""
    w = wp.tid()
    if world_bad[w] == 1:
        return
    c = moment[w] / wp.max(mass_sum[w], 1.0e-30)
    center_out[w] = c
    p = peak_center_io[w]
    peak_center_io[w] = wp.vec3(wp.max(p[0], c[0]), wp.max(p[1], c[1]), wp.max(p[2], c[2]))
    final_kinetic_out[w] = kinetic[w]


@wp.kernel
def track_particles(
    q: wp.array(dtype=wp.vec3),
    tracked: wp.array(dtype=int),
    particle_count: int,
    world_bad: wp.array(dtype=int),
    final_out: wp.array(dtype=wp.vec3),
    peak_io: wp.array(dtype=wp.vec3),
):
    """Positions [m] of tracked particles (indices within one world), per (world, tracked) pair:
    the latest good one and the component-wise peak."""
    w, k = wp.tid()
    if world_bad[w] == 1:
        return
    x = q[w * particle_count + tracked[k]]
    t = w * tracked.shape[0] + k
    final_out[t] = x
    p = peak_io[t]
    peak_io[t] = wp.vec3(wp.max(p[0], x[0]), wp.max(p[1], x[1]), wp.max(p[2], x[2]))


_metric_kernels = {}


def user_metric_kernel(func):
    """A kernel that adds ``func(x, v, m)`` (a ``@wp.func`` of (wp.vec3 [m], wp.vec3 [m/s],
    float [kg]) -> float) of every particle into ``out[world]`` (summed per world in particle
    order by the world's first thread: no float atomics; frozen worlds skipped); built once per
    function."""
    if func in _metric_kernels:
        return _metric_kernels[func]

    def eval_user_metric(
        q: wp.array(dtype=wp.vec3),
        qd: wp.array(dtype=wp.vec3),
        mass: wp.array(dtype=float),
        particle_world: wp.array(dtype=int),
        world_bad: wp.array(dtype=int),
        out: wp.array(dtype=float),
    ):
        i = wp.tid()
        if not first_of_world(i, particle_world):
            return
        w = particle_world[i]
        if world_bad[w] == 1:
            return
        total = float(0.0)  # noqa: UP018
        j = i
        while j < q.shape[0] and particle_world[j] == w:
            total += func(q[j], qd[j], mass[j])
            j += 1
        out[w] = out[w] + total

    kernel = wp.kernel(eval_user_metric, enable_backward=False, module="unique")
    _metric_kernels[func] = kernel
    return kernel


@wp.kernel
def keep_metric(world_bad: wp.array(dtype=int), value: wp.array(dtype=float), final_out: wp.array(dtype=float),
                peak_io: wp.array(dtype=float)):
    """Latest good value and peak so far of a per-world metric."""
    w = wp.tid()
    if world_bad[w] == 1:
        return
    final_out[w] = value[w]
    peak_io[w] = wp.max(peak_io[w], value[w])
