"""Interaction kernels: the drag spring that pulls a grabbed particle toward a (keyframed)
target, its Jacobian for implicit Euler, and the particle-to-ray distances used for picking.

The drag state lives in device arrays so a captured step replays correctly: ``grab`` (1,) int
particle index (-1: nothing grabbed), ``window`` (2,) [s] the times the grab starts and is
released, ``key_times`` (K,) [s] and ``key_points`` (K,) [m] the target path (piecewise linear,
held constant before the first and after the last key).
"""

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.func
def keyframe_target(t: float, key_times: wp.array(dtype=float), key_points: wp.array(dtype=wp.vec3)):
    """Target position [m] and velocity [m/s] at time t on the piecewise-linear path."""
    count = key_times.shape[0]
    if t <= key_times[0]:
        return key_points[0], wp.vec3(0.0)
    if t >= key_times[count - 1]:
        return key_points[count - 1], wp.vec3(0.0)
    k = int(0)  # noqa: UP018, RUF046 (a Warp dynamic variable)
    while key_times[k + 1] < t:
        k += 1
    span = key_times[k + 1] - key_times[k]
    s = (t - key_times[k]) / span
    p = key_points[k] + s * (key_points[k + 1] - key_points[k])
    return p, (key_points[k + 1] - key_points[k]) / span


@wp.func
def drag_active(grab: wp.array(dtype=int), window: wp.array(dtype=float), t: float) -> int:
    p = grab[0]
    if p < 0 or t < window[0] or t > window[1]:
        return -1
    return p


@wp.kernel
def eval_drag_spring(
    q: wp.array(dtype=wp.vec3),
    qd: wp.array(dtype=wp.vec3),
    grab: wp.array(dtype=int),
    window: wp.array(dtype=float),
    key_times: wp.array(dtype=float),
    key_points: wp.array(dtype=wp.vec3),
    time: wp.array(dtype=float),
    time_offset: float,
    stiffness: float,
    damping: float,
    f_out: wp.array(dtype=wp.vec3),
):
    """f[p] += -k (x_p - target) - c (v_p - v_target) for the grabbed particle p (one thread)."""
    t = time[0] + time_offset
    p = drag_active(grab, window, t)
    if p < 0:
        return
    target, target_velocity = keyframe_target(t, key_times, key_points)
    f = -stiffness * (q[p] - target) - damping * (qd[p] - target_velocity)
    f_out[p] = f_out[p] + f


@wp.kernel
def eval_drag_spring_jacobian(
    grab: wp.array(dtype=int),
    window: wp.array(dtype=float),
    time: wp.array(dtype=float),
    time_offset: float,
    stiffness: float,
    damping: float,
    ck: float,
    cd: float,
    diag_out: wp.array(dtype=wp.mat33),
):
    """diag[p] += ck (-k I) + cd (-c I) for the grabbed particle p."""
    p = drag_active(grab, window, time[0] + time_offset)
    if p < 0:
        return
    s = -(ck * stiffness + cd * damping)
    diag_out[p] = diag_out[p] + wp.mat33(s, 0.0, 0.0, 0.0, s, 0.0, 0.0, 0.0, s)


@wp.kernel
def distance_to_ray(
    q: wp.array(dtype=wp.vec3),
    origin: wp.vec3,
    direction: wp.vec3,
    dist_out: wp.array(dtype=float),
):
    """Distance [m] from each particle to the ray origin + t direction, t >= 0 (unit direction)."""
    i = wp.tid()
    d = q[i] - origin
    t = wp.max(0.0, wp.dot(d, direction))
    dist_out[i] = wp.length(d - t * direction)
