"""Cloth: grid and triangle-mesh cloth builders with structural, shear and bend springs
(``builder``), the Baraff-Witkin implicit Euler solver on ``warp.sparse`` + CG and a fused
semi-implicit solver (``solver``); the preallocated block-Jacobi CG they use is
``warpsim.core.block_cg``.

Drives ``warpsim.kernels.cloth`` (with ``forces`` and ``integrate``).
Entry classes: add_cloth_grid, add_cloth_mesh, ClothSimulator, ClothImplicitEuler.
"""

from .builder import Cloth, add_cloth_grid, add_cloth_mesh
from .solver import ClothImplicitEuler, ClothSemiImplicitEuler, ClothSimulator, cloth_energy

__all__ = ["Cloth", "add_cloth_grid", "add_cloth_mesh", "cloth_energy", "ClothImplicitEuler",
           "ClothSemiImplicitEuler", "ClothSimulator"]
