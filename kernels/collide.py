"""Collision kernels, run after integration on the new positions and velocities (in place).

Plane convention: a plane is ``n . x = offset`` with unit normal ``n`` pointing into the free
side. A particle of radius ``r`` penetrates by ``h = r - (n . x - offset)`` when ``h > 0``.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})

COLLIDE_REFLECT = wp.constant(0)
COLLIDE_PROJECT = wp.constant(1)


@wp.func
def respond_velocity(v: wp.vec3, n: wp.vec3, restitution: float, friction: float) -> wp.vec3:
    """Normal velocity v_n -> -e v_n when approaching; Coulomb friction removes at most
    mu (1 + e) |v_n| of tangential speed and never reverses it."""
    vn = wp.dot(v, n)
    if vn >= 0.0:
        return v
    vt = v - vn * n
    vt_len = wp.length(vt)
    impulse = (1.0 + restitution) * (-vn)
    if vt_len > 0.0:
        vt = vt * wp.max(0.0, 1.0 - friction * impulse / vt_len)
    return vt - restitution * vn * n


@wp.kernel
def collide_planes(
    inv_mass: wp.array(dtype=float),
    radius: wp.array(dtype=float),
    normals: wp.array(dtype=wp.vec3),
    offsets: wp.array(dtype=float),
    restitution: float,
    friction: float,
    mode: int,
    q_io: wp.array(dtype=wp.vec3),
    qd_io: wp.array(dtype=wp.vec3),
):
    """Resolve particle i against every plane of one collider.

    reflect: the position is mirrored out of the plane scaled by restitution, h' = e h;
    project: the particle is placed on the plane (position correction)."""
    i = wp.tid()
    if inv_mass[i] == 0.0:
        return
    x = q_io[i]
    v = qd_io[i]
    for p in range(normals.shape[0]):
        n = normals[p]
        h = radius[i] - (wp.dot(n, x) - offsets[p])
        if h > 0.0:
            if mode == COLLIDE_REFLECT:
                x = x + (1.0 + restitution) * h * n
            else:
                x = x + h * n
            v = respond_velocity(v, n, restitution, friction)
    q_io[i] = x
    qd_io[i] = v
