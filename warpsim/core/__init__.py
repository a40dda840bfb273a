"""The particle core: :class:`ModelBuilder` -> :class:`Model` / :class:`State`, the forces, the five
time integrators (and :class:`FastMassSpring`: backward Euler for copies of one spring body by
local-global iterations), the systems they advance, the :class:`Simulator` loop (with its
differentiable mode's ``Rollout``, ``rollout``; ``warpsim.diff`` is its public face) and the
angle-form :class:`Pendulum`.

Drives ``warpsim.kernels.forces`` (gravity, wind, drag, magnets, springs) and
``warpsim.kernels.integrate`` (explicit/semi-implicit/implicit Euler, RK2, RK4, sparse Jacobians) and
``warpsim.kernels.fracture`` (springs that break: ``SpringFracture``) and ``warpsim.kernels.block_cg``
(``BlockCG``: the preallocated block-Jacobi CG of the implicit solvers) and
``warpsim.kernels.fast_mass_spring`` (``FastMassSpring``'s local step and tiled global product) and
``warpsim.kernels.autodiff`` (the rollout's out-of-place steps, contacts and losses).
Entry classes: ModelBuilder, Simulator, Gravity, Springs, SemiImplicitEuler, Pendulum.
"""

from .builder import ModelBuilder
from .errors import SimulationError
from .fast_mass_spring import FastMassSpring
from .forces import ConstantForce, Drag, Force, ForceField, Gravity, Magnets, Springs, Wind
from .fracture import BreakReport, SpringFracture, spring_segments
from .integrators import INTEGRATORS, RK2, RK4, ExplicitEuler, ImplicitEuler, Integrator, SemiImplicitEuler
from .model import Model, State
from .pendulum import Pendulum, exact_period
from .simulator import Simulator
from .stability import StabilityLimit, StabilityWarning
from .system import DynamicSystem, ParticleSystem, PendulumSystem

__all__ = [
    "ModelBuilder", "Model", "State", "Simulator", "SimulationError", "Force", "Gravity", "ConstantForce", "Wind",
    "Magnets", "Drag", "Springs", "ForceField", "Integrator", "ExplicitEuler", "SemiImplicitEuler", "ImplicitEuler",
    "RK2", "RK4", "INTEGRATORS", "FastMassSpring", "Pendulum", "exact_period", "DynamicSystem", "ParticleSystem", "PendulumSystem",
    "SpringFracture", "BreakReport", "spring_segments", "StabilityLimit", "StabilityWarning",
]
