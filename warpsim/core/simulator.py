"""Simulator: forces -> integrator -> colliders, with optional adaptive sub-stepping and
blow-up detection."""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from ..kernels import integrate as K
from .collider import Collider
from . import checks
from .errors import SimulationError
from .forces import Force, Gravity, cached_launch
from .fracture import SpringFracture
from .model import Model
from .integrators import make_integrator
from .system import ParticleSystem

REMEDY = "use a smaller dt, more sub-steps (or adaptive=True), or integrator='implicit_euler'"


def check_dt(dt) -> float:
    """dt as a float, or ValueError when it is not a finite positive number."""
    if isinstance(dt, (str, bytes, bool)) or dt is None:
        raise ValueError(f"dt must be a number > 0 [s], got {dt!r}")
    try:
        value = float(dt)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"dt must be a number > 0 [s], got {dt!r}") from exc
    if not math.isfinite(value) or value <= 0.0:
        raise ValueError(f"dt must be > 0 and finite [s], got {dt}")
    return value


class Simulator:
    """Steps a Model's particles.

    Args:
        model: a finalized ws.Model.
        integrator: a name from ``ws.INTEGRATORS`` ("explicit_euler", "semi_implicit_euler",
            "implicit_euler", "rk2", "rk4") or an Integrator instance (e.g. ws.ImplicitEuler(...)).
        forces: list of ws.Force; None means [ws.Gravity()], [] means no external force. The
            model's springs always act.
        colliders: list of ws.Collider, applied in order after each (sub-)step.
        adaptive: split each ``step(dt)`` into as many sub-steps as needed so that no particle
            moves more than ``max_displacement`` [m] per sub-step (estimated as |v| h + |a| h^2/2
            at the start of the step), at most ``max_substeps``.
        max_speed: speed [m/s] beyond which the run counts as blown up.
        check_every: test for blow-up every this many steps (0: never; the test reads one int
            back from the device).
        differentiable: step out of place, one State per step, recorded on a ``wp.Tape``
            (``sim.rollout``, a ``warpsim.diff.Rollout``: gradients of a loss with respect to
            spring stiffness/damping, masses, the initial state and force coefficients; the
            forward result equals the ordinary mode's). Raises ValueError for what cannot be
            differentiated (adaptive steps, implicit Euler, continuous collision detection, ...).
    """

    def __init__(self, model, integrator="semi_implicit_euler", forces=None, colliders=(), *, adaptive=False,
                 max_displacement=None, max_substeps=64, max_speed=1.0e4, check_every=1, differentiable=False):
        if not (isinstance(model, Model) or (hasattr(model, "particle_count") and hasattr(model, "state"))):
            raise ValueError(f"Simulator model must be a ws.Model (builder.finalize()), got {checks.show(model)}")
        for flag, value in (("differentiable", differentiable), ("adaptive", adaptive)):
            if not isinstance(value, (bool, np.bool_)):  # 'no' is truthy: never turn a mode on by accident
                raise TypeError(f"Simulator {flag} must be True or False, got {checks.show(value)}; e.g. "
                                f"{flag}=True")
        self.model = model
        self.device = model.device
        self.integrator = make_integrator(integrator)
        forces = [Gravity()] if forces is None else checks.sequence_of(forces, "forces", Force, "forces=[ws.Gravity()]")
        colliders = checks.sequence_of(colliders, "colliders", Collider, "colliders=[ws.Plane()]")
        if adaptive and max_displacement is None:
            raise ValueError("adaptive=True needs max_displacement > 0 [m] (the most a particle may move per sub-step)")
        max_displacement = 0.0 if max_displacement is None else checks.positive(
            max_displacement, "Simulator max_displacement", "m", "the most a particle may move per sub-step, e.g. 0.01")
        max_substeps = checks.count(max_substeps, "Simulator max_substeps", fix="give e.g. 64")
        max_speed = checks.positive(max_speed, "Simulator max_speed", "m/s",
                                    "the speed that counts as a blow-up, e.g. 1e4")
        check_every = checks.count(check_every, "Simulator check_every", minimum=0,
                                   fix="steps between blow-up checks (0: never)")
        self.system = ParticleSystem(model, forces)
        self.forces = self.system.forces
        self.colliders = colliders
        for c in self.colliders:
            c.bind(model)
        self.fracture = next((c for c in self.colliders if isinstance(c, SpringFracture)), None)
        """The spring-breaking stage (added by itself when the model has breakable springs) or None."""
        if self.fracture is None and getattr(model, "breakable_spring_count", 0):
            self.fracture = SpringFracture()
            self.fracture.bind(model)
            self.colliders.append(self.fracture)
        self.adaptive = bool(adaptive)
        self.max_displacement = max_displacement
        self.max_substeps = max_substeps
        self.max_speed = max_speed
        self.check_every = check_every

        self.state = model.state()
        self._check_finite_host()
        d = self.device
        self._q_prev = wp.zeros_like(self.state.positions)
        self._time = wp.zeros(1, dtype=float, device=d)
        self._scratch_float = wp.zeros(1, dtype=float, device=d)
        self._first_bad = wp.full(1, self.system.count, dtype=int, device=d)  # kept at count: nothing bad
        self._check_launches = {}
        self._check_due = False  # the current sub-step ends a step whose blow-up test is due
        self._device_checked = False  # that test already ran inside the integrator's pass
        self.time = 0.0
        """Simulated time [s]."""
        self.step_count = 0
        """Integration steps taken (sub-steps included)."""
        self.last_substeps = 0
        """Sub-steps the last ``step(dt)`` took."""
        self.substep_history = []
        """Sub-steps taken by each ``step(dt)`` call (adaptive runs)."""
        self.integrator.prepare(self.system)
        self.rollout = None
        """The differentiable rollout (``warpsim.diff.Rollout``) when ``differentiable=True``."""
        if differentiable:
            from ..diff import Rollout

            self.rollout = Rollout(self)

    # ----------------------------------------------------------------------------------
    def _check_finite_host(self):
        for name, arr in (("position", self.state.positions), ("velocity", self.state.velocities)):
            values = arr.numpy()
            bad = np.flatnonzero(~np.all(np.isfinite(values), axis=1))
            if len(bad):
                raise ValueError(f"particle {int(bad[0])} has a non-finite {name} {values[bad[0]]}; give finite values")

    def _substeps_for(self, dt: float) -> int:
        if not self.adaptive:
            return 1
        s = self.system
        s.eval_forces(self.state.positions, self.state.velocities, self._time, 0.0, self.state.forces)
        self._scratch_float.zero_()
        wp.launch(K.max_step_displacement, s.count,
                  inputs=[self.state.velocities, self.state.forces, s.inv_mass, dt, self._scratch_float], device=self.device)
        distance = float(self._scratch_float.numpy()[0])
        if not math.isfinite(distance):
            return self.max_substeps
        return int(min(self.max_substeps, max(1, math.ceil(distance / self.max_displacement))))

    def _advance_substep(self, h: float) -> None:
        """One sub-step of ``h`` [s]: integrate, collide, advance the device clock."""
        if self.rollout is not None:
            return self.rollout.advance(h)
        st = self.state
        fuses = getattr(self.integrator, "fuses", None)
        if fuses is not None and fuses(self.system):
            # one particle pass: q_prev (for the colliders), integration, the step's force, gravity
            # for the next step, the clock and (without colliders, whose passes come later) the
            # blow-up test
            check = (self.max_speed, self._first_bad) if self._check_due and not self.colliders else None
            self.integrator.fused_step(self.system, st.positions, st.velocities, self._time, h, f_out=st.forces,
                                       q_prev_out=self._q_prev if self.colliders else None, advance_time=True,
                                       check=check)
            self._device_checked = check is not None
            for c in self.colliders:
                c.apply(self.model, st, self._q_prev, h)
            return
        wp.copy(self._q_prev, st.positions)
        self.integrator.step(self.system, st.positions, st.velocities, self._time, h, f_out=st.forces)
        for c in self.colliders:
            c.apply(self.model, st, self._q_prev, h)
        wp.launch(K.advance_time, 1, inputs=[self._time, h], device=self.device)

    def add_force(self, force) -> None:
        """Add ``force`` (e.g. a ``ws.DragSpring`` for mouse dragging) to a running simulation;
        the integrator re-allocates its buffers for the new force list (once, here)."""
        self.system.add_force(force)
        self.forces = self.system.forces
        self.integrator._system = None  # prepare() is idempotent per system: force a re-allocation
        self.integrator.prepare(self.system)

    def step(self, dt: float) -> int:
        """Advance by ``dt`` [s]; returns the number of sub-steps taken."""
        dt = check_dt(dt)
        n = self._substeps_for(dt)
        h = dt / n
        due = bool(self.check_every) and (self.step_count + n) % self.check_every < n
        for k in range(n):
            self._check_due = due and k == n - 1
            self._device_checked = False
            self._advance_substep(h)
            self.time += h
            self.step_count += 1
        self._check_due = False
        self.last_substeps = n
        if self.adaptive:
            self.substep_history.append(n)
        if due:
            # a test fused into the last pass leaves first_bad at count when all is well; anything
            # else is confirmed (and reported) by check() on the same state
            if not self._device_checked or int(self._first_bad.numpy()[0]) < self.system.count:
                self.check()
        return n

    def check(self) -> None:
        """Raise SimulationError if a particle has a non-finite state or exceeds max_speed."""
        count = self.system.count
        self._first_bad.fill_(count)
        inputs = (self.state.positions, self.state.velocities, float(self.max_speed), self._first_bad)
        cached_launch(K.find_blow_up, count, inputs, self.device, self._check_launches,
                      key=(count, id(inputs[0]), id(inputs[1]), inputs[2], id(inputs[3])))
        bad = int(self._first_bad.numpy()[0])
        if bad < count:
            x = self.state.positions.numpy()[bad]
            v = self.state.velocities.numpy()[bad]
            raise SimulationError(
                f"simulation blew up at step {self.step_count} (t = {self.time:.6g} s): particle {bad} has position "
                f"{x} and velocity {v} (speed bound {self.max_speed:g} m/s). Remedy: {REMEDY}.",
                step=self.step_count, time=self.time, particle=bad,
            )

    def run(self, frames: int, frame_dt: float = 1.0 / 60.0, substeps: int = 1, callback=None, writer=None):
        """Simulate ``frames`` frames of ``frame_dt`` [s], each split into ``substeps`` steps.

        Frame 0 is the initial state. After each frame ``callback(frame, sim)`` is called and
        ``writer.write(frame, state)`` streams it. A blow-up raises SimulationError with ``frame``
        set; frames already handed to the writer stay written."""
        frame_dt = check_dt(frame_dt)
        substeps = checks.count(substeps, "run substeps", fix="give steps per frame, e.g. 1")
        frames = checks.count(frames, "run frames", minimum=0, fix="give the number of frames, e.g. 120")
        if writer is not None:
            writer.write(0, self.state)
        for frame in range(1, int(frames) + 1):
            try:
                for _ in range(int(substeps)):
                    self.step(frame_dt / substeps)
            except SimulationError as err:
                err.frame = frame
                err.args = (f"frame {frame}: {err.args[0]}",)
                raise
            if self.fracture is not None:
                self.fracture.end_frame(frame)  # per-frame BreakReport in self.fracture.history
            if callback is not None:
                callback(frame, self)
            if writer is not None:
                writer.write(frame, self.state)
