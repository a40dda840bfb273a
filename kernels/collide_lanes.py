"""Colliders on the CPU, eight consecutive particles a thread (``warpsim.bodies.colliders``).

A thread loads its eight particles into ``lane8`` vectors and a vector filter finds the lanes that
may touch the shape (with a margin for rounding); only those run ``kernels/collide.py``'s
per-particle functions, once each, so the one-thread-per-particle kernels' bits. Particles far
from every shape (most of a cloth, most of the time) cost a few vector operations. A separate
module from ``cloth_lanes`` so that a floor does not compile the cloth step.
"""

import warp as wp

from .cloth_lanes import LANES, lane8
from .collide import collide_particle_capsule, collide_particle_planes

wp.set_module_options({"enable_backward": False})


@wp.func
def load_positions(q: wp.array(dtype=wp.vec3), base: int, count: int):
    """Particles base .. base + 7 of q (the last of ``count`` repeated past the end) as lanes."""
    x = lane8()
    y = lane8()
    z = lane8()
    for c in range(LANES):
        p = q[wp.min(base + c, count - 1)]
        x[c] = p[0]
        y[c] = p[1]
        z[c] = p[2]
    return x, y, z


@wp.func
def lane_l1(x: lane8, y: lane8, z: lane8) -> lane8:
    """|x| + |y| + |z| lane by lane."""
    return wp.abs(x) + wp.abs(y) + wp.abs(z)


@wp.func
def load_radii(radius: wp.array(dtype=float), thickness: float, base: int, count: int) -> lane8:
    """radius + thickness [m] of particles base .. base + 7 (clamped as ``load_positions``)."""
    d = lane8()
    for c in range(LANES):
        d[c] = radius[wp.min(base + c, count - 1)] + thickness
    return d


@wp.kernel
def collide_planes_lanes(
    count: int,
    inv_mass: wp.array(dtype=float),
    radius: wp.array(dtype=float),
    normals: wp.array(dtype=wp.vec3),
    offsets: wp.array(dtype=float),
    restitution: float,
    friction: float,
    mode: int,
    thickness: float,
    stiffness: float,
    damping_ratio: float,
    dt: float,
    q_prev: wp.array(dtype=wp.vec3),
    forces: wp.array(dtype=wp.vec3),
    q_io: wp.array(dtype=wp.vec3),
    qd_io: wp.array(dtype=wp.vec3),
):
    """``collide_planes`` on particles 8t .. 8t + 7 (t = tid, ceil(count / 8) threads): lanes whose
    depth against some plane is above -1e-5 of the coordinates' scale run
    ``collide_particle_planes`` (which tests exactly); the others cannot touch."""
    base = LANES * wp.tid()
    x, y, z = load_positions(q_io, base, count)
    d = load_radii(radius, thickness, base, count)
    scale = lane_l1(x, y, z) + d
    near = lane8()
    for p in range(normals.shape[0]):
        n = normals[p]
        o = offsets[p]
        h = d - (n[0] * x + n[1] * y + n[2] * z - lane8(o)) + 1.0e-5 * (scale + lane8(wp.abs(o)))
        near = wp.max(near, h)
    for c in range(LANES):
        if near[c] > 0.0 and base + c < count:
            collide_particle_planes(base + c, inv_mass, radius, normals, offsets, restitution, friction, mode,
                                    thickness, stiffness, damping_ratio, dt, q_prev, forces, q_io, qd_io)


@wp.kernel
def collide_capsule_lanes(
    count: int,
    inv_mass: wp.array(dtype=float),
    radius: wp.array(dtype=float),
    q_prev: wp.array(dtype=wp.vec3),
    continuous: int,
    a: wp.vec3,
    b: wp.vec3,
    shape_radius: float,
    inside: int,
    pose_prev: wp.transform,
    pose: wp.transform,
    far_center: wp.vec3,
    far_half: float,
    restitution: float,
    friction: float,
    mode: int,
    thickness: float,
    stiffness: float,
    damping_ratio: float,
    dt: float,
    forces: wp.array(dtype=wp.vec3),
    q_io: wp.array(dtype=wp.vec3),
    qd_io: wp.array(dtype=wp.vec3),
):
    """``collide_capsule`` on particles 8t .. 8t + 7 (t = tid): with far_half >= 0 (a static solid
    shape) ``out_of_reach``'s test in lanes keeps the lanes that may touch, which run
    ``collide_particle_capsule``; otherwise every lane runs it."""
    base = LANES * wp.tid()
    near = lane8(1.0)
    if far_half >= 0.0:
        x, y, z = load_positions(q_io, base, count)
        x0, y0, z0 = load_positions(q_prev, base, count)
        r = load_radii(radius, thickness, base, count) + lane8(shape_radius)
        ex = x - lane8(far_center[0])
        ey = y - lane8(far_center[1])
        ez = z - lane8(far_center[2])
        dist2 = wp.cw_mul(ex, ex) + wp.cw_mul(ey, ey) + wp.cw_mul(ez, ez)
        reach = lane_l1(x - x0, y - y0, z - z0) + lane8(far_half) + r
        center = lane8(wp.abs(far_center[0]) + wp.abs(far_center[1]) + wp.abs(far_center[2]))
        margin = 1.0e-5 * (lane_l1(x, y, z) + center + reach) + 2.0e-5 * wp.cw_div(dist2 + wp.cw_mul(reach, reach), r)
        bound = reach + margin
        near = wp.cw_mul(bound, bound) - dist2
    for c in range(LANES):
        if not (near[c] < 0.0) and base + c < count:  # NaN: the full test, as collide_capsule
            collide_particle_capsule(base + c, inv_mass, radius, q_prev, continuous, a, b, shape_radius, inside,
                                     pose_prev, pose, far_center, far_half, restitution, friction, mode, thickness,
                                     stiffness, damping_ratio, dt, forces, q_io, qd_io)
