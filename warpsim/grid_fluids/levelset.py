"""Level sets on a MacGrid: a signed distance phi at cell centres (phi < 0 inside the liquid),
advected by the grid velocity, re-distanced, and optionally corrected by marker particles
(the particle level set of Enright et al. 2002)."""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from ..core import checks
from .advection import Advector
from ..core.reduction import FixedOrderReduction
from .particles import GridParticles
from ..kernels import advect as KA
from ..kernels import levelset as K
from .mac_grid import check_positive


class LevelSet:
    """A signed distance field with re-distancing and a particle level set.

    Args:
        grid: the MacGrid.
        phi0: initial signed distance [m]: an array of shape (nx, ny, nz) (2D: (nx, ny) or (nx, ny, 1)),
            or a function of cell-centre positions (..., 3) -> (...). Re-distanced on entry.
        scheme: advection scheme for phi (see Advector).
        band: half width of the narrow band [cells]: particles live within it and re-distancing
            caps |phi| at ``band + 2`` cells.
        particle_level_set: track the interface with marker particles too.
        particles_per_cell: particles seeded per band cell (half each side).
        reseed_every: reseed (cull crowded cells, top up sparse band cells) every this many ``advect``
            calls (0: never).
        capacity: particle capacity (default: enough for a band of cells_in_band x per_cell, estimated
            from the initial surface and doubled).
        seed: random seed for particle placement.
        redistance_iterations: eikonal sweeps per re-distancing (default band + 3).

    Attributes: ``phi`` (wp.array3d, [m]); particle arrays ``particle_q`` (vec3, [m]), ``particle_radius``
    ([m]), ``particle_sign`` (+1 outside, -1 inside, 0 deleted), ``particle_count`` (device int[1]).
    """

    def __init__(self, grid, phi0, scheme="maccormack", band=3.0, particle_level_set=True, particles_per_cell=16,
                 reseed_every=20, capacity=None, seed=1, redistance_iterations=None, advector=None):
        self.grid, self.device = grid, grid.device
        self.band = check_positive(band, "level set band [cells]")
        self.dx = grid.dx
        self.max_dist = (self.band + 2.0) * grid.dx
        if redistance_iterations is None:
            redistance_iterations = math.ceil(self.band) + 3
        if int(redistance_iterations) != redistance_iterations or redistance_iterations < 1:
            raise ValueError(f"redistance_iterations must be a positive integer, got {redistance_iterations!r}")
        self.redistance_iterations = int(redistance_iterations)
        if int(particles_per_cell) != particles_per_cell or particles_per_cell < 2:
            raise ValueError(f"particles_per_cell must be an integer >= 2, got {particles_per_cell!r}")
        self.particles_per_cell = int(particles_per_cell)
        if int(reseed_every) != reseed_every or reseed_every < 0:
            raise ValueError(f"reseed_every must be an integer >= 0, got {reseed_every!r}")
        self.reseed_every = int(reseed_every)
        self.use_particles = checks.flag(particle_level_set, "LevelSet particle_level_set")
        self.max_escape = grid.dx  # escaped markers deeper than one cell are not used, then deleted
        self.seed = int(seed)
        self.advector = advector if advector is not None else Advector(grid, scheme)
        d, shape = self.device, grid.shape
        values = phi0(grid.positions("center")) if callable(phi0) else phi0
        values = np.asarray(values, dtype=np.float64)
        if values.size != grid.cell_count:
            raise ValueError(f"phi0 has {values.size} values; the grid has {grid.cell_count} cells {shape}")
        values = values.reshape(shape)
        if not np.all(np.isfinite(values)):
            raise ValueError("phi0 must be finite at every cell centre")
        self.phi = wp.array(values.astype(np.float32), dtype=float, device=d)
        self._phi_tmp = wp.zeros(shape, dtype=float, device=d)
        self._phi_minus = wp.zeros(shape, dtype=float, device=d)
        self._fixed = wp.zeros(shape, dtype=int, device=d)
        self._volume = FixedOrderReduction(1, device=d)  # the liquid volume, summed in a fixed order
        self.r_min, self.r_max = 0.1 * grid.dx, 0.5 * grid.dx
        self.redistance()
        if capacity is None:
            near = int(np.count_nonzero(np.abs(self.phi.numpy()) < self.band * grid.dx))
            capacity = max(1024, 2 * near * self.particles_per_cell)
        if int(capacity) != capacity or capacity < 1:
            raise ValueError(f"particle capacity must be a positive integer, got {capacity!r}")
        self.particles = GridParticles(int(capacity) if self.use_particles else 1, ["x"], ["radius", "sign"],
                                       alive="sign", device=d)
        self.capacity = self.particles.capacity
        self.particle_q = self.particles["x"]
        self.particle_radius = self.particles["radius"]
        self.particle_sign = self.particles["sign"]
        self.particle_count = self.particles.count
        self._cell_count = wp.zeros(shape, dtype=int, device=d)
        self._steps = 0
        if self.use_particles:
            self.reseed()

    # ------------------------------------------------------------------ re-distancing
    def redistance(self, iterations=None) -> None:
        """Make phi a signed distance (|grad phi| = 1) without moving its zero level set."""
        g, d = self.grid, self.device
        n = self.redistance_iterations if iterations is None else int(iterations)
        wp.launch(K.redistance_init, g.shape, inputs=[self.phi, g.dx, self.max_dist],
                  outputs=[self._phi_tmp, self._fixed], device=d)
        src, dst = self._phi_tmp, self.phi
        for _ in range(n):
            wp.launch(K.redistance_sweep, g.shape, inputs=[src, self._fixed, g.dx], outputs=[dst], device=d)
            src, dst = dst, src
        if src is not self.phi:
            wp.copy(self.phi, src)

    # ------------------------------------------------------------------ particles
    def reseed(self) -> None:
        """Keep the band populated (Enright et al. 2002): cells holding more than 2 x particles_per_cell
        lose the excess, band cells holding fewer than particles_per_cell are topped up, and deleted
        entries are compacted away."""
        g, P = self.grid, self.particles
        P.count_cells(g, self._cell_count)
        P.cull(2 * self.particles_per_cell)
        P.compact()
        # append in cell order (count, prefix sum, write): the same slots on every run and device
        emitted, offsets = P.begin_append(g.cell_count)
        inputs = [self.phi, g.wp_origin, g.dx, g.dim, self.band * g.dx, self.particles_per_cell,
                  self.seed + 7919 * self._steps, self.r_min, self.r_max, self._cell_count, P.count]
        for write in (0, 1):
            wp.launch(K.pls_seed, g.shape, inputs=[*inputs, write, emitted, offsets],
                      outputs=[self.particle_q, self.particle_radius, self.particle_sign], device=self.device)
            if write == 0:
                P.scan_append()
        P.finish_append()

    def correct(self) -> None:
        """Rebuild phi near escaped particles (phi+ / phi- merge of Enright et al. 2002)."""
        g, d = self.grid, self.device
        wp.copy(self._phi_tmp, self.phi)
        wp.copy(self._phi_minus, self.phi)
        wp.launch(K.pls_scatter_escaped, self.capacity,
                  inputs=[self.phi, g.wp_origin, g.dx, self.particle_count, self.particle_q, self.particle_radius,
                          self.particle_sign, self.max_escape], outputs=[self._phi_tmp, self._phi_minus], device=d)
        wp.launch(K.pls_merge, g.shape, inputs=[self._phi_tmp, self._phi_minus], outputs=[self.phi], device=d)

    def adjust_radii(self) -> None:
        g = self.grid
        wp.launch(K.pls_adjust_radii, self.capacity,
                  inputs=[self.phi, g.wp_origin, g.dx, self.r_min, self.r_max, 1.5 * self.band * g.dx,
                          self.max_escape, self.particle_count],
                  outputs=[self.particle_q, self.particle_radius, self.particle_sign], device=self.device)

    # ------------------------------------------------------------------ stepping
    def advect(self, dt) -> None:
        """Carry phi (and the particles) through the grid velocity over ``dt`` [s], then correct with
        the particles, re-distance, correct again, adjust radii and reseed when due."""
        g, d = self.grid, self.device
        dt = check_positive(dt, "dt")
        self.advector.advect(self.phi, self._phi_tmp, dt, "center")
        wp.copy(self.phi, self._phi_tmp)
        if self.use_particles:
            wp.launch(KA.advect_particles_rk2, self.capacity,
                      inputs=[*g.faces, g.wp_origin, g.dx, dt, wp.vec3(*g.lower), wp.vec3(*g.upper),
                              self.particle_count], outputs=[self.particle_q], device=d)
            self.correct()
        self.redistance()
        if self.use_particles:
            self.correct()
            self.adjust_radii()
        self._steps += 1
        if self.use_particles and self.reseed_every and self._steps % self.reseed_every == 0:
            self.reseed()

    def checkpoint(self) -> dict:
        """phi, the marker particles and the step counter (host copies)."""
        return {"phi": self.phi.numpy(), "levelset_steps": self._steps, **self.particles.checkpoint("marker_")}

    def restore(self, data) -> None:
        """Inverse of :meth:`checkpoint`."""
        self.phi.assign(np.asarray(data["phi"]))
        self._steps = int(data["levelset_steps"])
        self.particles.restore(data, "marker_")

    def volume(self) -> float:
        """Liquid volume [m^3] (2D: area [m^2] = volume / dx), smoothed-Heaviside estimate over non-solid cells."""
        g = self.grid
        wp.launch(K.liquid_volume, self._volume.slots, inputs=[self.phi, g.solid_phi, 1.5 * g.dx, g.dx ** 3],
                  outputs=[self._volume.partials], device=self.device)
        v = float(self._volume.finish().numpy()[0])
        return v / g.dx if g.dim == 2 else v

    def live_particle_count(self) -> int:
        """Marker particles alive (host read-back)."""
        return self.particles.live_count()
