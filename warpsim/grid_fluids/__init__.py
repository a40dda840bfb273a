"""Eulerian grid fluids: the staggered MAC grid (``mac_grid``), advection (``advection``), the
pressure projection with CG and a multigrid preconditioner (``pressure``, ``multigrid``), marker
particles (``particles``), level sets and the level-set liquid, smoke, FLIP/PIC and viscosity.

Drives ``warpsim.kernels.grid``, ``advect``, ``multigrid``, ``grid_forces``, ``grid_particles``,
``levelset`` and ``flip``.
Entry classes: MacGrid, Smoke, LevelSetLiquid, FlipLiquid, PressureSolver.
"""

from .advection import Advector
from .flip import FlipLiquid
from .levelset import LevelSet
from .levelset_liquid import LevelSetLiquid
from .mac_grid import MacGrid
from .pressure import PressureSolver
from .smoke import Smoke
from .viscosity import Viscosity

__all__ = ["MacGrid", "PressureSolver", "Advector", "LevelSet", "LevelSetLiquid", "Smoke", "FlipLiquid", "Viscosity"]
