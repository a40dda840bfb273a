"""Divergence-free SPH (Bender and Koschier 2015, "Divergence-Free Smoothed Particle
Hydrodynamics"), the second method of :class:`warpsim.particle_fluids.pbf.ParticleFluid`
(``method="dfsph"``); drives ``warpsim.kernels.dfsph``.

A step of ``dt`` (Algorithm 1 of the paper, in the order SPlisHSPlasH runs it):

1. neighbours of every fluid particle among the fluid and the boundary particles (one
   ``wp.HashGrid`` holds both), fused with the densities and the DFSPH factors;
2. the divergence solve: Jacobi iterations of a pressure that makes the velocity field
   divergence-free (mean relative density change per step below ``divergence_tolerance``);
3. non-pressure accelerations: gravity, SPH viscosity (fluid-fluid and against the walls' particles),
   XSPH, wall friction;
4. the density solve: Jacobi iterations of a pressure that brings the predicted density back to
   rest (mean compression below ``density_tolerance``, at least two iterations);
5. x += dt v (planes as a safety net, then the colliders' shapes).

Boundaries: the domain box is a shell of static boundary particles continuing the fluid's lattice
(``boundary="particles"``, :func:`boundary_lattice`), so a resting lattice at a wall has exactly
the rest density; the colliders (and, with ``boundary="volume"``, the domain walls too) act
through their signed distance: the kernel integral over the solid, the volume-map idea (Bender et
al. 2019), with the tables ParticleFluid builds.

Every sum is a gather in the neighbour list's fixed order and both solve loops are decided on the
device (``wp.capture_while``): a step allocates nothing, reads nothing back inside a CUDA graph and
gives the same bits every run.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from ..core.reduction import FixedOrderReduction
from ..kernels import dfsph as D
from ..kernels import sph as K

BOUNDARIES = ("particles", "volume")
NO_SLIP = ("all", "floor")
"""Which walls ``boundary_viscosity`` makes no-slip: every boundary particle, or the floor's only."""


def floor_mask(points, lower, upper, gravity) -> np.ndarray:
    """Boolean mask of the boundary particles (M, 3) [m] behind the floor: the box's wall that
    ``gravity`` (3,) [m/s^2] points at (along its largest component), its edges and corners
    included (every particle beyond that wall's plane). ValueError for zero gravity."""
    g = np.asarray(gravity, np.float64).reshape(3)
    k = int(np.argmax(np.abs(g)))
    if g[k] == 0.0:
        raise ValueError("no_slip='floor' needs gravity to say where the floor is; gravity is zero")
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    return pts[:, k] < float(lower[k]) if g[k] < 0.0 else pts[:, k] > float(upper[k])


def boundary_lattice(lower, upper, spacing: float, layers: int) -> np.ndarray:
    """Boundary particle centres (M, 3) [m]: the shell of ``layers`` lattice layers outside the box
    [lower, upper] (edges and corners filled), continuing a fluid lattice whose particles sit half a
    spacing inside the walls. Along each axis the inner nodes spread evenly over the box (spacing
    adjusted to fit a whole number), the outer ones at (k + 1/2) spacing beyond each wall."""
    axes, inside = [], []
    for lo, hi in zip(np.asarray(lower, float), np.asarray(upper, float)):
        cells = max(1, int(round((hi - lo) / spacing)))
        step = (hi - lo) / cells
        inner = lo + (np.arange(cells) + 0.5) * step
        outer = (np.arange(layers) + 0.5) * spacing
        axes.append(np.concatenate([lo - outer[::-1], inner, hi + outer]))
        inside.append((layers, layers + cells))
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    idx = np.stack(np.meshgrid(*[np.arange(len(a)) for a in axes], indexing="ij"), axis=-1).reshape(-1, 3)
    interior = np.all([(idx[:, k] >= inside[k][0]) & (idx[:, k] < inside[k][1]) for k in range(3)], axis=0)
    return grid[~interior]


