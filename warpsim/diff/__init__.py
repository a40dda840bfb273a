"""Differentiable runs: gradients of a loss on a rollout with respect to the physics parameters.

``ws.Simulator(model, ..., differentiable=True)`` (and ``ws.ClothSimulator(...,
integrator="semi_implicit_euler", differentiable=True)``) steps out of place, one State per step,
every launch recorded on a ``wp.Tape`` (:class:`Rollout`, ``sim.rollout``); the forward result
equals the ordinary mode's. Kernels: the force kernels of ``warpsim.kernels.forces`` (compiled
with their adjoints) and ``warpsim.kernels.autodiff`` (integrators, contacts, losses).

The Rollout lives beside the Simulator that builds it (``warpsim.core.rollout``, re-exported here);
this package adds the float64 NumPy references the tests check gradients against (``reference``).

Entry points: :class:`Rollout` (``sim.rollout``: ``tape``, ``states``, ``reset``, ``backward``,
``mass_gradient``, ``coefficient_gradients``, ``trajectory_loss``) and
:func:`check_differentiable` (the refusals, also for fluid solvers).
"""

from ..core.rollout import DIFFERENTIABLE_FORCES, Rollout, check_differentiable

__all__ = ["DIFFERENTIABLE_FORCES", "Rollout", "check_differentiable"]
