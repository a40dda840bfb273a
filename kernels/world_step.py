"""One fused semi-implicit Euler step of many mass-spring worlds that share one topology.

World w owns particles ``w P .. (w + 1) P - 1`` (state, masses, radii per world); the springs,
their CSR adjacency and the base values of their parameters are stored ONCE (world 0's, local
particle indices, one 16-byte entry + one int per spring end), and a parameter that differs
between worlds is ``coefficient[e] * world_values[w K + key[e]]`` (the tiling rule of
``kernels/worlds.py: tile_float``, evaluated on the fly). Per particle, one thread does what the generic Simulator does in its passes, with the
same arithmetic in the same order, so the results are bit-identical to it:

  f = 0 + m g_w                               (``seed_forces`` / ``eval_gravity_worlds``)
  f = f + sum of its springs in CSR order      (``kernels/forces.py: eval_springs_gather``)
  v = v + (h / m) f, x = x + h v               (``kernels/integrate.py: step_particles_semi_implicit``)
  every plane of every wall collider in order  (``kernels/collide.py: resolve_plane``)

No floating-point contraction (``fuse_fp`` off here and in forces.py, integrate.py and collide.py):
CUDA builds contract a * b + c into one fused multiply-add by default, and where they do depends
on how a kernel is composed, so this fused step and the Simulator's separate passes would round
differently on GPUs (Warp's CPU builds do not contract).

Reads (q, qd), writes (q_out, qd_out): other threads read this step's positions of the
neighbours, so the stepper ping-pongs two buffers.

Per-world step counts (``WorldSteps``): world w takes ``steps[w]`` steps of ``h[w]`` [s] a frame
(the count and step it takes run alone); a batch launches its largest count, and at sub-step k
world w steps only while k < steps[w] (the others idle: no read, no write). The count is data, not
host control flow, so a frame captures as one CUDA graph. With the per-step kernel, sub-step k
reads buffer k % 2 and writes the other, so a world that took an odd count ends in the spare
buffer (``settle_worlds`` brings it home).

Occupancy (``marks``, ``kernels/occupancy.py: CellMarks``; empty arrays: off): at a world's last
sub-step of the frame each of its threads marks the cell of the position it has just computed,
and the block-per-world kernel folds its world's marks into the record's bits after its last
barrier.
"""

import warp as wp

from .collide import resolve_plane
from .forces import damped_spring_force
from .occupancy import CellMarks, fold_world_marks, mark_cell

wp.set_module_options({"enable_backward": False, "fuse_fp": False})  # no FMA contraction: see the module doc


@wp.func
def world_value(value: float, key: int, world_values: wp.array(dtype=float), key_count: int, w: int) -> float:
    """A spring parameter in world w: ``value`` itself (key < 0), or value (the coefficient) times
    world w's varied parameter ``key`` (bit-identical to ``tile_float``: the product commutes)."""
    if key < 0:
        return value
    return value * world_values[w * key_count + key]


@wp.struct
class SharedSprings:
    """One world's springs, shared by every world, as a CSR adjacency over local particle indices:
    row p = entries ``offsets[p] .. offsets[p + 1]`` (ascending spring index), each entry a vec4
    (rest length [m], stiffness [N/m], damping [N s/m]: base values or coefficients; the other
    end as a float, 2 o + 1 when p is the spring's second end) and ``keys`` (int: the varied
    parameter of each of the three values + 1 in bits 0-9, 10-19, 20-29; 0 = not varied)."""

    offsets: wp.array(dtype=int)
    entries: wp.array(dtype=wp.vec4)
    keys: wp.array(dtype=int)
    world_values: wp.array(dtype=float)
    key_count: int


@wp.struct
class WorldSteps:
    """Steps per frame of each world (world_count,) and each world's step [s] (world_count,)."""

    steps: wp.array(dtype=int)
    h: wp.array(dtype=float)


@wp.struct
class WorldWalls:
    """Planes of the wall colliders, in order: normal, offset and collider index per plane (G,);
    per collider (C,): mode, thickness [m], penalty stiffness [N/m]; per world and collider
    (world_count C,): restitution, friction, penalty damping ratio."""

    normals: wp.array(dtype=wp.vec3)
    offsets: wp.array(dtype=float)
    collider: wp.array(dtype=int)
    mode: wp.array(dtype=int)
    thickness: wp.array(dtype=float)
    stiffness: wp.array(dtype=float)
    restitution: wp.array(dtype=float)
    friction: wp.array(dtype=float)
    damping_ratio: wp.array(dtype=float)
    collider_count: int


@wp.func
def step_shared_particle(
    t: int,
    w: int,
    p: int,
    first: int,
    q: wp.array(dtype=wp.vec3),
    qd: wp.array(dtype=wp.vec3),
    mass: wp.array(dtype=float),
    inv_mass: wp.array(dtype=float),
    radius: wp.array(dtype=float),
    world_gravity: wp.array(dtype=wp.vec3),
    springs: SharedSprings,
    walls: WorldWalls,
    h: float,
):
    """The stepped (x, v) of particle t = first + p of world w (module docstring)."""
    f = wp.vec3() + mass[t] * world_gravity[w]
    x = q[t]
    v = qd[t]
    fs = wp.vec3()
    for a in range(springs.offsets[p], springs.offsets[p + 1]):
        e = springs.entries[a]
        packed = springs.keys[a]
        code = int(e[3])
        other = first + code / 2
        rest = world_value(e[0], (packed & 1023) - 1, springs.world_values, springs.key_count, w)
        k = world_value(e[1], ((packed >> 10) & 1023) - 1, springs.world_values, springs.key_count, w)
        kd = world_value(e[2], ((packed >> 20) & 1023) - 1, springs.world_values, springs.key_count, w)
        # spring s evaluated from its first end, as eval_springs_gather does
        if code % 2 == 0:
            fs = fs + damped_spring_force(x, q[other], v, qd[other], rest, k, kd)
        else:
            fs = fs - damped_spring_force(q[other], x, qd[other], v, rest, k, kd)
    f = f + fs
    im = inv_mass[t]
    x0 = x
    v = v + (h * im) * f
    x = x + h * v
    if im != 0.0:
        d = radius[t]
        for g in range(walls.normals.shape[0]):
            c = walls.collider[g]
            wc = w * walls.collider_count + c
            x, v = resolve_plane(x, v, x0, im * f, walls.normals[g], walls.offsets[g], d + walls.thickness[c],
                                 walls.mode[c], walls.restitution[wc], walls.friction[wc], walls.stiffness[c],
                                 walls.damping_ratio[wc], im, h)
    return x, v


