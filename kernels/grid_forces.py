"""Body forces on MAC-grid face velocities: constant acceleration (gravity), buoyancy from
smoke density and temperature, and vorticity confinement. Layout: see kernels/advect.py."""

import warp as wp

from .grid import axis_step

wp.set_module_options({"enable_backward": False})


@wp.kernel
def add_constant(value: float, f_io: wp.array3d(dtype=float)):
    """f += value (e.g. one component of g dt) on every face."""
    i, j, k = wp.tid()
    f_io[i, j, k] = f_io[i, j, k] + value


@wp.kernel
def add_buoyancy(
    density: wp.array3d(dtype=float),
    temperature: wp.array3d(dtype=float),
    alpha: float,
    beta: float,
    ambient: float,
    dt: float,
    v_io: wp.array3d(dtype=float),
):
    """Interior y-faces: v += dt (-alpha rho + beta (T - T_ambient)), rho and T averaged from the
    two cells the face separates (Fedkiw, Stam and Jensen 2001). alpha [m^4/(kg s^2)] scales
    density [kg/m^3], beta [m/(s^2 K)] temperature [K]."""
    i, j, k = wp.tid()
    if j == 0 or j == density.shape[1]:
        return
    rho = 0.5 * (density[i, j - 1, k] + density[i, j, k])
    t = 0.5 * (temperature[i, j - 1, k] + temperature[i, j, k])
    v_io[i, j, k] = v_io[i, j, k] + dt * (-alpha * rho + beta * (t - ambient))


@wp.func
def _cell_velocity(u: wp.array3d(dtype=float), v: wp.array3d(dtype=float), w: wp.array3d(dtype=float),
                   i: int, j: int, k: int) -> wp.vec3:
    return 0.5 * wp.vec3(u[i, j, k] + u[i + 1, j, k], v[i, j, k] + v[i, j + 1, k], w[i, j, k] + w[i, j, k + 1])


@wp.func
def _clamped(i: int, n: int) -> int:
    return wp.clamp(i, 0, n - 1)


@wp.kernel
def compute_vorticity(
    u: wp.array3d(dtype=float),
    v: wp.array3d(dtype=float),
    w: wp.array3d(dtype=float),
    dx: float,
    omega_out: wp.array3d(dtype=wp.vec3),
):
    """Vorticity curl(u) [1/s] at cell centres, central differences of cell-centred velocities
    (one-sided at the grid boundary)."""
    i, j, k = wp.tid()
    nx = omega_out.shape[0]
    ny = omega_out.shape[1]
    nz = omega_out.shape[2]
    ip = _clamped(i + 1, nx)
    im = _clamped(i - 1, nx)
    jp = _clamped(j + 1, ny)
    jm = _clamped(j - 1, ny)
    kp = _clamped(k + 1, nz)
    km = _clamped(k - 1, nz)
    hx = wp.max(float(ip - im), 1.0) * dx
    hy = wp.max(float(jp - jm), 1.0) * dx
    hz = wp.max(float(kp - km), 1.0) * dx
    dudx = (_cell_velocity(u, v, w, ip, j, k) - _cell_velocity(u, v, w, im, j, k)) / hx
    dudy = (_cell_velocity(u, v, w, i, jp, k) - _cell_velocity(u, v, w, i, jm, k)) / hy
    dudz = (_cell_velocity(u, v, w, i, j, kp) - _cell_velocity(u, v, w, i, j, km)) / hz
    omega_out[i, j, k] = wp.vec3(dudy[2] - dudz[1], dudz[0] - dudx[2], dudx[1] - dudy[0])


