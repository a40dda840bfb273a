"""Per-world step counts on the batch paths without a masked step kernel: one pass per count.

A :class:`warpsim.worlds.WorldBatch` on the shared path steps every world by its own count in one
kernel (:mod:`warpsim.worlds.shared`). The other paths step with the scene's own simulator (the
tiled model: one launch per stage with one step h for every particle; cloth's captured frames).
When their worlds take different automatic counts, a frame runs once per distinct count c: every
world is stepped c times of ``frame_dt / c`` from the frame's start and the worlds that take c
keep that result (``kernels/worlds.py: keep_worlds_of_count``). The clocks a pass advances (the
simulator's host time and device clock, kinematic colliders' clocks) are kept per count from frame
to frame, so each world sees the clock of its own run. The cost is the sum of the distinct counts
in steps a frame instead of the largest.
"""
from __future__ import annotations

import numpy as np
import warp as wp

from ..kernels import worlds as KW

__all__ = ["CountPasses"]


class CountPasses:
    """The passes of ``batch`` (a WorldBatch) whose worlds take ``counts`` (world_count,) steps a
    frame; buffers allocated once (a frame makes no allocation)."""

    def __init__(self, batch, counts):
        d, st = batch.device, batch.sim.state
        self.batch = batch
        self.host_counts = np.array(counts, dtype=np.int64)
        """Each world's count (world_count,), on the host."""
        self.counts = sorted({int(c) for c in counts})
        self.world_steps = wp.array(self.host_counts.astype(np.int32), dtype=int, device=d)
        self.start = (wp.empty_like(st.positions), wp.empty_like(st.velocities))
        self.result = (wp.empty_like(st.positions), wp.empty_like(st.velocities))
        sim = batch.sim
        self._clock = getattr(sim, "_time", None)  # the simulator's device clock [s], (1,)
        self._clocks = None if self._clock is None else wp.zeros(len(self.counts), dtype=float, device=d)
        self._host = [None] * len(self.counts)  # per count: (host time, collider clocks), None: the frame start's
        self._started = [False] * len(self.counts)
        sim.warn_unstable = False  # a pass's step is another world's: the batch warns per world instead

    def _colliders(self):
        return [c for c in self.batch.sim.colliders if hasattr(c, "set_clock") and hasattr(c, "time")]

    def _load(self, i: int) -> None:
        """Put pass i's clocks in place (its first frame: the frame start's)."""
        sim = self.batch.sim
        if not self._started[i]:
            if self._clock is not None:
                wp.copy(self._clocks, self._clock, dest_offset=i, src_offset=0, count=1)
            self._host[i] = (sim.time, [c.time for c in self._colliders()])
            self._started[i] = True
        if self._clock is not None:
            wp.copy(self._clock, self._clocks, dest_offset=0, src_offset=i, count=1)
        time, clocks = self._host[i]
        sim.time = time
        for c, t in zip(self._colliders(), clocks):
            if c.time != t:
                c.set_clock(t)

    def _save(self, i: int) -> None:
        sim = self.batch.sim
        if self._clock is not None:
            wp.copy(self._clocks, self._clock, dest_offset=i, src_offset=0, count=1)
        self._host[i] = (sim.time, [c.time for c in self._colliders()])

    def frame(self, step) -> None:
        """One frame: ``step(c)`` advances every world by a frame of c steps; pass by pass."""
        b = self.batch
        st, d = b.sim.state, b.device
        wp.copy(self.start[0], st.positions)
        wp.copy(self.start[1], st.velocities)
        for i, c in enumerate(self.counts):
            if i:
                wp.copy(st.positions, self.start[0])
                wp.copy(st.velocities, self.start[1])
            self._load(i)
            step(c)
            self._save(i)
            wp.launch(KW.keep_worlds_of_count, st.positions.shape[0],
                      inputs=[st.positions, st.velocities, b.model.particle_world, self.world_steps, c, *self.result],
                      device=d)
        wp.copy(st.positions, self.result[0])
        wp.copy(st.velocities, self.result[1])
