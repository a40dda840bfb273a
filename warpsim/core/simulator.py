"""Simulator: forces -> integrator -> colliders, with optional adaptive sub-stepping and
blow-up detection (non-finite states and a speed bound every step; an energy balance every frame,
``warpsim.core.energy``)."""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from ..kernels import integrate as K
from .collider import Collider
from . import checks
from .errors import SimulationError
from .forces import Force, Gravity
from .launch import cached_launch
from .fracture import SpringFracture
from .model import Model
from .integrators import make_integrator
from .solver import SolverBase, check_change, frame_steps
from . import stability as stab
from .system import ParticleSystem

REMEDY = ("use a smaller dt, more sub-steps (substeps='auto'; --substeps auto on the command line, or "
          "adaptive=True), or integrator='implicit_euler'")


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


def _idle(force) -> bool:
    """Whether a driving force can add no energy as set now, so the advice never blames it: a zero
    coefficient or stiffness (``Wind`` with coefficient 0, the cloth scene's default; a ``DragSpring``
    of stiffness 0), still air (``Wind`` of speed 0 is a drag), a zero ``ConstantForce``, ``Magnets``
    of zero strength, a ``DragSpring`` holding no particle."""
    def zero(name):
        value = getattr(force, name, None)
        if value is None or callable(value):
            return False
        try:
            return bool(np.all(np.asarray(value, dtype=np.float64) == 0.0))
        except (TypeError, ValueError):
            return False

    if any(zero(name) for name in ("coefficient", "stiffness", "strengths")):
        return True
    if type(force).__name__ == "Wind" and zero("speed"):
        return True
    if type(force).__name__ == "ConstantForce" and zero("force"):
        return True
    grabbed = getattr(force, "particle", None)
    return bool(type(force).__name__ == "DragSpring" and isinstance(grabbed, (int, np.integer)) and grabbed < 0)


def _ratio(gain: float) -> str:
    return "a non-finite amount" if gain >= 1.0e29 else f"{gain:.3g}x"