@wp.kernel
def vorticity_confinement_force(
    omega: wp.array3d(dtype=wp.vec3),
    epsilon: float,
    dx: float,
    force_out: wp.array3d(dtype=wp.vec3),
):
    """f = epsilon dx (N x omega), N = grad|omega| / |grad|omega|| [m/s^2] at cell centres
    (Fedkiw, Stam and Jensen 2001)."""
    i, j, k = wp.tid()
    nx = omega.shape[0]
    ny = omega.shape[1]
    nz = omega.shape[2]
    gx = wp.length(omega[_clamped(i + 1, nx), j, k]) - wp.length(omega[_clamped(i - 1, nx), j, k])
    gy = wp.length(omega[i, _clamped(j + 1, ny), k]) - wp.length(omega[i, _clamped(j - 1, ny), k])
    gz = wp.length(omega[i, j, _clamped(k + 1, nz)]) - wp.length(omega[i, j, _clamped(k - 1, nz)])
    g = wp.vec3(gx, gy, gz)
    n = g / (wp.length(g) + 1.0e-12)
    force_out[i, j, k] = epsilon * dx * wp.cross(n, omega[i, j, k])


@wp.kernel
def add_cell_force(force: wp.array3d(dtype=wp.vec3), axis: int, dt: float, f_io: wp.array3d(dtype=float)):
    """Interior faces along ``axis``: f += dt * mean of the two adjacent cells' force component."""
    i, j, k = wp.tid()
    a = wp.vec3i(i, j, k)
    if a[axis] == 0 or a[axis] == force.shape[axis]:
        return
    b = a - axis_step(axis)
    f_io[i, j, k] = f_io[i, j, k] + 0.5 * dt * (force[i, j, k][axis] + force[b[0], b[1], b[2]][axis])


@wp.kernel
def source_in_box(
    lower: wp.vec3, upper: wp.vec3, value: float, origin: wp.vec3, dx: float, f_io: wp.array3d(dtype=float)
):
    """Source term: f = max(f, value) at cell centres inside [lower, upper] [m]."""
    i, j, k = wp.tid()
    x = origin + (wp.vec3(float(i), float(j), float(k)) + wp.vec3(0.5)) * dx
    inside = x[0] >= lower[0] and x[1] >= lower[1] and x[2] >= lower[2]
    if inside and x[0] <= upper[0] and x[1] <= upper[1] and x[2] <= upper[2]:
        f_io[i, j, k] = wp.max(f_io[i, j, k], value)


@wp.kernel
def zero_in_solid(solid_phi: wp.array3d(dtype=float), f_io: wp.array3d(dtype=float)):
    """f = 0 in solid cells (no smoke inside obstacles)."""
    i, j, k = wp.tid()
    if solid_phi[i, j, k] < 0.0:
        f_io[i, j, k] = 0.0


@wp.kernel
def diffuse_faces(
    f_in: wp.array3d(dtype=float),
    axis: int,
    no_slip: int,
    wall_velocity: wp.array(dtype=wp.vec3),
    coef: float,
    f_out: wp.array3d(dtype=float),
):
    """Explicit viscosity on one velocity component: f += coef * (sum of the 6 neighbours - 6 f),
    coef = nu dt / dx^2. Past a wall in a tangential direction the ghost value is 2 U_t - f for
    no-slip walls moving at U (``wall_velocity[side]``, sides -x, +x, -y, +y, -z, +z) or f for
    free-slip; past a wall in the normal direction the wall face (normal velocity 0) is the
    neighbour. Faces on the walls normal to ``axis`` are left unchanged."""
    i, j, k = wp.tid()
    c = wp.vec3i(i, j, k)
    f = f_in[i, j, k]
    if c[axis] == 0 or c[axis] == f_in.shape[axis] - 1:
        f_out[i, j, k] = f
        return
    s = float(0.0)
    for b in range(3):
        for side in range(2):
            n = c + axis_step(b) * (2 * side - 1)
            if n[b] >= 0 and n[b] < f_in.shape[b]:
                s += f_in[n[0], n[1], n[2]]
            elif no_slip != 0 and f_in.shape[b] > 1:
                s += 2.0 * wall_velocity[2 * b + side][axis] - f
            else:
                s += f
    f_out[i, j, k] = f + coef * (s - 6.0 * f)
