"""Divergence-free SPH (DFSPH; Bender and Koschier 2015/2017) kernels.

Conventions (shared with ``kernels/sph.py``, whose smoothing-kernel, boundary and neighbour-list
helpers these kernels use):

* One position array ``x_all`` holds the static boundary particles first (indices
  ``0 .. boundary_count-1``) and the fluid particles after them (fluid particle i at
  ``boundary_count + i``); both live in the same ``wp.HashGrid``. Boundary particles continue the
  fluid's lattice behind the walls, so each carries a fluid particle's volume ``V = m / rho0``.
* Densities are normalised, rho_hat = rho / rho0 = sum_j V_j W_ij (+ the signed-distance
  boundaries' solid fraction phi). The pressure unknown ``kappa_i`` [m^2/s^2] gives the
  acceleration a_i = -sum_fluid V (kappa_i + kappa_j) grad W_ij - sum_boundary V kappa_i grad W_ib
  - kappa_i grad phi_i, i.e. kappa_i = p_i rho0 / rho_i^2 (pressure p = rho0 rho_hat^2 kappa).
* Every sum is a gather over particle i's neighbour list, in the list's fixed order: no float
  atomics, so two runs give the same bits.
"""

import warp as wp

from .sph import (Boundaries, FluidParams, NeighborList, boundary_density, close_neighbor_list, list_neighbors,
                  pair_terms)

wp.set_module_options({"enable_backward": False})


@wp.struct
class DfsphParams:
    """DFSPH constants besides :class:`FluidParams` (see ``warpsim.particle_fluids.dfsph``)."""

    boundary_count: int  # boundary particles at the front of x_all
    kinematic_viscosity: float  # nu of the SPH (Monaghan) viscosity between fluid particles [m^2/s]
    boundary_viscosity: float  # nu of the same term against boundary particles at rest [m^2/s] (no-slip walls)
    no_slip_start: int  # boundary_viscosity acts against boundary particles no_slip_start <= j < no_slip_end
    no_slip_end: int  # only (0, boundary_count: every wall; 0, floor count: the floor, its particles first)
    viscosity_eps: float  # 0.01 h^2 [m^2], keeps the viscosity term finite at r -> 0
    dimension_factor: float  # 2 (d + 2) = 10 in 3D
    lattice_count: float  # neighbours of a particle inside a full lattice (for the signed-distance walls)
    min_neighbors: float  # fewer (effective) neighbours: a free-surface particle, no divergence correction
    beta_eps: float  # smallest denominator of the DFSPH factor [1/m^2]
    moving_start: int  # boundary particles from this index on move with boundary_velocity (a gate)
    boundary_velocity: wp.vec3  # [m/s]


@wp.func
def boundary_velocity(dp: DfsphParams, j: int) -> wp.vec3:
    """Velocity of boundary particle j [m/s]: the moving ones' (a gate), zero for the walls."""
    if j >= dp.moving_start:
        return dp.boundary_velocity
    return wp.vec3(0.0)


@wp.func
def neighbor_gradient(p: FluidParams, nb: NeighborList, e: int, r2: float) -> float:
    """The gradient factor f of list entry e ((m / rho0) grad W = f (x_i - x_j)), cached or re-evaluated."""
    if nb.cache_gradients != 0:
        return nb.grad_factor[e]
    return pair_terms(p, r2)[1]