class Simulator(SolverBase):
    """Steps a Model's particles (a ``warpsim.core.solver.Solver``: ``step``, ``frame``, ``state``,
    ``notify_changed``).

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
        warn_unstable: before the first step of each new step size, compare it with
            ``stable_dt()`` and issue one ``ws.StabilityWarning`` naming the limiting spring when
            it is above (not while a graph is being captured, nor in adaptive runs).
        differentiable: step out of place, one State per step, recorded on a ``wp.Tape``
            (``sim.rollout``, a ``warpsim.diff.Rollout``, from ``warpsim.core.rollout``: gradients
            of a loss with respect to spring stiffness/damping, masses, the initial state and force
            coefficients; the forward result equals the ordinary mode's). Raises ValueError for
            what cannot be differentiated (adaptive steps, implicit Euler, continuous collision detection, ...).
    """

    def __init__(self, model, integrator="semi_implicit_euler", forces=None, colliders=(), *, adaptive=False,
                 max_displacement=None, max_substeps=64, max_speed=1.0e4, check_every=1, differentiable=False,
                 warn_unstable=True):
        if not (isinstance(model, Model) or (hasattr(model, "particle_count") and hasattr(model, "state"))):
            raise ValueError(f"Simulator model must be a ws.Model (builder.finalize()), got {checks.show(model)}")
        differentiable = checks.flag(differentiable, "Simulator differentiable")  # 'no' is truthy: refused
        adaptive = checks.flag(adaptive, "Simulator adaptive")
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
        self.warn_unstable = bool(warn_unstable)
        self._stability = None  # the last StabilityLimit (auto sub-steps reuse it until invalidated)
        self.stability_model = None
        """None, or a callable returning the model the stability estimate reads in place of
        ``model`` (a batch of worlds whose springs are stored once and stepped outside this
        simulator hands a stand-in holding every world's springs)."""
        self._checked_dt = None  # the step size last compared with the limit

        self.state = model.state()
        self._check_finite_host()
        d = self.device
        self._q_prev = wp.zeros_like(self.state.positions)
        self._time = wp.zeros(1, dtype=float, device=d)
        self._scratch_float = wp.zeros(1, dtype=float, device=d)
        self._first_bad = wp.full(1, self.system.count, dtype=int, device=d)  # kept at count: nothing bad
        self._energy = None  # the energy balance (warpsim.core.energy), started at the first step
        self._energy_step: float | None = None  # the step its runaway threshold was set for
        self._last_h = None
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
            from .rollout import Rollout

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
        self.notify_changed("forces")

    def notify_changed(self, what: str) -> None:
        """Announce an edit from outside (``warpsim.core.solver.CHANGES``): "forces" (the force
        list changed: the integrator re-allocates its buffers, once, here), "colliders" or
        "parameters" (the stability limit is taken again), "state" (the energy balance takes its
        reference again at the next step, and an integrator with a memory of the steps before, ws.VBD's
        adaptive guess, forgets it: ``forget_history``)."""
        what = check_change(what, type(self).__name__)
        if what == "forces":
            self.integrator.reset()  # prepare() is idempotent per system: force a re-allocation
            self.integrator.prepare(self.system)
        if what == "state":
            self.restart_energy()
            forget = getattr(self.integrator, "forget_history", None)  # ws.VBD: its guess's last acceleration
            if forget is not None:
                forget()
        else:
            self.invalidate_stability()

    # ------------------------------------------------------------------ stability
    def stability(self, positions=None, iterations: int = stab.POWER_ITERATIONS) -> stab.StabilityLimit:
        """The largest stable step and what sets it (``ws.StabilityLimit``: limiting spring or
        collider, its k and m, per-spring and per-particle limits), from the model's springs,
        masses, damping, linear drag and penalty colliders linearised about ``positions`` (None:
        the current state) with this integrator's stability region; see
        ``warpsim.core.stability`` for the bound's assumptions."""
        q = self.state.positions if positions is None else positions
        velocities = self.state.velocities.numpy() if positions is None else None  # else the model's initial ones
        model = self.model if self.stability_model is None else self.stability_model()
        limit = stab.particle_limits(model, q, self.integrator, self.forces, self.colliders, iterations=iterations,
                                     velocities=velocities)[0]
        self._stability = stab.with_force_limits(limit, self.forces, q, self.integrator)
        return self._stability

    def stable_dt(self) -> float:
        """Largest stable step [s] of this model with its integrator (inf: unrestricted, e.g.
        implicit Euler; 0.0: no step is stable, e.g. undamped springs with explicit Euler)."""
        return self.stability().dt

    def invalidate_stability(self) -> None:
        """Forget the cached limit (after changing stiffness, masses, forces or colliders in place);
        the energy balance takes its reference again at the next step (the energy changed by hand)."""
        self._stability = None
        self._checked_dt = None
        self._energy = None

    def auto_substeps(self, frame_dt: float, safety: float = stab.AUTO_SAFETY, minimum: int = 1) -> int:
        """Sub-steps for a frame of ``frame_dt`` [s] keeping every step <= ``safety`` x the
        stability limit, at least ``minimum``. The limit is computed once about the model's initial
        positions (so a resumed or re-run simulation picks the same count) and cached until
        ``invalidate_stability``."""
        if self._stability is None:
            self.stability(positions=self.model.particle_q)
        return self._stability.substeps_for(frame_dt, safety, minimum)

    def _warn_if_unstable(self, h: float) -> None:
        self._checked_dt = h
        if self.adaptive or wp.get_device(self.device).is_capturing:
            return
        limit = self._stability if self._stability is not None else self.stability()
        if limit.exceeded_by(h):
            import warnings

            warnings.warn(limit.warning(h), stab.StabilityWarning, stacklevel=3)

    def step(self, dt: float) -> int:
        """Advance by ``dt`` [s]; returns the number of sub-steps taken."""
        dt = check_dt(dt)
        n = self._substeps_for(dt)
        h = dt / n
        if self._energy is None and self.check_every and self.rollout is None and \
                not wp.get_device(self.device).is_capturing:
            self._start_energy(h)
        self._last_h = h
        if self.warn_unstable and h != self._checked_dt:
            self._warn_if_unstable(h)
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
                f"{x} and velocity {v} (speed bound {self.max_speed:g} m/s). {self._energy_remedy(speed=True)}",
                step=self.step_count, time=self.time, particle=bad,
            )

    # ------------------------------------------------------------------ energy balance
    def _start_energy(self, h: float) -> None:
        from .energy import EnergyBalance, gravity_of

        st = self.state
        self._energy_step = None  # a new balance takes its runaway threshold at its first check
        self._energy = EnergyBalance(self.model, self.forces, self.colliders, gravity_of(self.forces),
                                     synchronise=stab.synchronised_energy(self.integrator),
                                     springs=None if self.stability_model is None else self.stability_model())
        self._energy.start(st, h, time=self._time)

    def restart_energy(self) -> None:
        """Take the energy balance's reference again at the next step (after editing the state,
        restoring a checkpoint or changing parameters in place)."""
        self._energy = None

    @property
    def energy_gain(self) -> float:
        """Largest energy gain so far beyond the work of driving forces, relative to the run's
        energy scale (``warpsim.core.energy.EnergyBalance.gains``: the figure the blow-up message gives
        and a sweep's ``energy_gain`` column for the same world; 0.0 before the first frame check)."""
        return 0.0 if self._energy is None else float(self._energy.gains()[0])

    def check_frame(self, frame_dt: float) -> None:
        """End-of-frame energy balance (call once per frame of ``frame_dt`` [s]; ``run`` and the
        scenes do; skipped when ``check_every`` is 0): raise SimulationError when energy beyond the
        work of driving forces has appeared (more than ``warpsim.core.energy.MARGIN`` of the run's
        energy scale) or the energy is non-finite, naming the fastest particle and a remedy that
        fits the cause. Contact, drags and zero damping never trip it. Reads back one int."""
        if not self.check_every or self.rollout is not None or self._energy is None or \
                wp.get_device(self.device).is_capturing:
            return
        eb, st = self._energy, self.state
        h = self._last_h or frame_dt
        if self._energy_step != h:  # the threshold of K + U's growth depends on the step against the limit
            limit = self._stability if self._stability is not None else self.stability(positions=self.model.particle_q)
            eb.set_limits(h, limit.dt)
            self._energy_step = h
        eb.update(st, h, frame_dt, time=self._time)
        if int(eb.unstable_frame.numpy()[0]) < 0:
            return
        v = st.velocities.numpy()
        speed = np.where(self.system.inv_mass.numpy() > 0, np.linalg.norm(v, axis=1), -1.0)
        speed = np.where(np.isfinite(speed), speed, np.inf)
        bad = int(np.argmax(speed))
        gain, modified = float(eb.gains()[0]), float(eb.modified_gains()[0])  # gain: energy_gain's one figure
        grew = (f"energy grew by {_ratio(gain)} of the run's energy scale beyond the work of its driving forces"
                if modified > eb.margin and modified >= gain else
                f"its kinetic and elastic energy grew to {_ratio(gain)} its energy scale")
        raise SimulationError(
            f"unstable at step {self.step_count} (t = {self.time:.6g} s): {grew}; particle {bad} moves at "
            f"{float(speed[bad]):.4g} m/s. {self._energy_remedy()}", step=self.step_count, time=self.time,
            particle=bad)

    def _energy_remedy(self, speed: bool = False) -> str:
        """Why energy appeared and what to do, by cause: the step above its limit, the lecture's
        seed collisions, the integrator itself (``Integrator.energy_cause``: iterations stopped far from
        converged), or (with the step inside its limit) a force or collider; ``speed``: the
        speed bound tripped (perhaps a fast but sound run)."""
        h = self._last_h
        limit = self._stability if self._stability is not None else self.stability(positions=self.model.particle_q)
        if h is None or limit.exceeded_by(h):
            where = "" if h is None else (f"Cause: a step of {h:.4g} s is above the stability limit of {limit.dt:.4g} s "
                                          f"set by {limit.who()}. ")
            return f"{where}Remedy: {REMEDY}."
        seed = [c for c in self.colliders if getattr(c, "mode_name", None) == "seed"]
        if seed:
            return (f"Cause: {type(seed[0]).__name__} uses mode='seed' (the lecture's mirror), which gains energy at "
                    "large steps. Remedy: mode='reflect' (resolved at the time of impact), or a smaller dt.")
        if speed:
            return (f"Cause: not the step (within its stability limit of {limit.dt:.4g} s). Remedy: if such speeds "
                    f"are expected, raise max_speed (now {self.max_speed:g} m/s); else look for a force or collider "
                    f"that adds energy.")
        cause = getattr(self.integrator, "energy_cause", None)  # an integrator of one's own may lack it
        own = None if h is None or cause is None else cause(h)
        if own:
            return own
        driving = sorted({type(f).__name__ for f in self.forces
                          if getattr(f, "energy_role", "driving") == "driving" and not _idle(f)})
        step = "" if h is None else f"the step of {h:.4g} s is within its stability limit of {limit.dt:.4g} s, so "
        what = f"forces {', '.join(driving)}" if driving else "the colliders or an external edit of the state"
        return (f"Cause: {step}the energy came from elsewhere: check {what} (coefficients, moving shapes). Remedy: "
                "fix the input that adds energy; a smaller step will not help.")

    def frame(self, frame_dt: float = 1.0 / 60.0, steps: int = 1) -> None:
        """Advance one frame of ``frame_dt`` [s] in ``steps`` equal ``step`` calls, then the
        frame's energy balance (``check_frame``)."""
        frame_dt, steps = frame_steps(frame_dt, steps, type(self).__name__)
        for _ in range(steps):
            self.step(frame_dt / steps)
        self.check_frame(frame_dt)

    def run(self, frames: int, frame_dt: float = 1.0 / 60.0, substeps=1, callback=None, writer=None):
        """Simulate ``frames`` frames of ``frame_dt`` [s], each split into ``substeps`` steps
        (``"auto"``: as many as keep each step within half the stability limit, see ``auto_substeps``).

        Frame 0 is the initial state. After each frame ``callback(frame, sim)`` is called and
        ``writer.write(frame, state)`` streams it. A blow-up raises SimulationError with ``frame``
        set; frames already handed to the writer stay written."""
        frame_dt = check_dt(frame_dt)
        if substeps == "auto":
            substeps = self.auto_substeps(frame_dt)
        substeps = checks.count(substeps, "run substeps", fix="give steps per frame, e.g. 1, or 'auto'")
        frames = checks.count(frames, "run frames", minimum=0, fix="give the number of frames, e.g. 120")
        self._run_frames(frames, frame_dt, substeps, callback, writer)

    def _run_frames(self, frames: int, frame_dt: float, substeps: int, callback, writer) -> None:
        """``run``'s loop over checked arguments (``ClothSimulator.run`` too): frame 0 to the writer,
        then each frame advanced by ``frame``, its fracture report, callback and write."""
        if writer is not None:
            writer.write(0, self.state)
        for frame in range(1, int(frames) + 1):
            try:
                self.frame(frame_dt, substeps)
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
