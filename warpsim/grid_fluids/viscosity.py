"""Viscosity on a MAC grid: explicit diffusion of the face velocities with no-slip (optionally
moving, e.g. a driven lid) or free-slip domain walls."""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from ..core import checks
from ..kernels import grid_forces as KF
from .mac_grid import SIDES, check_positive


class Viscosity:
    """u += nu dt laplacian(u), explicit, in as many equal sub-steps as stability needs
    (nu dt / dx^2 <= 1 / (2 dim) per sub-step; the count comes from dt on the host).

    Args:
        grid: the MacGrid.
        nu: kinematic viscosity [m^2/s].
        no_slip: walls hold the tangential velocity at their own (else free-slip).
        wall_velocity: {side: (ux, uy, uz)} [m/s] tangential velocity of moving walls, sides
            "-x", "+x", "-y", "+y", "-z", "+z" (e.g. {"+y": (1, 0, 0)} for a driven lid).
    """

    def __init__(self, grid, nu, no_slip=True, wall_velocity=None):
        self.grid, self.device = grid, grid.device
        self.nu = check_positive(nu, "viscosity nu [m^2/s]")
        self.no_slip = checks.flag(no_slip, "Viscosity no_slip")
        walls = np.zeros((6, 3), np.float32)
        for side, vel in (wall_velocity or {}).items():
            if side not in SIDES:
                raise ValueError(f"wall_velocity side {side!r} is unknown; use some of {SIDES}")
            v = np.asarray(vel, np.float64).reshape(-1)
            if v.shape != (3,) or not np.all(np.isfinite(v)):
                raise ValueError(f"wall_velocity[{side!r}] must be 3 finite numbers [m/s], got {vel!r}")
            walls[SIDES.index(side)] = v
        self.wall_velocity = wp.array(walls, dtype=wp.vec3, device=self.device)
        self._tmp = [wp.zeros(f.shape, dtype=float, device=self.device) for f in grid.faces]

    def apply(self, dt):
        """Diffuse the face velocities over ``dt`` [s]; returns the sub-step count."""
        g = self.grid
        coef = self.nu * check_positive(dt, "dt") / g.dx ** 2
        n = max(1, math.ceil(coef * 2 * g.dim / 0.9))
        for _ in range(n):
            for axis, (f, tmp) in enumerate(zip(g.faces, self._tmp)):
                if axis == 2 and g.dim == 2:
                    continue
                wp.launch(KF.diffuse_faces, f.shape, inputs=[f, axis, int(self.no_slip), self.wall_velocity, coef / n],
                          outputs=[tmp], device=self.device)
                wp.copy(f, tmp)
        g.enforce_boundaries()
        return n