class DfsphSolver:
    """The DFSPH step on a ParticleFluid's buffers (built by ParticleFluid for ``method="dfsph"``).

    Args:
        positions, velocities: the fluid's capacity-sized wp.vec3 buffers [m], [m/s] (updated in place).
        density_out, pressure_out: capacity-sized float buffers [kg/m^3], [Pa] written each step.
        params: the fluid's ``K.FluidParams`` (kernel, mass, gravity, XSPH, wall friction).
        boundaries: the fluid's ``K.Boundaries`` (every plane, shape and mesh).
        domain: (lower, upper) or None; spacing, support: [m] and support in spacings.
        boundary: "particles" (the domain walls as boundary particles) or "volume" (signed distance).
        kinematic_viscosity, boundary_viscosity: [m^2/s] of the SPH viscosity (fluid, walls).
        no_slip: "all" (boundary_viscosity against every boundary particle) or "floor" (against the
            floor's only, :func:`floor_mask`, whose particles then come first; the side walls and a
            slab's front and back walls stay free slip). Needs boundary particles.
        density_tolerance, divergence_tolerance: mean relative errors the two solves stop at.
        iterations: most iterations of each solve; total_counter: the fluid's int buffer of all iterations.
        grid_dims: hash grid cells per axis; max_neighbors: list capacity; device: Warp device.
        moving_boundary: None or (points (M, 3) [m] at t = 0, velocity (3,) [m/s]): boundary
            particles moving at a constant velocity (a gate lifted off a column), at
            points + t velocity at the start of each step.
    """

    def __init__(self, *, positions, velocities, density_out, pressure_out, params, boundaries, domain, spacing,
                 support, boundary, kinematic_viscosity, boundary_viscosity, density_tolerance,
                 divergence_tolerance, iterations, total_counter, grid_dims, max_neighbors, device,
                 moving_boundary=None, no_slip="all"):
        if boundary not in BOUNDARIES:
            raise ValueError(f"boundary={boundary!r} is unknown; use one of {list(BOUNDARIES)}")
        if no_slip not in NO_SLIP:
            raise ValueError(f"no_slip={no_slip!r} is unknown; use one of {list(NO_SLIP)}")
        if boundary == "particles" and domain is None:
            boundary = "volume"  # no box to sample: the colliders act through their signed distance
        d = self.device = wp.get_device(device)
        self.boundary = boundary
        self._x, self._v = positions, velocities
        self._density, self._pressure = density_out, pressure_out
        self._p, self._all = params, boundaries
        self.density_tolerance, self.divergence_tolerance = float(density_tolerance), float(divergence_tolerance)
        self.iterations = int(iterations)
        self._total = total_counter
        layers = int(np.ceil(support)) if boundary == "particles" else 0
        pts = boundary_lattice(domain[0], domain[1], spacing, layers) if layers else np.zeros((0, 3))
        no_slip_end = len(pts)
        if no_slip == "floor":
            if not layers:
                raise ValueError("no_slip='floor' needs boundary='particles' and a domain box (the floor's "
                                 "particles)")
            floor = floor_mask(pts, domain[0], domain[1], [params.gravity[k] for k in range(3)])
            pts = np.concatenate([pts[floor], pts[~floor]])  # the floor's first: no slip on 0 .. floor count
            no_slip_end = int(np.count_nonzero(floor))
        self.no_slip = no_slip
        """Which walls boundary_viscosity makes no-slip ("all" or "floor")."""
        moving_start = len(pts)
        self._moving = None
        if moving_boundary is not None:
            if boundary != "particles":
                raise ValueError("moving_boundary needs boundary='particles' and a domain box")
            mpts, mvel = moving_boundary
            mpts = np.asarray(mpts, np.float64).reshape(-1, 3)
            if len(mpts) == 0 or not np.all(np.isfinite(mpts)):
                raise ValueError(f"moving_boundary points must be a non-empty finite (M, 3) array, got shape {mpts.shape}")
            mvel = np.asarray(mvel, np.float64).reshape(3)
            self._moving = (wp.array(mpts.astype(np.float32), dtype=wp.vec3, device=d), wp.vec3(*mvel), len(mpts))
            pts = np.concatenate([pts, mpts])
        self.boundary_points = pts.astype(np.float32)
        """Boundary particle centres at t = 0, (M, 3) [m] (empty with boundary="volume")."""
        nbc = len(pts)
        cap = positions.shape[0]
        self._x_all = wp.zeros(nbc + cap, dtype=wp.vec3, device=d)
        if nbc:
            wp.copy(self._x_all, wp.array(self.boundary_points, dtype=wp.vec3, device=d), count=nbc)
        self._sdf = self._density_boundaries(boundaries, domain is not None and boundary == "particles")
        dp = D.DfsphParams()
        dp.boundary_count = nbc
        dp.kinematic_viscosity = float(kinematic_viscosity)
        dp.boundary_viscosity = float(boundary_viscosity)
        dp.no_slip_start = 0
        dp.no_slip_end = nbc if no_slip == "all" else no_slip_end  # "all": a gate's particles too
        h = support * spacing
        dp.viscosity_eps = 0.01 * h * h
        dp.dimension_factor = 10.0
        offsets = np.arange(-int(np.ceil(support)), int(np.ceil(support)) + 1)
        lattice = np.stack(np.meshgrid(offsets, offsets, offsets, indexing="ij"), -1).reshape(-1, 3)
        r = np.linalg.norm(lattice, axis=1)
        dp.lattice_count = float(np.count_nonzero((r > 0) & (r < support)))
        # SPlisHSPlasH's 20 in 3D, where a particle inside the lattice has 26 neighbours at support 2
        dp.min_neighbors = 20.0 / 26.0 * dp.lattice_count
        dp.beta_eps = 1.0e-9 / (h * h)
        dp.moving_start = moving_start
        dp.boundary_velocity = self._moving[1] if self._moving else wp.vec3(0.0, 0.0, 0.0)
        self._dp = dp
        # the fluid's own projection keeps a particle half a spacing from a wall; the pressure keeps it
        # there, so the safety net here acts only at a quarter spacing
        self._min_distance = 0.25 * spacing
        self._v_star = wp.zeros(cap, dtype=wp.vec3, device=d)
        self._kappa = wp.zeros(cap, dtype=float, device=d)
        self._kappa_sum = wp.zeros(cap, dtype=float, device=d)
        self._error = wp.zeros(cap, dtype=float, device=d)
        self._beta_inv = wp.zeros(cap, dtype=float, device=d)
        self._share = wp.zeros(cap, dtype=float, device=d)
        self._bgrad = wp.zeros(cap, dtype=wp.vec3, device=d)
        self._neighbors = wp.zeros(cap, dtype=float, device=d)
        nb = K.NeighborList()
        nb.capacity = int(max_neighbors)
        nb.count = wp.zeros(cap, dtype=int, device=d)
        nb.index = wp.zeros(cap * nb.capacity, dtype=int, device=d)
        nb.cache_gradients = int(d.is_cpu)  # as PBF: cache on the CPU, re-evaluate on GPUs
        nb.grad_factor = wp.zeros(cap * nb.capacity if nb.cache_gradients else 1, dtype=float, device=d)
        nb.stride_i, nb.stride_k = nb.capacity, 1
        self._nb = nb
        self._overflow = wp.zeros(1, dtype=int, device=d)
        self._reduction = FixedOrderReduction(2, first_max_column=1, device=d)
        self._div_counter = wp.zeros(1, dtype=int, device=d)  # iterations of the last divergence solve
        self._density_counter = wp.zeros(1, dtype=int, device=d)  # ... and of the last density solve
        self._go = wp.zeros(1, dtype=int, device=d)
        self._grid = wp.HashGrid(*grid_dims, device=d)
        self._has_shapes = bool(boundaries.capsule_radii.shape[0] or boundaries.mesh_ids.shape[0])

    @property
    def boundary_count(self) -> int:
        return self._dp.boundary_count

    @property
    def no_slip_count(self) -> int:
        """Boundary particles that boundary_viscosity acts against (the first ones)."""
        return self._dp.no_slip_end - self._dp.no_slip_start

    def _density_boundaries(self, b, skip_domain: bool):
        """The signed-distance boundaries that add to the density: all of the fluid's, without the
        six domain planes (first in its list) when boundary particles stand in for them."""
        if not skip_domain:
            return b
        s = K.Boundaries()
        for name in ("capsule_a", "capsule_b", "capsule_radii", "capsule_signs", "mesh_ids", "mesh_thickness",
                     "mesh_solid", "phi_table", "dphi_table"):
            setattr(s, name, getattr(b, name))
        if b.plane_offsets.shape[0] > 6:
            s.plane_normals, s.plane_offsets = b.plane_normals[6:], b.plane_offsets[6:]
        else:
            s.plane_normals = wp.zeros(0, dtype=wp.vec3, device=self.device)
            s.plane_offsets = wp.zeros(0, dtype=float, device=self.device)
        return s

    def overflow(self) -> int:
        """Largest neighbour count that did not fit since the last call (a read-back; then reset)."""
        over = int(self._overflow.numpy()[0])
        if over:
            self._overflow.zero_()
        return over

    def solve(self, n: int, dt: float, t: float = 0.0) -> None:
        """One DFSPH step of the first n fluid particles from time t [s] (allocates nothing)."""
        d, p, dp, nb = self.device, self._p, self._dp, self._nb
        nbc = dp.boundary_count
        x, v = self._x[:n], self._v[:n]
        wp.copy(self._x_all, self._x, dest_offset=nbc, count=n)
        if self._moving is not None:
            start_points, velocity, count = self._moving
            wp.launch(D.move_boundary, count, inputs=[start_points, velocity, t, dp.moving_start],
                      outputs=[self._x_all], device=d)
        self._grid.build(self._x_all[: nbc + n], p.h)
        wp.launch(D.find_neighbors_factor, n, inputs=[self._grid.id, p, dp, self._sdf, self._x_all],
                  outputs=[nb, self._overflow, self._density, self._beta_inv, self._share, self._bgrad, self._neighbors],
                  device=d)
        self._kappa_sum.zero_()
        self._pressure_solve(n, dt, v, divergence=1, tolerance=self.divergence_tolerance, min_iterations=1,
                             counter=self._div_counter)
        wp.launch(D.apply_nonpressure, n, inputs=[p, dp, self._x_all, v, self._density, self._share, nb, dt],
                  outputs=[self._v_star], device=d)
        v_star = self._v_star[:n]
        self._pressure_solve(n, dt, v_star, divergence=0, tolerance=self.density_tolerance, min_iterations=2,
                             counter=self._density_counter)
        wp.copy(v, v_star, count=n)
        wp.launch(D.advance_positions, n, inputs=[p, self._all, dt, self._min_distance], outputs=[v, x], device=d)
        if self._has_shapes:
            wp.launch(K.project_boundaries, n, inputs=[p, self._all, x], device=d)
        wp.launch(D.store_pressure, n, inputs=[p, self._density, self._kappa_sum], outputs=[self._pressure], device=d)

    @property
    def last_iterations(self) -> int:
        """Iterations of the last step's divergence and density solves together (two read-backs)."""
        return int(self._div_counter.numpy()[0]) + int(self._density_counter.numpy()[0])

    def _pressure_solve(self, n, dt, vel, divergence, tolerance, min_iterations, counter):
        """Jacobi iterations on ``vel`` until the mean error is below ``tolerance`` (decided on the device)."""
        d, p, dp, nb = self.device, self._p, self._dp, self._nb
        predict = [p, dp, self._x_all, vel, self._density, self._beta_inv, self._bgrad, self._neighbors, nb, dt,
                   divergence]
        # the loop control PBF uses (kernels/sph.py), without its peak condition
        control = [self._reduction.result, n, tolerance, 3.0e38, min_iterations, self.iterations]
        counters = [counter, self._total, self._go]
        counter.zero_()
        wp.launch(D.predict_error, n, inputs=predict, outputs=[self._kappa, self._error], device=d)
        self._reduction.sum_max(self._error, n)
        wp.launch(K.iteration_control, 1, inputs=[*control, 0], outputs=counters, device=d)

        def body():
            wp.launch(D.apply_pressure, n, inputs=[p, dp, self._x_all, self._kappa, self._bgrad, nb, dt],
                      outputs=[vel, self._kappa_sum], device=d)
            wp.launch(D.predict_error, n, inputs=predict, outputs=[self._kappa, self._error], device=d)
            self._reduction.sum_max(self._error, n)
            wp.launch(K.iteration_control, 1, inputs=[*control, 1], outputs=counters, device=d)

        wp.capture_while(self._go, body)