@wp.kernel
def find_neighbors_factor(
    grid: wp.uint64,
    p: FluidParams,
    dp: DfsphParams,
    b: Boundaries,
    x_all: wp.array(dtype=wp.vec3),
    nb_out: NeighborList,
    overflow_out: wp.array(dtype=int),
    density_out: wp.array(dtype=float),
    beta_inv_out: wp.array(dtype=float),
    boundary_share_out: wp.array(dtype=float),
    boundary_grad_out: wp.array(dtype=wp.vec3),
    neighbors_out: wp.array(dtype=float),
):
    """For fluid particle i: its neighbour list (fluid and boundary particles of the hash grid with
    |x_i - x_j| < h, indices into x_all), fused with its density rho_i = rho0 (sum_j V_j W_ij + phi_i)
    [kg/m^3], the inverse DFSPH factor 1 / (|sum_j V_j grad W_ij + grad phi_i|^2 + sum_fluid
    |V_j grad W_ij|^2) [m^2] (0 for an isolated particle), the boundary's share of the density
    (particles and signed-distance walls) and the signed-distance walls' gradient grad phi [1/m],
    and the effective neighbour count (list length + phi * lattice count). overflow_out[0]
    receives the largest count that did not fit."""
    i = wp.tid()
    nbc = dp.boundary_count
    self_index = nbc + i
    xi = x_all[self_index]
    count, rho, grad_sum, grad2, rho_boundary = list_neighbors(grid, p, x_all, self_index, xi, nbc, 1, nb_out,
                                                               i * nb_out.stride_i)
    count = close_neighbor_list(nb_out, i, count, overflow_out)
    bd = boundary_density(b, xi, p.h)
    gb = wp.vec3(bd[0], bd[1], bd[2])
    g = grad_sum + gb
    beta = wp.dot(g, g) + grad2
    beta_inv = float(0.0)
    if beta > dp.beta_eps:
        beta_inv = 1.0 / beta
    density_out[i] = rho + p.rest_density * bd[3]
    beta_inv_out[i] = beta_inv
    boundary_share_out[i] = rho_boundary / p.rest_density + bd[3]
    boundary_grad_out[i] = gb
    neighbors_out[i] = float(count) + bd[3] * dp.lattice_count


@wp.kernel
def apply_nonpressure(
    p: FluidParams,
    dp: DfsphParams,
    x_all: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    density: wp.array(dtype=float),
    boundary_share: wp.array(dtype=float),
    nb: NeighborList,
    dt: float,
    v_out: wp.array(dtype=wp.vec3),
):
    """v* = v + dt (g + a_visc) + XSPH, then the wall friction v* *= exp(-k phi dt).
    a_visc = 2 (d + 2) sum_j nu (2 m / (rho_i + rho_j)) (v_ij . x_ij) / (|x_ij|^2 + 0.01 h^2) grad W_ij
    (Monaghan's SPH viscosity with symmetric weights, so momentum is conserved; against boundary
    particles at rest with nu_boundary: a no-slip wall, against those with no_slip_start <= j <
    no_slip_end only, the others free slip); XSPH c sum_j 2 m W_ij / (rho_i + rho_j) (v_j - v_i)."""
    i = wp.tid()
    nbc = dp.boundary_count
    xi = x_all[nbc + i]
    vi = v[i]
    rhoi = density[i]
    dv = wp.vec3(0.0)
    acc = wp.vec3(0.0)
    e = i * nb.stride_i
    end = e + nb.count[i] * nb.stride_k
    while e < end:
        j = nb.index[e]
        e += nb.stride_k
        rij = xi - x_all[j]
        r2 = wp.dot(rij, rij)
        wf = pair_terms(p, r2)
        if j >= nbc:
            jf = j - nbc
            vij = vi - v[jf]
            rhoj = density[jf]
            dv -= (2.0 * wf[0] / (rhoi + rhoj)) * vij
            s = dp.kinematic_viscosity * 2.0 * p.rest_density / (rhoi + rhoj) * wp.dot(vij, rij) / (r2 + dp.viscosity_eps)
            acc += (dp.dimension_factor * s * wf[1]) * rij
        elif j >= dp.no_slip_start and j < dp.no_slip_end:
            s = dp.boundary_viscosity * wp.dot(vi - boundary_velocity(dp, j), rij) / (r2 + dp.viscosity_eps)
            acc += (dp.dimension_factor * s * wf[1]) * rij
    vnew = vi + p.viscosity * dv + dt * (p.gravity + acc)
    if p.wall_friction > 0.0:
        vnew = vnew * wp.exp(-p.wall_friction * boundary_share[i] * dt)
    v_out[i] = vnew