@wp.kernel
def step_shared_worlds(
    q: wp.array(dtype=wp.vec3),
    qd: wp.array(dtype=wp.vec3),
    mass: wp.array(dtype=float),
    inv_mass: wp.array(dtype=float),
    radius: wp.array(dtype=float),
    world_gravity: wp.array(dtype=wp.vec3),
    particle_count: int,
    springs: SharedSprings,
    walls: WorldWalls,
    steps: WorldSteps,
    k: int,
    q_out: wp.array(dtype=wp.vec3),
    qd_out: wp.array(dtype=wp.vec3),
    marks: CellMarks,
):
    """Sub-step ``k`` of particle t = w P + p (module docstring); P = ``particle_count`` per world:
    world w steps by ``steps.h[w]`` [s] while k < ``steps.steps[w]`` and idles after; at its last
    sub-step the new position marks its cell in ``marks``."""
    t = wp.tid()
    w = t / particle_count
    n = steps.steps[w]
    if k >= n:
        return
    p = t - w * particle_count
    x, v = step_shared_particle(t, w, p, w * particle_count, q, qd, mass, inv_mass, radius, world_gravity, springs,
                                walls, steps.h[w])
    q_out[t] = x
    qd_out[t] = v
    if k == n - 1:
        mark_cell(marks, w, x)


@wp.kernel
def settle_worlds(
    q_spare: wp.array(dtype=wp.vec3),
    qd_spare: wp.array(dtype=wp.vec3),
    particle_count: int,
    steps: WorldSteps,
    q: wp.array(dtype=wp.vec3),
    qd: wp.array(dtype=wp.vec3),
):
    """After a frame of ``step_shared_worlds``: particle t of a world that took an odd count goes
    from the spare buffers home to (q, qd)."""
    t = wp.tid()
    if steps.steps[t / particle_count] % 2 == 1:
        q[t] = q_spare[t]
        qd[t] = qd_spare[t]


@wp.func_native("WP_TILE_SYNC();")
def sync_block():
    """Barrier of the thread block (``__syncthreads`` on CUDA; a no-op for CPU launches, whose
    blocks are one thread)."""
    ...


@wp.kernel
def frame_shared_worlds(
    q: wp.array(dtype=wp.vec3),
    qd: wp.array(dtype=wp.vec3),
    q_spare: wp.array(dtype=wp.vec3),
    qd_spare: wp.array(dtype=wp.vec3),
    mass: wp.array(dtype=float),
    inv_mass: wp.array(dtype=float),
    radius: wp.array(dtype=float),
    world_gravity: wp.array(dtype=wp.vec3),
    particle_count: int,
    lanes: int,
    springs: SharedSprings,
    walls: WorldWalls,
    steps: WorldSteps,
    marks: CellMarks,
):
    """A whole frame in one launch, one thread block per world: world w takes ``steps.steps[w]``
    steps of ``steps.h[w]`` [s] (a block is one world, so its loop count is uniform across its
    lanes); launched with dim = world_count x ``lanes`` and block_dim = ``lanes`` (1 on the CPU:
    one thread steps a whole world). Lane l steps particles l, l + lanes, ... of its world from
    one buffer pair into the other (q, qd -> spares on even steps, back on odd ones), then the
    block waits for every lane (``sync_block``) before the next step reads its neighbours; after
    an odd count each lane copies its own particles home. The same arithmetic as
    ``step_shared_worlds``, sub-step by sub-step: the same bits. ``marks``: the world's last
    sub-step's positions mark their cells, which the block folds into its world's words after the
    barrier."""
    tid = wp.tid()
    w = tid / lanes
    lane = tid - w * lanes
    first = w * particle_count
    n = steps.steps[w]
    h = steps.h[w]
    for k in range(n):
        p = lane
        while p < particle_count:
            t = first + p
            if k % 2 == 0:
                x, v = step_shared_particle(t, w, p, first, q, qd, mass, inv_mass, radius, world_gravity, springs,
                                            walls, h)
                q_spare[t] = x
                qd_spare[t] = v
            else:
                x, v = step_shared_particle(t, w, p, first, q_spare, qd_spare, mass, inv_mass, radius,
                                            world_gravity, springs, walls, h)
                q[t] = x
                qd[t] = v
            if k == n - 1:
                mark_cell(marks, w, x)
            p += lanes
        sync_block()
    fold_world_marks(marks, w, lane, lanes)
    if n % 2 == 1:
        p = lane
        while p < particle_count:
            q[first + p] = q_spare[first + p]
            qd[first + p] = qd_spare[first + p]
            p += lanes
