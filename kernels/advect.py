"""Advection on a MAC grid: trilinear sampling of staggered fields, an RK2 back-trace,
semi-Lagrangian advection, MacCormack and BFECC corrections with a min/max limiter, and
RK2 particle advection through the grid velocity.

Grid conventions (shared by every grid kernel): cell (i, j, k) spans
``origin + [i, i+1] x [j, j+1] x [k, k+1] * dx``. A staggered field ``f`` of shape (n0, n1, n2)
stores the value at ``origin + ((i, j, k) + offset) * dx``: cell centres have offset
(0.5, 0.5, 0.5), x-faces (u) (0, 0.5, 0.5), y-faces (v) (0.5, 0, 0.5), z-faces (w) (0.5, 0.5, 0).
A 2D grid is a 3D grid one cell thick (nz = 1) with w = 0. Samples outside a field clamp to its
nearest stored values.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})

OFFSET_U = wp.constant(wp.vec3(0.0, 0.5, 0.5))
OFFSET_V = wp.constant(wp.vec3(0.5, 0.0, 0.5))
OFFSET_W = wp.constant(wp.vec3(0.5, 0.5, 0.0))


@wp.func
def _axis_cell(g: float, n: int):
    """Clamped lower index and fraction along one axis for continuous index g."""
    x = wp.clamp(g, 0.0, float(n - 1))
    i = wp.min(int(x), wp.max(n - 2, 0))
    return i, x - float(i)


@wp.func
def sample_grid(f: wp.array3d(dtype=float), g: wp.vec3) -> float:
    """Trilinear interpolation of ``f`` at continuous index ``g`` (in stored-value units)."""
    i, tx = _axis_cell(g[0], f.shape[0])
    j, ty = _axis_cell(g[1], f.shape[1])
    k, tz = _axis_cell(g[2], f.shape[2])
    i1 = wp.min(i + 1, f.shape[0] - 1)
    j1 = wp.min(j + 1, f.shape[1] - 1)
    k1 = wp.min(k + 1, f.shape[2] - 1)
    c00 = wp.lerp(f[i, j, k], f[i1, j, k], tx)
    c10 = wp.lerp(f[i, j1, k], f[i1, j1, k], tx)
    c01 = wp.lerp(f[i, j, k1], f[i1, j, k1], tx)
    c11 = wp.lerp(f[i, j1, k1], f[i1, j1, k1], tx)
    return wp.lerp(wp.lerp(c00, c10, ty), wp.lerp(c01, c11, ty), tz)


@wp.func
def sample_minmax(f: wp.array3d(dtype=float), g: wp.vec3) -> wp.vec2:
    """(min, max) of the 8 stored values ``sample_grid(f, g)`` interpolates (the limiter's bounds)."""
    i, _tx = _axis_cell(g[0], f.shape[0])
    j, _ty = _axis_cell(g[1], f.shape[1])
    k, _tz = _axis_cell(g[2], f.shape[2])
    lo = f[i, j, k]
    hi = lo
    for a in range(2):
        for b in range(2):
            for c in range(2):
                x = f[wp.min(i + a, f.shape[0] - 1), wp.min(j + b, f.shape[1] - 1), wp.min(k + c, f.shape[2] - 1)]
                lo = wp.min(lo, x)
                hi = wp.max(hi, x)
    return wp.vec2(lo, hi)


@wp.func
def sample_at(f: wp.array3d(dtype=float), offset: wp.vec3, origin: wp.vec3, inv_dx: float, x: wp.vec3) -> float:
    """Value of staggered field ``f`` (stored at ``origin + (idx + offset) dx``) at world point ``x`` [m]."""
    return sample_grid(f, (x - origin) * inv_dx - offset)


@wp.func
def sample_velocity(
    u: wp.array3d(dtype=float),
    v: wp.array3d(dtype=float),
    w: wp.array3d(dtype=float),
    origin: wp.vec3,
    inv_dx: float,
    x: wp.vec3,
) -> wp.vec3:
    """MAC-grid velocity [m/s] at world point ``x`` [m] (each component interpolated on its faces)."""
    g = (x - origin) * inv_dx
    return wp.vec3(sample_grid(u, g - OFFSET_U), sample_grid(v, g - OFFSET_V), sample_grid(w, g - OFFSET_W))


@wp.func
def backtrace_rk2(
    u: wp.array3d(dtype=float),
    v: wp.array3d(dtype=float),
    w: wp.array3d(dtype=float),
    origin: wp.vec3,
    inv_dx: float,
    x: wp.vec3,
    dt: float,
) -> wp.vec3:
    """Midpoint (RK2) trace of ``x`` through the velocity over ``-dt`` (dt < 0 traces forward)."""
    v0 = sample_velocity(u, v, w, origin, inv_dx, x)
    xm = x - 0.5 * dt * v0
    return x - dt * sample_velocity(u, v, w, origin, inv_dx, xm)


@wp.func
def stored_position(i: int, j: int, k: int, offset: wp.vec3, origin: wp.vec3, dx: float) -> wp.vec3:
    return origin + (wp.vec3(float(i), float(j), float(k)) + offset) * dx


@wp.kernel
def advect_semi_lagrangian(
    f_in: wp.array3d(dtype=float),
    offset: wp.vec3,
    u: wp.array3d(dtype=float),
    v: wp.array3d(dtype=float),
    w: wp.array3d(dtype=float),
    origin: wp.vec3,
    dx: float,
    dt: float,
    f_out: wp.array3d(dtype=float),
):
    """f_out(x) = f_in(x_back), x_back the RK2 back-trace of the stored point x over dt [s]."""
    i, j, k = wp.tid()
    inv_dx = 1.0 / dx
    x = stored_position(i, j, k, offset, origin, dx)
    xb = backtrace_rk2(u, v, w, origin, inv_dx, x, dt)
    f_out[i, j, k] = sample_at(f_in, offset, origin, inv_dx, xb)


@wp.kernel
def advect_limited(
    f_src: wp.array3d(dtype=float),
    f_ref: wp.array3d(dtype=float),
    f_hat: wp.array3d(dtype=float),
    f_bar: wp.array3d(dtype=float),
    scheme: int,
    offset: wp.vec3,
    u: wp.array3d(dtype=float),
    v: wp.array3d(dtype=float),
    w: wp.array3d(dtype=float),
    origin: wp.vec3,
    dx: float,
    dt: float,
    f_out: wp.array3d(dtype=float),
):
    """Second-order corrections of semi-Lagrangian advection, clamped to the min/max of the
    8 values of ``f_ref`` around the back-traced point (Selle et al. 2008):

    scheme 0, MacCormack: f_out = f_hat + (f_src - f_bar) / 2, with f_hat = SL(f_src, dt) and
    f_bar = SL(f_hat, -dt);
    scheme 1, BFECC final pass: f_out = SL(f_src, dt) where f_src = f + (f - f_bar) / 2."""
    i, j, k = wp.tid()
    inv_dx = 1.0 / dx
    x = stored_position(i, j, k, offset, origin, dx)
    xb = backtrace_rk2(u, v, w, origin, inv_dx, x, dt)
    g = (xb - origin) * inv_dx - offset
    value = float(0.0)
    if scheme == 0:
        value = f_hat[i, j, k] + 0.5 * (f_src[i, j, k] - f_bar[i, j, k])
    else:
        value = sample_grid(f_src, g)
    bounds = sample_minmax(f_ref, g)
    f_out[i, j, k] = wp.clamp(value, bounds[0], bounds[1])


@wp.kernel
def bfecc_midpoint(f: wp.array3d(dtype=float), f_bar: wp.array3d(dtype=float), f_out: wp.array3d(dtype=float)):
    """f_out = f + (f - f_bar) / 2: the error-compensated field BFECC advects in its last pass."""
    i, j, k = wp.tid()
    f_out[i, j, k] = f[i, j, k] + 0.5 * (f[i, j, k] - f_bar[i, j, k])


@wp.kernel
def advect_particles_rk2(
    u: wp.array3d(dtype=float),
    v: wp.array3d(dtype=float),
    w: wp.array3d(dtype=float),
    origin: wp.vec3,
    dx: float,
    dt: float,
    lower: wp.vec3,
    upper: wp.vec3,
    count: wp.array(dtype=int),
    x_io: wp.array(dtype=wp.vec3),
):
    """Move particles i < count[0] along the grid velocity by midpoint RK2 over dt [s],
    clamped into the box [lower, upper] [m]."""
    i = wp.tid()
    if i >= count[0]:
        return
    inv_dx = 1.0 / dx
    x = backtrace_rk2(u, v, w, origin, inv_dx, x_io[i], -dt)
    x_io[i] = wp.vec3(
        wp.clamp(x[0], lower[0], upper[0]), wp.clamp(x[1], lower[1], upper[1]), wp.clamp(x[2], lower[2], upper[2])
    )
