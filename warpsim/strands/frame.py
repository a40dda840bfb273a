"""A hair frame's strand steps with the head's poses on the device, so the frame can be captured
as one CUDA graph and replayed while the head moves (``HairFrame``; the ``hair`` scene uses it).

Kinematic colliders pass their pose to their kernels as launch parameters, which a graph would
freeze. ``PosedSphere`` (a ``ws.Sphere``) and ``StrandRoots`` with ``poses=`` read the pose of the
frame's step k from a small device array instead (``HeadPoses``: 2 transforms a step, before and
after it), which the host fills once a frame (one copy) by advancing the head exactly as the
eager steps would (``Sphere.advance_pose``: its clock, pose and surface speed stay the same). Stepping
allocates nothing and reads nothing back inside a frame; the blow-up test reads one int after it.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from ..bodies.colliders import Plane, Sphere
from ..core.solver import SolverBase
from ..kernels import strands as K

__all__ = ["HairFrame", "HeadPoses", "PosedSphere"]


class HeadPoses:
    """The head's poses for the steps of one frame: ``poses`` (2 n,) wp.transform on ``device``,
    poses[2 k] and poses[2 k + 1] the head before and after step k. ``load`` advances ``head`` n
    steps of ``h`` [s] on the host and copies the poses in; the users' step counters restart."""

    def __init__(self, head, device):
        self.head = head
        self.device = wp.get_device(device)
        self.poses = None
        self._host = None
        self.users: list = []
        self.steps = 0
        self._copied = None  # CUDA: the event after the last copy out of the pinned host buffer

    def load(self, h: float, n: int) -> None:
        if self.poses is None or self.poses.shape[0] < 2 * n:  # the first frame (or more steps): outside capture
            self.poses = wp.zeros(2 * n, dtype=wp.transform, device=self.device)
            self._host = self.poses if self.device.is_cpu else wp.zeros(2 * n, dtype=wp.transform, device="cpu",
                                                                          pinned=True)
        if self._copied is not None:
            wp.synchronize_event(self._copied)  # the previous frame's copy has read the buffer
        host = self._host.numpy()
        for k in range(n):
            prev, now = self.head.advance_pose(h)
            host[2 * k] = np.asarray(prev, np.float32)
            host[2 * k + 1] = np.asarray(now, np.float32)
        if self._host is not self.poses:
            wp.copy(self.poses, self._host, count=2 * n)
            self._copied = self.device.stream.record_event()
        self.steps = n
        for user in self.users:
            user.step_index = 0


class PosedSphere(Sphere):
    """``ws.Sphere`` whose steps inside a ``HairFrame`` read their pose from ``HeadPoses`` (device);
    stepped on its own (``Simulator.step`` outside a frame) it is a plain ``ws.Sphere``."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.frame_poses: HeadPoses | None = None
        self.step_index = 0

    def apply(self, model, state, q_prev, dt) -> None:
        fp = self.frame_poses
        if fp is None or self.step_index >= fp.steps:
            return super().apply(model, state, q_prev, dt)
        k, self.step_index = self.step_index, self.step_index + 1
        wp.launch(K.collide_sphere_posed, model.particle_count,
                  inputs=[model.particle_inv_mass, model.particle_radius, q_prev, fp.poses, k, self.radius,
                          *self._contact_args(dt), state.forces, state.positions, state.velocities],
                  device=model.device)


class HairFrame(SolverBase):
    """Steps a hair ``Simulator`` one frame of n equal steps with a ``PosedSphere`` head and its
    ``StrandRoots`` reading the head's poses from the device; on CUDA (``use_graph``) the frame is
    captured once per (n, h) as a CUDA graph (after one eager frame: every module loaded) and
    replayed. The host keeps the simulator's clock and step count as ``Simulator.step`` would and
    runs its blow-up test after the frame when due (one int read back). A
    ``warpsim.core.solver.Solver``: ``frame`` is ``advance``, ``step`` and ``state`` the simulator's."""

    def __init__(self, sim, head: PosedSphere, roots, use_graph=None):
        self.sim, self.head, self.roots = sim, head, roots
        self.poses = HeadPoses(head, sim.device)
        head.frame_poses = self.poses
        roots.use_poses(self.poses)
        self.poses.users = [head, roots]
        self.use_graph = wp.get_device(sim.device).is_cuda if use_graph is None else bool(use_graph)
        self._graphs: dict = {}

    def _key(self, n: int, h: float):
        """What the captured launches bake in: the step, the forces (a drag spring's target is a
        launch parameter) and the colliders' contact parameters; None when a collider cannot be
        replayed (another moving shape, strand-strand collisions: their launches vary)."""
        sim = self.sim
        if any(not isinstance(c, (PosedSphere, Plane)) and c is not self.roots for c in sim.colliders) or \
                any(getattr(c, "motion", None) is not None and c is not self.head for c in sim.colliders):
            return None
        if any(hasattr(f, "target_at") for f in sim.forces):
            return None
        keys = ("restitution", "friction", "mode", "thickness", "stiffness")
        contact = tuple(tuple(getattr(c, a, None) for a in keys) for c in sim.colliders)
        return n, h, tuple(map(id, sim.forces)), contact

    @property
    def state(self):
        """The simulator's state."""
        return self.sim.state

    def step(self, dt: float) -> int:
        """One eager step of the simulator (the head's pose as a launch parameter)."""
        return self.sim.step(dt)

    def frame(self, frame_dt: float, steps: int = 1) -> None:
        """As :meth:`advance`."""
        self.advance(frame_dt, steps)

    def notify_changed(self, what: str) -> None:
        """As ``Simulator.notify_changed``; the captured frame graphs are dropped too (re-captured
        with the new values)."""
        self.sim.notify_changed(what)
        self._graphs.clear()

    def advance(self, frame_dt: float, n: int) -> None:
        h = frame_dt / n
        self.poses.load(h, n)
        key = self._key(n, h) if self.use_graph else None
        graph = self._graphs.get(key)
        if key is None or (graph is None and self.sim.step_count == 0):
            for _ in range(n):  # eager (the first frame loads every module before a capture)
                self.sim.step(h)
            return
        sim = self.sim
        if graph is None:
            kept = sim.check_every, sim.time, sim.step_count
            sim.check_every = 0  # no read-back inside the capture
            try:
                with wp.ScopedCapture(device=sim.device) as capture:
                    for _ in range(n):
                        sim.step(h)
            finally:  # the capture ran no step: its host bookkeeping is taken back
                sim.check_every, sim.time, sim.step_count = kept
            if len(self._graphs) >= 8:
                self._graphs.clear()
            graph = self._graphs[key] = capture.graph
        wp.capture_launch(graph)
        for _ in range(n):  # as Simulator.step does, one step at a time
            sim.time += h
            sim.step_count += 1
        sim.last_substeps = 1
        if sim.check_every and sim.step_count % sim.check_every < n:
            sim.check()  # one int read back; raises SimulationError naming the particle
