"""Cloth solvers: Baraff-Witkin implicit Euler on ``warp.sparse`` + CG, a fused semi-implicit
Euler, and a Simulator that replays each frame's sub-steps as a captured graph.

- :class:`ClothImplicitEuler` (``warpsim.cloth.implicit``): each step solves
  ``(M - h D - h^2 K) dv = h (f0 + h K v0)`` (Baraff & Witkin 1998; ``newton_iterations > 1``
  continues with Newton iterations on backward Euler). Spring blocks are written by one kernel
  straight into a fixed-topology BSR matrix; block-Jacobi preconditioned CG solves it
  (``warpsim.core.block_cg.BlockCG``, capturable, by default; or ``warp.optim.linear.cg``,
  preallocated); pinned rows and columns are filtered.
  Per step it reports CG iterations, final residual and tolerance.
- :class:`ClothSemiImplicitEuler` (``warpsim.cloth.semi_implicit``): v += h (f/m + g), x += h v
  with springs, gravity and the update fused ("scatter": spring-force kernels + particle kernels;
  "owner", the CPU default: each spring evaluated once by its lower end's thread + a particle
  kernel, scatter's sums bit for bit; "gather", the CUDA default: one particle-centric kernel).
  All sum each particle's springs in a fixed order without float atomics, as does the implicit
  solver's assembly and its CG dot products, so runs are bit-reproducible on every device.
- :class:`ClothSimulator` (here): a ``ws.Simulator`` whose ``frame()`` / ``run()`` capture a frame's
  sub-steps (forces, solve, colliders) in a graph (CUDA and CPU) and replay it; no allocation
  and no host read-back inside a frame.

All three accept any ws.Force list: gravity and the model springs are fused; other forces are
evaluated through their own kernels (for the implicit solver they must have per-particle
Jacobian blocks only). The two integrators are importable from here as before.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from ..core import checks
from ..core.forces import Gravity, Springs
from ..core.integrators import INTEGRATORS, Integrator, make_integrator
from ..core.simulator import Simulator, check_dt
from ..kernels import cloth as KC
from ..kernels import integrate as KI
from .implicit import CONTACT_MODES, GEOMETRIC_MODES, LINEAR_SOLVERS, ClothImplicitEuler
from .semi_implicit import GATHER_MAX_PARTICLES, ClothSemiImplicitEuler

__all__ = [
    "CLOTH_INTEGRATORS", "CONTACT_MODES", "GATHER_MAX_PARTICLES", "GEOMETRIC_MODES", "LINEAR_SOLVERS",
    "ClothImplicitEuler", "ClothSemiImplicitEuler", "ClothSimulator", "cloth_energy", "make_cloth_integrator",
]


CLOTH_INTEGRATORS = {"semi_implicit_euler": ClothSemiImplicitEuler, "implicit_euler": ClothImplicitEuler,
                     ClothSemiImplicitEuler.name: ClothSemiImplicitEuler, ClothImplicitEuler.name: ClothImplicitEuler}


def make_cloth_integrator(integrator) -> Integrator:
    """The fused cloth integrator for "semi_implicit_euler" / "implicit_euler" (and their
    ``cloth_*`` names); any other name or Integrator instance as ``ws.Simulator`` takes it."""
    if isinstance(integrator, str) and integrator in CLOTH_INTEGRATORS:
        return CLOTH_INTEGRATORS[integrator]()
    if isinstance(integrator, str) and integrator not in INTEGRATORS:
        valid = ", ".join(sorted(set(INTEGRATORS) | set(CLOTH_INTEGRATORS)))
        raise ValueError(f"unknown integrator {integrator!r}; valid integrators: {valid}")
    return make_integrator(integrator)


class ClothSimulator(Simulator):
    """``ws.Simulator`` for cloth: the fused integrators, and frames whose sub-steps run as one
    captured graph.

    Args: as ``ws.Simulator`` (``integrator`` defaults to "implicit_euler"; "semi_implicit_euler"
    and "implicit_euler" pick the cloth integrators above), plus
        use_graph: capture each frame's sub-steps once and replay them (None: yes, on CUDA and on
            the CPU). Frames run eagerly while a collider follows a ``motion`` callback, and the
            graphs are re-captured after a collider's ``set_transform``. Forces, colliders and
            model parameters must not be replaced after the first frame (arrays may change in
            place).
        check_every: blow-up test every this many frames (``step`` tests every this many steps).

    ``frame(frame_dt, substeps)`` advances one frame; ``run`` uses it. ``step(dt)`` takes one
    eager step like ws.Simulator. The blow-up test (every ``check_every`` frames) runs inside
    the frame and costs one read-back of an int. ``state.forces`` is not filled: the fused
    kernels never materialise the total force.
    """

    def __init__(self, model, integrator="implicit_euler", forces=None, colliders=(), *, use_graph=None,
                 check_every=1, **kwargs):
        super().__init__(model, make_cloth_integrator(integrator), forces, colliders, check_every=check_every,
                         **kwargs)
        bind = getattr(self.integrator, "bind_colliders", None)
        if bind is not None:
            bind(self.colliders)  # contact constraints inside the implicit solve
        if use_graph is None:
            use_graph = True
        self.use_graph = checks.flag(use_graph, "ClothSimulator use_graph") and not self.adaptive
        self._needs_time = any(not isinstance(f, (Gravity, Springs)) for f in self.forces)
        self._graphs = {}
        self._captured_poses = ()
        self.frame_count = 0
        """Frames advanced by ``frame``."""
        st = self.state
        self._home = (st.positions, st.velocities)
        self._spare = (wp.zeros_like(st.positions), wp.zeros_like(st.velocities))

    def add_force(self, force) -> None:
        """As ``Simulator.add_force``; the captured frame graphs are dropped and re-captured."""
        super().add_force(force)
        self._needs_time = any(not isinstance(f, (Gravity, Springs)) for f in self.forces)
        self._graphs.clear()

    def notify_changed(self, what: str) -> None:
        """As ``Simulator.notify_changed``; the captured frame graphs are dropped too (re-captured
        at the next frame, with the new values baked into their launches)."""
        super().notify_changed(what)
        self._graphs.clear()

    def _gather(self) -> bool:
        return isinstance(self.integrator, ClothSemiImplicitEuler) and self.integrator.out_of_place

    def _substep(self, h: float, time_offset_steps: int, pingpong: bool) -> None:
        """One sub-step: integrate, collide, (advance time). No host read-back."""
        st, system = self.state, self.system
        if pingpong and self._gather():
            q_out = self._spare[0] if st.positions is self._home[0] else self._home[0]
            qd_out = self._spare[1] if st.velocities is self._home[1] else self._home[1]
            self.integrator.step_to(system, st.positions, st.velocities, self._time, h, q_out, qd_out)
            q_prev = st.positions
            st.positions, st.velocities = q_out, qd_out
        else:
            q_prev = self._q_prev
            if self.colliders:
                wp.copy(q_prev, st.positions)
            self.integrator.step(system, st.positions, st.velocities, self._time, h)
        for c in self.colliders:
            c.apply(self.model, st, q_prev, h)
        if self._needs_time:
            wp.launch(KI.advance_time, 1, inputs=[self._time, h], device=self.device)

    def _go_home(self) -> None:
        st = self.state
        if st.positions is not self._home[0]:
            wp.copy(self._home[0], st.positions)
            wp.copy(self._home[1], st.velocities)
            st.positions, st.velocities = self._home

    def _frame_body(self, frame_dt: float, substeps: int) -> None:
        h = frame_dt / substeps
        begin = getattr(self.integrator, "begin_frame", None)
        if begin is not None:
            begin(self.system)
        try:
            for k in range(substeps):
                self._substep(h, k, pingpong=True)
        finally:
            if begin is not None:
                self.integrator.end_frame()
        self._go_home()
        if not self._needs_time:
            wp.launch(KI.advance_time, 1, inputs=[self._time, frame_dt], device=self.device)
        # blow-up detection inside the frame: the host reads one int afterwards
        self._first_bad.fill_(self.system.count)
        wp.launch(KI.find_blow_up, self.system.count, inputs=[self.state.positions, self.state.velocities,
                                                              self.max_speed, self._first_bad], device=self.device)

    def frame(self, frame_dt: float = 1.0 / 60.0, substeps: int = 1) -> None:
        """Advance one frame of ``frame_dt`` [s] in ``substeps`` equal steps (graph replay where
        enabled), then test for blow-up every ``check_every`` frames."""
        frame_dt = check_dt(frame_dt)
        if int(substeps) < 1:
            raise ValueError(f"substeps = {substeps}; it must be >= 1")
        substeps = int(substeps)
        if self.warn_unstable and frame_dt / substeps != self._checked_dt:
            self._warn_if_unstable(frame_dt / substeps)  # once per step size, before the first step
        if self.rollout is not None:  # differentiable: eager steps, one recorded state per sub-step
            for _ in range(substeps):
                Simulator.step(self, frame_dt / substeps)
            self.frame_count += 1
            return
        self.integrator.prepare(self.system)
        h = frame_dt / substeps
        if self._energy is None and self.check_every and not wp.get_device(self.device).is_capturing:
            self._start_energy(h)  # the energy balance's frame 0 (``check_frame`` folds in each frame)
        self._last_h = h
        poses = self._collider_poses()
        if poses is None or poses != self._captured_poses:
            self._graphs.clear()  # a collider moves: its pose is baked into the launches
        if self.use_graph and poses is not None:
            key = (frame_dt, substeps)
            graph = self._graphs.get(key)
            if graph is None:
                self._frame_body(frame_dt, substeps)  # eager first frame loads every module
                self._advance_host(frame_dt, substeps)
                with wp.ScopedCapture(device=self.device) as capture:
                    self._frame_body(frame_dt, substeps)
                self._graphs[key] = capture.graph
                self._captured_poses = poses
            else:
                wp.capture_launch(graph)
                self._advance_host(frame_dt, substeps)
        else:
            self._frame_body(frame_dt, substeps)
            self._advance_host(frame_dt, substeps)
        due = self.check_every and self.frame_count % self.check_every == 0
        if due and int(self._first_bad.numpy()[0]) < self.system.count:
            self.check()  # raises SimulationError naming step, particle and remedy

    def _collider_poses(self):
        """Poses of kinematic colliders (None when one follows a ``motion`` callback: such frames
        run eagerly, since collider poses are launch parameters that a graph would freeze)."""
        poses = []
        for c in self.colliders:
            if getattr(c, "motion", None) is not None:
                return None
            if hasattr(c, "world_pose"):
                p, q = c.world_pose()
                poses.append(tuple(np.round(np.concatenate([p, q]), 12)))
        return tuple(poses)

    def _advance_host(self, frame_dt, substeps):
        self.time += frame_dt
        self.step_count += substeps
        self.frame_count += 1
        self.last_substeps = substeps

    def _advance_substep(self, h: float) -> None:
        """One eager sub-step for :meth:`Simulator.step` (adaptive sub-stepping included)."""
        if self.rollout is not None:
            return self.rollout.advance(h)
        self._substep(h, 0, pingpong=False)
        if not self._needs_time:
            wp.launch(KI.advance_time, 1, inputs=[self._time, h], device=self.device)

    def run(self, frames: int, frame_dt: float = 1.0 / 60.0, substeps: int = 1, callback=None, writer=None):
        """As ws.Simulator.run, each frame advanced by ``frame``."""
        frame_dt = check_dt(frame_dt)
        if int(frames) < 0:
            raise ValueError(f"frames = {frames}; it must be >= 0")
        self._run_frames(int(frames), frame_dt, substeps, callback, writer)


def cloth_energy(model, q, qd, gravity=(0.0, 0.0, 0.0)) -> tuple:
    """(kinetic, spring potential, gravitational potential) energy [J] of a state (reads back;
    not for use inside a step). Gravitational potential is -m g . x."""
    d = model.device
    out = wp.zeros(2, dtype=float, device=d)
    wp.launch(KC.eval_kinetic_energy, model.particle_count, inputs=[qd, model.particle_mass, out[0:1]], device=d)
    if model.spring_count:
        wp.launch(KC.eval_cloth_spring_energy, model.spring_count,
                  inputs=[q, model.spring_indices, model.spring_rest_length, model.spring_stiffness,
                          model.spring_broken, out[1:2]],
                  device=d)
    kinetic, spring = (float(x) for x in out.numpy())
    m = model.particle_mass.numpy().astype(np.float64)
    grav = float(-(m[:, None] * q.numpy().astype(np.float64) * np.asarray(gravity)).sum())
    return kinetic, spring, grav