@wp.kernel
def predict_error(
    p: FluidParams,
    dp: DfsphParams,
    x_all: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    density: wp.array(dtype=float),
    beta_inv: wp.array(dtype=float),
    boundary_grad: wp.array(dtype=wp.vec3),
    neighbors: wp.array(dtype=float),
    nb: NeighborList,
    dt: float,
    divergence: int,
    kappa_out: wp.array(dtype=float),
    error_out: wp.array(dtype=float),
):
    """The density error the velocities v would leave after dt and the pressure that removes it.
    Rate D_i = sum_fluid V (v_i - v_j) . grad W_ij + sum_boundary V v_i . grad W_ib + v_i . grad phi_i
    [1/s]; density solve (divergence 0): e_i = max(rho_hat_i - 1 + dt D_i, 0); divergence solve:
    e_i = max(dt D_i, 0), 0 for a particle with fewer than min_neighbors (a free surface).
    kappa_i = e_i / (dt^2 beta_i) [m^2/s^2]; error_out[i] = e_i (relative)."""
    i = wp.tid()
    nbc = dp.boundary_count
    xi = x_all[nbc + i]
    vi = v[i]
    rate = wp.dot(vi, boundary_grad[i])
    e = i * nb.stride_i
    end = e + nb.count[i] * nb.stride_k
    while e < end:
        j = nb.index[e]
        rij = xi - x_all[j]
        f = neighbor_gradient(p, nb, e, wp.dot(rij, rij))
        vij = vi - boundary_velocity(dp, j)
        if j >= nbc:
            vij = vi - v[j - nbc]
        rate += f * wp.dot(vij, rij)
        e += nb.stride_k
    err = float(0.0)
    if divergence != 0:
        if neighbors[i] >= dp.min_neighbors:
            err = wp.max(dt * rate, 0.0)
    else:
        err = wp.max(density[i] / p.rest_density - 1.0 + dt * rate, 0.0)
    kappa_out[i] = err * beta_inv[i] / (dt * dt)
    error_out[i] = err


@wp.kernel
def apply_pressure(
    p: FluidParams,
    dp: DfsphParams,
    x_all: wp.array(dtype=wp.vec3),
    kappa: wp.array(dtype=float),
    boundary_grad: wp.array(dtype=wp.vec3),
    nb: NeighborList,
    dt: float,
    v_io: wp.array(dtype=wp.vec3),
    kappa_sum_io: wp.array(dtype=float),
):
    """v_i -= dt (sum_fluid V (kappa_i + kappa_j) grad W_ij + kappa_i (sum_boundary V grad W_ib +
    grad phi_i)): the pressure acceleration (pairwise antisymmetric between fluid particles, so
    momentum is conserved); kappa_sum_io accumulates kappa_i over the step (the pressure)."""
    i = wp.tid()
    nbc = dp.boundary_count
    xi = x_all[nbc + i]
    ki = kappa[i]
    acc = ki * boundary_grad[i]
    e = i * nb.stride_i
    end = e + nb.count[i] * nb.stride_k
    while e < end:
        j = nb.index[e]
        rij = xi - x_all[j]
        f = neighbor_gradient(p, nb, e, wp.dot(rij, rij))
        kj = float(0.0)
        if j >= nbc:
            kj = kappa[j - nbc]
        acc += ((ki + kj) * f) * rij
        e += nb.stride_k
    v_io[i] = v_io[i] - dt * acc
    kappa_sum_io[i] = kappa_sum_io[i] + ki


@wp.kernel
def advance_positions(
    p: FluidParams,
    b: Boundaries,
    dt: float,
    min_distance: float,
    v_io: wp.array(dtype=wp.vec3),
    x_io: wp.array(dtype=wp.vec3),
):
    """x += dt v; a particle closer than ``min_distance`` to a plane is put back there and loses
    its velocity into the plane (a safety net: the boundary pressure keeps particles away)."""
    i = wp.tid()
    vi = v_io[i]
    y = x_io[i] + dt * vi
    for k in range(b.plane_offsets.shape[0]):
        n = b.plane_normals[k]
        d = wp.dot(n, y) - b.plane_offsets[k]
        if d < min_distance:
            y = y + (min_distance - d) * n
            vn = wp.dot(vi, n)
            if vn < 0.0:
                vi = vi - vn * n
    v_io[i] = vi
    x_io[i] = y


@wp.kernel
def move_boundary(
    start_points: wp.array(dtype=wp.vec3),
    velocity: wp.vec3,
    t: float,
    first: int,
    x_all_out: wp.array(dtype=wp.vec3),
):
    """Moving boundary particle k (a gate) at time t [s]: x_all[first + k] = start_points[k] + t velocity."""
    k = wp.tid()
    x_all_out[first + k] = start_points[k] + t * velocity


@wp.kernel
def store_pressure(
    p: FluidParams,
    density: wp.array(dtype=float),
    kappa_sum: wp.array(dtype=float),
    pressure_out: wp.array(dtype=float),
):
    """p_i = rho_i^2 / rho0 * sum(kappa_i) over the step's solves [Pa]."""
    i = wp.tid()
    rho = density[i]
    pressure_out[i] = rho * rho / p.rest_density * kappa_sum[i]
