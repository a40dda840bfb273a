"""Cloth: grid and triangle-mesh cloth builders with structural, shear and bend springs
(``builder``), the Baraff-Witkin implicit Euler solver on ``warp.sparse`` + CG (``implicit``, with
its contact constraints in ``contact``), a fused semi-implicit solver (``semi_implicit``, its
eight-lane blocks in ``lanes``) and the Simulator that replays a frame's sub-steps as a graph
(``solver``, which also re-exports both integrators); the preallocated block-Jacobi CG they use is
``warpsim.core.block_cg``.

Drives ``warpsim.kernels.cloth`` (with ``cloth_lanes``, ``cloth_contact``, ``forces`` and ``integrate``).
Entry classes: add_cloth_grid, add_cloth_mesh, ClothSimulator, ClothImplicitEuler.
"""

from .builder import Cloth, add_cloth_grid, add_cloth_mesh
from .solver import ClothImplicitEuler, ClothSemiImplicitEuler, ClothSimulator, cloth_energy

__all__ = ["Cloth", "add_cloth_grid", "add_cloth_mesh", "cloth_energy", "ClothImplicitEuler",
           "ClothSemiImplicitEuler", "ClothSimulator"]
