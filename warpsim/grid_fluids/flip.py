"""FLIP/PIC liquid (Zhu and Bridson 2005): particles carry the velocity, a MAC grid does the
pressure projection each step, and a FLIP/PIC blend transfers the grid's change back. A second,
position-only projection (implicit density projection, Kugelstadt et al., IEEE TVCG 2021) keeps the
particles at their rest density, so the liquid keeps its volume."""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from ..core.solver import SolverBase
from .particles import GridParticles
from .pressure import PressureSolver
from ..kernels import advect as KA
from ..kernels import flip as K
from ..kernels import grid_forces as KF
from .levelset_liquid import gravity_vector
from .mac_grid import MacGrid, check_finite, check_positive


class FlipLiquid(SolverBase):
    """A FLIP liquid on a MacGrid (a ``warpsim.core.solver.Solver``).

    Args:
        grid: the MacGrid (walls and solids hold the liquid).
        gravity: acceleration [m/s^2], 2 or 3 numbers.
        flip_ratio: r in [0, 1]: v_p = r (v_p + du) + (1 - r) u (1 = pure FLIP, 0 = pure PIC).
        particles_per_cell: particles seeded per cell (default 4 in 2D, 8 in 3D).
        min_per_cell, max_per_cell: reseeding bounds (default ppc/2 and 2 ppc): interior fluid cells
            are topped up to min_per_cell, cells above max_per_cell lose the excess.
        reseed_every: reseed every this many steps (0: never; the particle count then never changes).
        capacity: particle capacity (default 2 x the particles seeded by the first ``add_*`` call, at
            least 1024; pass it when adding liquid in several calls).
        tol, preconditioner: pressure solver settings.
        density_correction: strength in [0, 1] of the per-step volume correction (0: off). After the
            particles move, their density on the grid (hat-weighted particles per cell, rest value
            ``particles_per_cell``) sets a divergence target s = strength (rho / rest - 1) (only
            s > 0 within one cell of air); a second Poisson solve finds the curl-free displacement
            field with that divergence (zero on walls, zero pressure in air) and the particles move
            along it. Positions only: velocities are untouched (implicit density projection,
            Kugelstadt et al., IEEE TVCG 2021). It undoes the slow compaction of FLIP particles that otherwise
            shrinks the liquid, and keeps their spacing even, so reseeding adds few particles.
        density_tol: relative CG tolerance of the correction solve.
        max_density_target: cap on s per step (limits the displacement after a violent impact).
        deterministic: True (default): particle-to-grid sums are gathers over the cell-sorted particle
            list in a fixed order, so two runs give the same bits on every device. False: the sums
            scatter with float atomics (faster; on a GPU the summation order, and so the result's last
            bits, vary run to run). Reseeding appends particles in cell order either way.
        seed: random seed for particle placement.
        extrapolation_layers: faces filled beyond the liquid each step.

    Attributes: ``particles`` (GridParticles with fields ``x`` [m], ``v`` [m/s], ``alive``, ``id``
    (persistent, new ids for reseeded particles)),
    ``pressure`` (PressureSolver), ``phi`` (particle signed distance from ``surface()`` [m]),
    ``density`` (hat-weighted particles per cell, shape (nx, ny, nz), from the last correction or
    ``measure_density()``), ``correction`` (the displacement's PressureSolver; None when off).
    """

    def __init__(self, grid, gravity=(0.0, -9.81, 0.0), flip_ratio=0.95, particles_per_cell=None,
                 min_per_cell=None, max_per_cell=None, reseed_every=1, capacity=None, tol=1.0e-5,
                 preconditioner="mg", seed=3, extrapolation_layers=3, density_correction=1.0,
                 density_tol=1.0e-2, max_density_target=0.5, deterministic=True):
        self.grid, self.device = grid, grid.device
        if not isinstance(deterministic, bool):
            raise TypeError(f"deterministic must be True or False, got {deterministic!r}")
        self.deterministic = deterministic
        self.gravity = gravity_vector(gravity, grid.dim)
        r = check_finite(flip_ratio, "flip_ratio")
        if not 0.0 <= r <= 1.0:
            raise ValueError(f"flip_ratio must be in [0, 1] (1 = FLIP, 0 = PIC), got {flip_ratio}")
        self.flip_ratio = r
        ppc = (4 if grid.dim == 2 else 8) if particles_per_cell is None else particles_per_cell
        if int(ppc) != ppc or ppc < 1:
            raise ValueError(f"particles_per_cell must be a positive integer, got {particles_per_cell!r}")
        self.particles_per_cell = int(ppc)
        self.min_per_cell = max(1, self.particles_per_cell // 2) if min_per_cell is None else min_per_cell
        self.max_per_cell = 2 * self.particles_per_cell if max_per_cell is None else max_per_cell
        for name, v in (("min_per_cell", self.min_per_cell), ("max_per_cell", self.max_per_cell)):
            if int(v) != v or v < 1:
                raise ValueError(f"{name} must be a positive integer, got {v!r}")
        if self.min_per_cell > self.max_per_cell:
            raise ValueError(f"min_per_cell {self.min_per_cell} must not exceed max_per_cell {self.max_per_cell}")
        if int(reseed_every) != reseed_every or reseed_every < 0:
            raise ValueError(f"reseed_every must be an integer >= 0, got {reseed_every!r}")
        self.reseed_every = int(reseed_every)
        if int(extrapolation_layers) != extrapolation_layers or extrapolation_layers < 1:
            raise ValueError(f"extrapolation_layers must be an integer >= 1, got {extrapolation_layers!r}")
        self.extrapolation_layers = int(extrapolation_layers)
        self.seed = int(seed)
        self._capacity = capacity
        self.particles = None
        self.pressure = PressureSolver(grid, tol=tol, preconditioner=preconditioner)
        strength = check_finite(density_correction, "density_correction")
        if not 0.0 <= strength <= 1.0:
            raise ValueError(f"density_correction must be in [0, 1] (0 = off), got {density_correction}")
        self.density_correction = strength
        self.max_density_target = check_positive(max_density_target, "max_density_target")
        if not check_positive(density_tol, "density_tol") < 1.0:
            raise ValueError(f"density_tol must be < 1 (relative residual), got {density_tol}")
        self.density = wp.zeros(grid.shape, dtype=float, device=grid.device)
        self.correction = None
        if strength > 0.0:
            # a twin grid whose faces hold the displacement [m]; it shares the liquid's labels and solids
            twin = MacGrid(grid.shape[: grid.dim], grid.dx, grid.origin[: grid.dim], grid.open_sides, grid.device)
            twin.labels, twin.solid_phi = grid.labels, grid.solid_phi
            self._target = wp.zeros(grid.shape, dtype=float, device=grid.device)
            # a loose, single-pass solve: what it leaves is corrected in the next steps
            self.correction = PressureSolver(twin, tol=density_tol, preconditioner=preconditioner, refine=False)
        d, shape = self.device, grid.shape
        scatter = [] if deterministic else grid.faces  # sums and weights of the float-atomic P2G only
        self._sums = [wp.zeros(f.shape, dtype=float, device=d) for f in scatter]
        self._weights = [wp.zeros(f.shape, dtype=float, device=d) for f in scatter]
        self._old = [wp.zeros(f.shape, dtype=float, device=d) for f in grid.faces]
        self.cell_count = wp.zeros(shape, dtype=int, device=d)
        self.phi = wp.zeros(shape, dtype=float, device=d)
        self.next_id = wp.zeros(1, dtype=int, device=d)
        self._pending = []
        self.time, self.steps = 0.0, 0
        inset = 1.0e-3 * grid.dx
        self._lower = wp.vec3(*(l + inset for l in grid.lower))
        self._upper = wp.vec3(*(u - inset for u in grid.upper))

    # ------------------------------------------------------------------ seeding
    @property
    def state(self):
        """The MacGrid whose face velocities (``u``, ``v``, ``w``) this solver advances (the solver
        protocol's ``state``; the other fields are this object's attributes)."""
        return self.grid

    def add_box(self, lower, upper, velocity=(0.0, 0.0, 0.0)):
        """Fill the cells whose centres lie in [lower, upper] [m] with jittered particles moving at
        ``velocity`` [m/s]; cells inside solids are skipped."""
        g = self.grid
        n = len(self._pending)
        lo, hi = g.point(lower, f"liquid block {n} lower"), g.point(upper, f"liquid block {n} upper")
        centres = g.positions("center")
        inside = np.all((centres >= np.asarray(lo) - 1e-9 * g.dx) & (centres <= np.asarray(hi) + 1e-9 * g.dx), axis=-1)
        if g.dim == 2:
            inside = np.all((centres[..., :2] >= np.asarray(lo[:2])) & (centres[..., :2] <= np.asarray(hi[:2])), axis=-1)
        return self.add_cells(inside, velocity, what=f"liquid block {n}")

    def add_sdf(self, phi_fn, velocity=(0.0, 0.0, 0.0)):
        """Fill the cells whose centres satisfy ``phi_fn(points (..., 3)) < 0`` with particles."""
        values = np.asarray(phi_fn(self.grid.positions("center")))
        return self.add_cells(values < 0.0, velocity, what=f"liquid region {len(self._pending)}")

    def add_cells(self, mask, velocity=(0.0, 0.0, 0.0), what="liquid"):
        """Seed ``particles_per_cell`` jittered particles in every non-solid cell where ``mask``
        (shape (nx, ny, nz)) is True. Returns the number of particles added."""
        g = self.grid
        mask = np.asarray(mask, dtype=bool).reshape(g.shape) & (g.solid_phi.numpy() >= 0.0)
        vel = g.point(velocity, f"{what} velocity") if g.dim == 3 else [*map(float, list(velocity)[:2]), 0.0]
        if not all(math.isfinite(c) for c in vel):
            raise ValueError(f"{what} velocity must be finite, got {velocity!r}")
        cells = np.argwhere(mask)
        if len(cells) == 0:
            raise ValueError(f"{what} covers no non-solid cell centre of the grid; check its bounds")
        rng = np.random.default_rng(self.seed + len(self._pending))
        k = self.particles_per_cell
        jitter = rng.random((len(cells), k, 3))
        x = np.asarray(g.origin) + (cells[:, None, :] + jitter) * g.dx
        if g.dim == 2:
            x[..., 2] = g.origin[2] + 0.5 * g.dx
        x = x.reshape(-1, 3)
        self._pending.append((x, np.broadcast_to(np.asarray(vel), x.shape)))
        self._upload()
        return len(x)

    def _upload(self):
        x = np.concatenate([p[0] for p in self._pending])
        v = np.concatenate([p[1] for p in self._pending])
        if self.particles is None:
            cap = self._capacity if self._capacity is not None else max(1024, 2 * len(x))
            self.particles = GridParticles(cap, ["x", "v"], ["alive"], alive="alive", device=self.device,
                                           int_fields=["id"])
        P = self.particles
        if len(x) > P.capacity:
            raise ValueError(f"{len(x)} particles exceed the FLIP capacity {P.capacity}; pass a larger capacity")
        P["x"].assign(np.concatenate([x, np.zeros((P.capacity - len(x), 3))]).astype(np.float32))
        P["v"].assign(np.concatenate([v, np.zeros((P.capacity - len(v), 3))]).astype(np.float32))
        alive = np.zeros(P.capacity, dtype=np.float32)
        alive[: len(x)] = 1.0
        P["alive"].assign(alive)
        P["id"].assign(np.arange(P.capacity, dtype=np.int32))
        P.count.assign(np.array([len(x)], dtype=np.int32))
        self.next_id.assign(np.array([len(x)], dtype=np.int32))

    # ------------------------------------------------------------------ stepping
    def _transfer_to_grid(self):
        g, d, P = self.grid, self.device, self.particles
        P.count_cells(g, self.cell_count)
        if self.deterministic:
            for axis, f in enumerate(g.faces):
                wp.launch(K.gather_face_velocity, f.shape,
                          inputs=[self.cell_count, P.octant_start, P.octant_count, P.sorted_ids, P["x"], P["v"], axis,
                                  g.wp_origin, g.dx], outputs=[f], device=d)
        else:
            for s, w in zip(self._sums, self._weights):
                s.zero_()
                w.zero_()
            wp.launch(K.particles_to_grid, P.capacity,
                      inputs=[P.count, P["x"], P["v"], P["alive"], g.wp_origin, g.dx],
                      outputs=[self._sums[0], self._weights[0], self._sums[1], self._weights[1], self._sums[2],
                               self._weights[2]], device=d)
            for f, s, w in zip(g.faces, self._sums, self._weights):
                wp.launch(K.normalize_faces, f.shape, inputs=[s, w], outputs=[f], device=d)
        wp.launch(K.label_from_counts, g.shape, inputs=[self.cell_count, g.solid_phi], outputs=[g.labels], device=d)
        g.extrapolate_velocity(self.extrapolation_layers)

    def step(self, dt) -> None:
        """Advance by ``dt`` [s]: P2G, gravity, projection, G2P (FLIP/PIC blend), RK2 particle
        advection through the grid velocity, solid push-out, reseeding when due."""
        dt = check_positive(dt, "dt")
        if self.particles is None:
            raise ValueError("FlipLiquid has no particles: call add_box / add_sdf / add_cells first")
        g, d, P = self.grid, self.device, self.particles
        self._transfer_to_grid()
        for old, f in zip(self._old, g.faces):
            wp.copy(old, f)
        for axis, f in enumerate(g.faces):
            if self.gravity[axis] != 0.0:
                wp.launch(KF.add_constant, f.shape, inputs=[self.gravity[axis] * dt], outputs=[f], device=d)
        self.pressure.project()
        g.extrapolate_velocity(self.extrapolation_layers)
        wp.launch(K.grid_to_particles, P.capacity,
                  inputs=[P.count, P["x"], P["alive"], self.flip_ratio, *g.faces, *self._old, g.wp_origin, g.dx],
                  outputs=[P["v"]], device=d)
        wp.launch(KA.advect_particles_rk2, P.capacity,
                  inputs=[*g.faces, g.wp_origin, g.dx, dt, self._lower, self._upper, P.count], outputs=[P["x"]],
                  device=d)
        if g.solids:
            wp.launch(K.push_out_of_solids, P.capacity, inputs=[P.count, g.solid_phi, g.wp_origin, g.dx],
                      outputs=[P["x"]], device=d)
        if self.correction is not None:
            self.correct_density()
        self.steps += 1
        self.time += dt
        if self.reseed_every and self.steps % self.reseed_every == 0:
            self.reseed()

    def measure_density(self):
        """Relabel the cells from the particles and fill ``density`` (hat-weighted particles per cell;
        ``particles_per_cell`` in evenly filled cells). Returns it."""
        g, d, P = self.grid, self.device, self.particles
        P.count_cells(g, self.cell_count)
        wp.launch(K.label_from_counts, g.shape, inputs=[self.cell_count, g.solid_phi], outputs=[g.labels], device=d)
        return self._splat_density()

    def _splat_density(self):
        """Hat-weighted particles per cell into ``density`` (call ``count_cells`` at the current
        positions and indices first: the gather reads its cell-sorted list)."""
        g, P = self.grid, self.particles
        if self.deterministic:
            wp.launch(K.gather_particle_density, g.shape,
                      inputs=[P.octant_start, P.octant_count, P.sorted_ids, P["x"], g.wp_origin, g.dx],
                      outputs=[self.density], device=self.device)
        else:
            self.density.zero_()
            wp.launch(K.particle_density, P.capacity, inputs=[P.count, P["x"], P["alive"], g.wp_origin, g.dx],
                      outputs=[self.density], device=self.device)
        return self.density

    def correct_density(self) -> None:
        """Move the particles along the displacement field that restores the rest density (see the
        class docstring); velocities are left alone."""
        g, d, P = self.grid, self.device, self.particles
        twin = self.correction.grid
        self.measure_density()
        wp.launch(K.density_divergence_target, g.shape,
                  inputs=[self.density, g.labels, g.open_mask, float(self.particles_per_cell), self.density_correction,
                          self.max_density_target], outputs=[self._target], device=d)
        for f in twin.faces:
            f.zero_()
        self.correction.project(target=self._target)
        # the displacement [m] is a field like a velocity over a unit time: move along it (RK2 midpoint)
        wp.launch(KA.advect_particles_rk2, P.capacity,
                  inputs=[*twin.faces, g.wp_origin, g.dx, 1.0, self._lower, self._upper, P.count], outputs=[P["x"]],
                  device=d)
        if g.solids:
            wp.launch(K.push_out_of_solids, P.capacity, inputs=[P.count, g.solid_phi, g.wp_origin, g.dx],
                      outputs=[P["x"]], device=d)

    def reseed(self) -> None:
        """Cull particles beyond max_per_cell per cell, compact, and top interior fluid cells up to
        min_per_cell (new particles take the grid velocity); with the density correction on, only
        cells whose density is below min_per_cell too."""
        g, d, P = self.grid, self.device, self.particles
        P.count_cells(g, self.cell_count)
        P.cull(self.max_per_cell)
        P.compact()
        wp.launch(K.label_from_counts, g.shape, inputs=[self.cell_count, g.solid_phi], outputs=[g.labels], device=d)
        # with the density correction the interior stays evenly filled: only real holes (density below
        # min_per_cell as well as the count) are reseeded, so few particles (and little mass) are added
        min_density = 1.0e30
        if self.correction is not None:
            if self.deterministic:
                # the compaction renumbered the particles: sort them again for the density gather (the
                # counts become min(count, max_per_cell), which changes no label and no reseeding decision)
                P.count_cells(g, self.cell_count)
            self._splat_density()
            min_density = float(self.min_per_cell)
        # new particles are appended in cell order (count, prefix sum, write): the same slots and ids
        # on every run and device
        emitted, offsets = P.begin_append(g.cell_count)
        inputs = [self.cell_count, g.labels, g.open_mask, self.min_per_cell, self.density, min_density,
                  self.seed + 104729 * self.steps, g.dim, *g.faces, g.wp_origin, g.dx, P.count, self.next_id]
        for write in (0, 1):
            wp.launch(K.reseed_interior, g.shape, inputs=[*inputs, write, emitted, offsets],
                      outputs=[P["x"], P["v"], P["alive"], P["id"]], device=d)
            if write == 0:
                P.scan_append()
        P.finish_append(self.next_id)

    # ------------------------------------------------------------------ output
    def surface(self, radius=None):
        """phi = union of particle spheres of ``radius`` [m] (default 0.6 dx), capped at 3 dx, at cell
        centres; < 0 inside the liquid. Returns the array (also ``self.phi``)."""
        g, P = self.grid, self.particles
        r = 0.6 * g.dx if radius is None else check_positive(radius, "surface radius")
        self.phi.fill_(3.0 * g.dx)
        wp.launch(K.particle_sdf, P.capacity, inputs=[P.count, P["x"], P["alive"], r, g.wp_origin, g.dx],
                  outputs=[self.phi], device=self.device)
        return self.phi

    def checkpoint(self) -> dict:
        """Everything needed to continue bit for bit (host copies)."""
        return {**self.grid.checkpoint(), **self.particles.checkpoint("particle_"), "next_id": self.next_id.numpy(),
                "time": self.time, "steps": self.steps}

    def restore(self, data) -> None:
        """Inverse of :meth:`checkpoint` (same grid and settings; particles added first)."""
        if self.particles is None:
            raise ValueError("restore: add the liquid (add_box / add_sdf / add_cells) before restoring")
        self.grid.restore(data)
        self.particles.restore(data, "particle_")
        self.next_id.assign(np.asarray(data["next_id"]))
        self.time, self.steps = float(data["time"]), int(data["steps"])

    def particle_count(self) -> int:
        """Live particles (host read-back)."""
        return self.particles.live_count()
