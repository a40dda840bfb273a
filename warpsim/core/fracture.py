"""Springs that break: the per-step stage that marks springs past their threshold, and the
per-frame report of which springs broke.

Thresholds come from the builder (``add_spring(..., break_strain=, break_force=)`` or
``set_spring_breaking``); ``ws.Simulator`` adds a :class:`SpringFracture` stage by itself when
the model has breakable springs (``sim.fracture``). The stage runs after integration like a
collider (kernel ``warpsim.kernels.fracture.break_springs``) and writes the model's device mask
``model.spring_broken`` (int, (spring_count,), 1 = broken): a broken spring exerts no force and
leaves the implicit integrators' Jacobian for good. Nothing is allocated per step.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import warp as wp

from ..kernels import fracture as K
from .collider import Collider


@dataclass
class BreakReport:
    """Springs that broke during one frame: ``frame`` index and ``springs`` (their indices,
    int64, ascending); ``count`` = len(springs)."""

    frame: int
    springs: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    @property
    def count(self) -> int:
        return len(self.springs)


class SpringFracture(Collider):
    """Breaks springs past their thresholds after every (sub-)step (see module docstring).

    After :meth:`end_frame` (called by ``Simulator.run`` once per frame, or by a scene),
    ``history`` holds one :class:`BreakReport` per frame and ``broken_count`` the total.
    """

    def __init__(self):
        self.history: list[BreakReport] = []
        """One BreakReport per frame reported through :meth:`end_frame`."""
        self.model = None

    def bind(self, model) -> None:
        super().bind(model)
        if not hasattr(model, "spring_broken"):
            raise ValueError("SpringFracture needs a model from ws.ModelBuilder.finalize (spring_broken mask)")
        d = model.device
        self._known = model.spring_broken.numpy().astype(bool)
        self._count = wp.array([int(self._known.sum())], dtype=int, device=d)

    def apply(self, model, state, q_prev, dt) -> None:
        if not model.breakable_spring_count:
            return
        wp.launch(K.break_springs, model.spring_count,
                  inputs=[state.positions, state.velocities, model.spring_indices, model.spring_rest_length,
                          model.spring_stiffness, model.spring_damping, model.spring_break_strain,
                          model.spring_break_force, model.spring_broken, self._count], device=model.device)

    # ------------------------------------------------------------------ host side (between frames)
    @property
    def broken_count(self) -> int:
        """Springs broken so far (reads one int from the device)."""
        return int(self._count.numpy()[0])

    def broken(self) -> np.ndarray:
        """The mask as booleans, shape (spring_count,) (reads it back)."""
        return self.model.spring_broken.numpy().astype(bool)

    def poll(self) -> np.ndarray:
        """Indices of the springs broken since the last poll (reads one int; the mask only when
        that count changed)."""
        if self.broken_count == int(self._known.sum()):
            return np.zeros(0, dtype=np.int64)
        now = self.broken()
        new = np.flatnonzero(now & ~self._known).astype(np.int64)
        self._known = now
        return new

    def end_frame(self, frame: int) -> BreakReport:
        """Report the springs broken since the previous report as frame ``frame``'s breaks."""
        report = BreakReport(int(frame), self.poll())
        self.history.append(report)
        return report

    def restore(self, broken) -> None:
        """Set the mask (e.g. from a checkpoint): ``broken`` (spring_count,) booleans or 0/1."""
        mask = np.asarray(broken).astype(bool).reshape(-1)
        m = self.model
        if len(mask) != m.spring_count:
            raise ValueError(f"spring mask has {len(mask)} entries but the model has {m.spring_count} springs")
        m.spring_broken.assign(wp.array(mask.astype(np.int32), dtype=int, device=m.device))
        self._known = mask.copy()
        self._count.assign(wp.array([int(mask.sum())], dtype=int, device=m.device))


def spring_segments(positions, spring_indices, broken=None) -> np.ndarray:
    """End points of every spring as curve vertices, shape (2 * spring_count, 3): broken springs
    collapse onto their first particle (zero length, so a curves prim drawn from them loses the
    broken springs while its topology stays fixed). ``positions`` (n, 3), ``spring_indices``
    (2 m,) or (m, 2), ``broken`` (m,) or None."""
    x = np.asarray(positions.numpy() if hasattr(positions, "numpy") else positions)
    pairs = np.asarray(spring_indices.numpy() if hasattr(spring_indices, "numpy") else spring_indices)
    pairs = pairs.reshape(-1, 2)
    ends = pairs.copy()
    if broken is not None:
        mask = np.asarray(broken.numpy() if hasattr(broken, "numpy") else broken).astype(bool).reshape(-1)
        ends[mask, 1] = ends[mask, 0]
    return x[ends.reshape(-1)]
