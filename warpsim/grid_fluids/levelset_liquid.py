"""A level-set liquid on a MAC grid: the surface is a (particle) level set carried by the velocity,
gravity acts on the faces, and the pressure projection uses a ghost-fluid free surface."""

from __future__ import annotations

import numpy as np
import warp as wp

from ..core.solver import SolverBase
from .advection import Advector
from .pressure import PressureSolver
from ..kernels import grid_forces as KF
from .levelset import LevelSet
from .mac_grid import check_finite, check_positive


def gravity_vector(gravity, dim):
    try:
        g = [check_finite(c, "gravity component [m/s^2]") for c in gravity]
    except TypeError as exc:
        raise ValueError(f"gravity must be {dim} or 3 numbers [m/s^2], got {gravity!r}") from exc
    if len(g) not in (dim, 3):
        raise ValueError(f"gravity must be {dim} or 3 numbers [m/s^2], got {gravity!r}")
    g = g + [0.0] * (3 - len(g))
    if dim == 2:
        g[2] = 0.0
    return tuple(g)


class LevelSetLiquid(SolverBase):
    """Free-surface liquid: phi < 0 inside (a ``warpsim.core.solver.Solver``).

    Args:
        grid: the MacGrid (its walls and solids hold the liquid).
        phi0: initial signed distance [m] (array or function of cell centres, see LevelSet).
        gravity: acceleration [m/s^2], 2 or 3 numbers.
        scheme: advection scheme for the velocity (and for phi without particles).
        particle_level_set: correct phi with marker particles (keeps volume and thin features).
        levelset_scheme: advection scheme for phi; default semi-Lagrangian with particles (the markers
            carry the accuracy; the MacCormack field's sharper kinks make air markers escape into the
            liquid and carve it), else ``scheme``.
        tol: pressure CG tolerance; preconditioner: see PressureSolver.
        levelset_options: extra keyword arguments for LevelSet (band, particles_per_cell, ...).
    """

    def __init__(self, grid, phi0, gravity=(0.0, -9.81, 0.0), scheme="maccormack", particle_level_set=True,
                 levelset_scheme=None, tol=1.0e-5, preconditioner="mg", **levelset_options):
        self.grid, self.device = grid, grid.device
        self.gravity = gravity_vector(gravity, grid.dim)
        self.advector = Advector(grid, scheme)
        if levelset_scheme is None:
            levelset_scheme = "semi_lagrangian" if particle_level_set else scheme
        self.levelset = LevelSet(grid, phi0, scheme=levelset_scheme, particle_level_set=particle_level_set,
                                 **levelset_options)
        self.pressure = PressureSolver(grid, tol=tol, preconditioner=preconditioner)
        self.extrapolation_layers = int(np.ceil(self.levelset.band)) + 3
        self.time = 0.0
        self.steps = 0
        grid.label(self.levelset.phi)
        grid.extrapolate_velocity(self.extrapolation_layers)

    @property
    def phi(self):
        return self.levelset.phi

    @property
    def state(self):
        """The MacGrid whose face velocities (``u``, ``v``, ``w``) this solver advances (the solver
        protocol's ``state``; the other fields are this object's attributes)."""
        return self.grid

    def step(self, dt) -> None:
        """Advance by ``dt`` [s]: advect phi and velocity, add gravity, project with the ghost-fluid
        surface, extrapolate the velocity into the air."""
        dt = check_positive(dt, "dt")
        g = self.grid
        self.levelset.advect(dt)
        self.advector.advect_velocity(dt)
        for axis, f in enumerate(g.faces):
            if self.gravity[axis] != 0.0:
                wp.launch(KF.add_constant, f.shape, inputs=[self.gravity[axis] * dt], outputs=[f], device=self.device)
        g.label(self.levelset.phi)
        self.pressure.project(self.levelset.phi)
        g.extrapolate_velocity(self.extrapolation_layers)
        self.time += dt
        self.steps += 1

    def checkpoint(self) -> dict:
        """Everything needed to continue bit for bit (host copies)."""
        return {**self.grid.checkpoint(), **self.levelset.checkpoint(), "time": self.time, "steps": self.steps}

    def restore(self, data) -> None:
        """Inverse of :meth:`checkpoint` (same grid and settings)."""
        self.grid.restore(data)
        self.levelset.restore(data)
        self.time, self.steps = float(data["time"]), int(data["steps"])

    def volume(self) -> float:
        """Liquid volume [m^3] (2D: area [m^2])."""
        return self.levelset.volume()

    def max_speed(self) -> float:
        """Largest face speed [m/s] over faces next to liquid (host read-back)."""
        return max(float(np.abs(f.numpy()).max()) for f in self.grid.faces)
