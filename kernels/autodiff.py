"""Kernels of differentiable runs (``warpsim.diff``), compiled with their adjoints.

A differentiable step reads one state and writes another (out of place), so that the tape can
replay every launch backwards with its inputs intact. Nothing here is a new formula:

- ``rk_stage`` and ``step_semi_implicit_euler`` are the integrators' own kernels
  (``kernels/integrate.py``) registered a second time in this module with the backward pass on;
- ``collide_plane_out`` / ``collide_capsule_out`` call the colliders' shared funcs
  (``resolve_plane``, ``capsule_contact_point``, ``apply_local_contact``) with discrete
  detection, one plane per launch (a loop that rewrites (x, v) is not differentiable in Warp);
- ``integrate_cloth_out`` is the cloth solver's fused update ``v += h (w f + g), x += h v``
  (the func ``cloth_velocity`` of ``integrate_cloth_particles``) reading (q, qd, f) and writing
  (q_out, qd_out).

Arrays: positions ``q`` [m], velocities ``qd`` [m/s], forces ``f`` [N], shape (particle_count,),
``wp.vec3``; ``inv_mass`` [1/kg], float (0 = pinned).
"""

import warp as wp

from . import integrate as _integrate
from .cloth import cloth_velocity
from .collide import apply_local_contact, capsule_contact_point, resolve_plane

wp.set_module_options({"enable_backward": True})

_V = wp.array(dtype=wp.vec3)
_F = wp.array(dtype=float)

# The integrators' kernels, the same Python functions, with adjoints (vec3 coordinates).
rk_stage = wp.kernel(_integrate.rk_stage.func, enable_backward=True, module=__name__)
step_semi_implicit_euler = wp.kernel(_integrate.step_semi_implicit_euler.func, enable_backward=True,
                                     module=__name__)
wp.overload(rk_stage, [_V, _V, _V, _V, _F, float, _V, _V])
wp.overload(step_semi_implicit_euler, [_V, _V, _V, _F, float, _V, _V])


@wp.kernel
def integrate_cloth_out(
    q: wp.array(dtype=wp.vec3),
    qd: wp.array(dtype=wp.vec3),
    f: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    gravity: wp.vec3,
    h: float,
    q_out: wp.array(dtype=wp.vec3),
    qd_out: wp.array(dtype=wp.vec3),
):
    """Cloth semi-implicit Euler (``kernels/cloth.py: integrate_cloth_particles``) out of place:
    v = qd + h (w f + g) on free particles (pinned keep qd), x = q + h v."""
    i = wp.tid()
    v = cloth_velocity(qd[i], f[i], inv_mass[i], gravity, h)
    qd_out[i] = v
    q_out[i] = q[i] + h * v


@wp.kernel
def collide_plane_out(
    inv_mass: wp.array(dtype=float),
    radius: wp.array(dtype=float),
    normals: wp.array(dtype=wp.vec3),
    offsets: wp.array(dtype=float),
    plane: int,
    restitution: float,
    friction: float,
    mode: int,
    thickness: float,
    stiffness: float,
    damping_ratio: float,
    dt: float,
    q_start: wp.array(dtype=wp.vec3),
    forces: wp.array(dtype=wp.vec3),
    q: wp.array(dtype=wp.vec3),
    qd: wp.array(dtype=wp.vec3),
    q_out: wp.array(dtype=wp.vec3),
    qd_out: wp.array(dtype=wp.vec3),
):
    """Plane ``plane`` of a Planes collider against every particle, (q, qd) -> (q_out, qd_out)."""
    i = wp.tid()
    x = q[i]
    v = qd[i]
    w = inv_mass[i]
    if w != 0.0:
        x, v = resolve_plane(x, v, q_start[i], w * forces[i], normals[plane], offsets[plane], radius[i] + thickness,
                             mode, restitution, friction, stiffness, damping_ratio, w, dt)
    q_out[i] = x
    qd_out[i] = v


@wp.kernel
def collide_capsule_out(
    inv_mass: wp.array(dtype=float),
    radius: wp.array(dtype=float),
    a: wp.vec3,
    b: wp.vec3,
    shape_radius: float,
    inside: int,
    pose_prev: wp.transform,
    pose: wp.transform,
    restitution: float,
    friction: float,
    mode: int,
    thickness: float,
    stiffness: float,
    damping_ratio: float,
    dt: float,
    q_start: wp.array(dtype=wp.vec3),
    forces: wp.array(dtype=wp.vec3),
    q: wp.array(dtype=wp.vec3),
    qd: wp.array(dtype=wp.vec3),
    q_out: wp.array(dtype=wp.vec3),
    qd_out: wp.array(dtype=wp.vec3),
):
    """A static capsule or sphere (a == b) with discrete detection (``continuous=False``),
    (q, qd) -> (q_out, qd_out); the same funcs as ``collide_capsule``."""
    i = wp.tid()
    x = q[i]
    v = qd[i]
    w = inv_mass[i]
    if w != 0.0:
        d = radius[i] + thickness
        r = shape_radius + d
        if inside == 1:
            r = shape_radius - d
        xl = wp.transform_point(wp.transform_inverse(pose), x)
        x0l = wp.transform_point(wp.transform_inverse(pose_prev), q_start[i])
        h, nl, pl = capsule_contact_point(xl, a, b, r, inside)
        x, v = apply_local_contact(h, nl, pl, x0l, xl, w * forces[i], x, v, pose_prev, pose, mode, restitution,
                                   friction, stiffness, damping_ratio, w, dt)
    q_out[i] = x
    qd_out[i] = v


@wp.kernel
def advance_time_out(time: wp.array(dtype=float), h: float, time_out: wp.array(dtype=float)):
    """time_out[0] = time[0] + h (the per-step clock of a differentiable run)."""
    time_out[0] = time[0] + h


@wp.kernel
def dot_accumulate(a: wp.array(dtype=wp.vec3), b: wp.array(dtype=wp.vec3), slot: int, out: wp.array(dtype=float)):
    """out[slot] += sum_i a_i . b_i (coefficient gradients: a force per unit coefficient
    against the adjoint of the step's total force)."""
    i = wp.tid()
    wp.atomic_add(out, slot, wp.dot(a[i], b[i]))


@wp.kernel
def squared_distance(
    q: wp.array(dtype=wp.vec3),
    target: wp.array(dtype=wp.vec3),
    weight: float,
    loss: wp.array(dtype=float),
):
    """loss[0] += weight |q_i - target_i|^2 summed over particles [weight m^2]."""
    i = wp.tid()
    d = q[i] - target[i]
    wp.atomic_add(loss, 0, weight * wp.dot(d, d))


@wp.kernel
def mass_gradient(
    mass: wp.array(dtype=float),
    mass_grad: wp.array(dtype=float),
    inv_mass_grad: wp.array(dtype=float),
    out: wp.array(dtype=float),
):
    """dL/dm = dL/dm (direct, gravity) + dL/dw dw/dm with w = 1/m (0 for pinned particles)."""
    i = wp.tid()
    m = mass[i]
    g = mass_grad[i]
    if m > 0.0:
        g = g - inv_mass_grad[i] / (m * m)
    out[i] = g

