"""Lagrangian particle liquids: position-based fluids (``pbf``) with signed-distance boundaries
(``boundaries``), divergence-free SPH with boundary particles (``dfsph``, ``method="dfsph"``),
nozzles and sinks (``emitters``), the SPH smoothing kernels on the host (``smoothing``), a float64
NumPy reference step (``reference``), a surface mesh per frame (``surface``) and the dam break
against Martin and Moyce's (1952) table (``martin_moyce``).

Drives ``warpsim.kernels.sph``, ``warpsim.kernels.dfsph`` and ``warpsim.kernels.fluid_surface``
(with marching cubes).
Entry classes: ParticleFluid, fluid_block, Nozzle, Sink, FluidSurface.
"""

from .emitters import Nozzle, Sink
from .pbf import ParticleFluid
from .smoothing import fluid_block
from .surface import FluidSurface

__all__ = ["ParticleFluid", "Nozzle", "Sink", "fluid_block", "FluidSurface"]
