"""The protocol every solver follows (particles, cloth, strands, fluids, agents):

- ``step(dt)``: advance by ``dt`` [s] (one step, or the solver's own sub-steps of it);
- ``frame(frame_dt, steps)``: advance one frame of ``frame_dt`` [s] in ``steps`` equal steps, with
  the solver's per-frame work (blow-up and energy checks, sinks, captured graphs);
- ``state``: what the solver advances (a ``ws.State`` or a view with ``positions`` and
  ``velocities`` for particle solvers; the velocity grid for grid fluids; for ``Flock`` and
  ``Crowd``, whose positions and velocities are their own attributes, each agent's behaviour);
- ``notify_changed(what)``: announce an edit made from outside (``what`` in ``CHANGES``), so the
  solver drops what it derived from the old values (integrator buffers, stability limits,
  captured graphs, the energy balance's reference). Nothing edits another object's private fields
  to announce a change.

``SolverBase`` gives the plain versions: ``frame`` as ``steps`` calls of ``step`` and a
``notify_changed`` that checks its argument and forgets nothing (a solver that caches nothing).
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

from . import checks

CHANGES = ("forces", "colliders", "parameters", "state")
"""What ``notify_changed`` accepts: the force list, the colliders (added, moved by hand, clock
set), parameters edited in place (stiffness, masses, coefficients), the state edited by hand
(positions, velocities, a restored checkpoint)."""


@runtime_checkable
class Solver(Protocol):
    """The solver protocol (module docstring); ``isinstance(obj, Solver)`` checks the names."""

    @property
    def state(self) -> Any: ...

    def step(self, dt: float) -> Any: ...

    def frame(self, frame_dt: float, steps: int = 1) -> Any: ...

    def notify_changed(self, what: str) -> None: ...


def check_change(what, owner: str) -> str:
    """``what`` if it is one of ``CHANGES``; else ValueError naming ``owner`` and the choices."""
    return checks.choice(what, f"{owner}.notify_changed what", CHANGES, fix="say what was edited")


def frame_steps(frame_dt, steps, owner: str) -> tuple[float, int]:
    """(frame_dt, steps) checked: a finite frame length > 0 [s] and a step count >= 1."""
    frame_dt = checks.positive(frame_dt, f"{owner}.frame frame_dt", "s", "e.g. 1/60")
    steps = checks.count(steps, f"{owner}.frame steps", fix="equal steps per frame, e.g. 1")
    return frame_dt, steps


class SolverBase:
    """Default ``frame`` and ``notify_changed`` for a solver that has ``step(dt)`` and ``state``."""

    def step(self, dt: float) -> Any:
        raise NotImplementedError

    def frame(self, frame_dt: float, steps: int = 1) -> None:
        """Advance one frame of ``frame_dt`` [s] in ``steps`` equal calls of ``step``."""
        frame_dt, steps = frame_steps(frame_dt, steps, type(self).__name__)
        for _ in range(steps):
            self.step(frame_dt / steps)

    def notify_changed(self, what: str) -> None:
        """Announce an outside edit (``what`` in ``CHANGES``); this solver derives nothing from
        its inputs that could go stale, so it only checks ``what``."""
        check_change(what, type(self).__name__)
