"""Showing a ``ws.Simulator`` that the caller steps: a minimal Scene around it (its particles as
a points prim, its springs as curves) so the viewer draws it and the mouse can drag it."""
from __future__ import annotations

from typing import ClassVar

import numpy as np

from ..scenes import SimulatorScene

__all__ = ["SimulatorAdapter"]


class SimulatorAdapter(SimulatorScene):
    """Wraps a running ``ws.Simulator`` (``ws.Viewer(sim)``); never steps it itself."""

    name = "simulator"
    description = "a ws.Simulator stepped by the caller"
    params: ClassVar[dict] = {}

    def __init__(self, sim):
        self.sim = sim
        self.device = sim.device
        self.params = {}
        self.frame = 0

    def declare(self, sink):
        r = self.sim.model.particle_radius.numpy()
        radius = float(np.max(r)) if len(r) and np.max(r) > 0 else 0.01
        self.declare_state(sink, "particles", radius=radius, color=(0.2, 0.5, 0.9))
        if self.sim.model.spring_count:
            sink.add_curves("springs", self.sim.model.spring_indices.numpy(), width=0.002, color=(0.5, 0.5, 0.5))

    def frame_data(self):
        data = super().frame_data()
        if self.sim.model.spring_count:
            data["springs"] = {"points": self.sim.state.positions}
        return data

    def advance(self, frame_dt, substeps):
        raise ValueError("this viewer shows a simulator that the caller steps; call viewer.update() after stepping")
