"""One fused semi-implicit Euler step of many mass-spring worlds that share one topology.

World w owns particles ``w P .. (w + 1) P - 1`` (state, masses, radii per world); the springs,
their CSR adjacency and the base values of their parameters are stored ONCE (world 0's, local
particle indices), and a parameter that differs between worlds is ``coefficient[e] *
world_values[w K + key[e]]`` (the tiling rule of ``kernels/worlds.py: tile_float``, evaluated on
the fly). Per particle, one thread does what the generic Simulator does in its passes, with the
same arithmetic in the same order, so the results are bit-identical to it:

  f = 0 + m g_w                               (``seed_forces`` / ``eval_gravity_worlds``)
  f = f + sum of its springs in CSR order      (``kernels/forces.py: eval_springs_gather``)
  v = v + (h / m) f, x = x + h v               (``kernels/integrate.py: step_particles_semi_implicit``)
  every plane of every wall collider in order  (``kernels/collide.py: resolve_plane``)

Reads (q, qd), writes (q_out, qd_out): other threads read this step's positions of the
neighbours, so the stepper ping-pongs two buffers.
"""

import warp as wp

from .collide import resolve_plane
from .forces import damped_spring_force

wp.set_module_options({"enable_backward": False})


@wp.func
def world_value(base: wp.array(dtype=float), key: wp.array(dtype=int), coefficient: wp.array(dtype=float),
                world_values: wp.array(dtype=float), key_count: int, e: int, w: int) -> float:
    """Element e's value in world w: base[e], or coefficient[e] * world_values[w K + key[e]] when
    it scales with a varied parameter (bit-identical to ``tile_float``)."""
    k = key[e]
    if k < 0:
        return base[e]
    return coefficient[e] * world_values[w * key_count + k]


@wp.struct
class SharedSprings:
    """One world's springs, shared by every world: CSR adjacency (offsets (P + 1,), springs
    (2 S,)), ends (2 S,) as local particle indices, and (base, key, coefficient) (S,) of the rest
    length [m], stiffness [N/m] and damping [N s/m] (see ``world_value``)."""

    offsets: wp.array(dtype=int)
    springs: wp.array(dtype=int)
    ends: wp.array(dtype=int)
    rest_base: wp.array(dtype=float)
    rest_key: wp.array(dtype=int)
    rest_coefficient: wp.array(dtype=float)
    stiffness_base: wp.array(dtype=float)
    stiffness_key: wp.array(dtype=int)
    stiffness_coefficient: wp.array(dtype=float)
    damping_base: wp.array(dtype=float)
    damping_key: wp.array(dtype=int)
    damping_coefficient: wp.array(dtype=float)
    world_values: wp.array(dtype=float)
    key_count: int


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
    h: float,
    q_out: wp.array(dtype=wp.vec3),
    qd_out: wp.array(dtype=wp.vec3),
):
    """One step of particle t = w P + p (module docstring); P = ``particle_count`` per world, h [s]."""
    t = wp.tid()
    w = t / particle_count
    p = t - w * particle_count
    first = w * particle_count
    f = wp.vec3() + mass[t] * world_gravity[w]
    fs = wp.vec3()
    for a in range(springs.offsets[p], springs.offsets[p + 1]):
        s = springs.springs[a]
        si = springs.ends[2 * s]
        sj = springs.ends[2 * s + 1]
        rest = world_value(springs.rest_base, springs.rest_key, springs.rest_coefficient, springs.world_values,
                           springs.key_count, s, w)
        k = world_value(springs.stiffness_base, springs.stiffness_key, springs.stiffness_coefficient,
                        springs.world_values, springs.key_count, s, w)
        kd = world_value(springs.damping_base, springs.damping_key, springs.damping_coefficient,
                         springs.world_values, springs.key_count, s, w)
        fij = damped_spring_force(q[first + si], q[first + sj], qd[first + si], qd[first + sj], rest, k, kd)
        if si == p:
            fs = fs + fij
        else:
            fs = fs - fij
    f = f + fs
    x = q[t]
    im = inv_mass[t]
    v = qd[t] + (h * im) * f
    x = x + h * v
    if im != 0.0:
        d = radius[t]
        for g in range(walls.normals.shape[0]):
            c = walls.collider[g]
            wc = w * walls.collider_count + c
            x, v = resolve_plane(x, v, walls.normals[g], walls.offsets[g], d + walls.thickness[c], walls.mode[c],
                                 walls.restitution[wc], walls.friction[wc], walls.stiffness[c],
                                 walls.damping_ratio[wc], im, h)
    q_out[t] = x
    qd_out[t] = v
