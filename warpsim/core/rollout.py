"""Rollout: the differentiable mode of ``ws.Simulator`` (``differentiable=True``), beside the
Simulator that builds it (``warpsim.diff`` is its public face, with the float64 references).

Each step reads state k and writes state k + 1 (out of place; integrating in place would
overwrite the values the backward pass needs), and every launch is recorded on ``tape``:

    forces f_k = f(q_k, v_k, t_k)            (the forces' own kernels, with adjoints)
    integrate (q_k, v_k, f_k) -> stage 0     (explicit / semi-implicit Euler, or the cloth's
                                              fused semi-implicit update)
    contacts  stage j -> stage j + 1 -> ... -> state k + 1   (one launch per plane / sphere)

Forward results equal the ordinary mode's bit for bit (same kernels or the same funcs, same
order of operations; tested on the CPU). One exception by design: on CUDA the ordinary cloth
semi-implicit path defaults to the "gather" kernel (sums each particle's springs in another
order), so there the two agree to float rounding; ``ClothSemiImplicitEuler(mode="scatter")``
is the bit-for-bit reference.

Memory: one State (positions, velocities, forces) per step plus one buffer pair per contact
launch, each with its gradient: 2 x 12 bytes x (3 + 2 L) per particle and step (L contact
launches); a 1,000-step rollout of a 64 x 64 cloth holds about 0.3 GB without colliders, 0.47 GB
with a floor (benchmarks/bench_differentiable.py), so no checkpointing is needed at that size.

What differentiates (derivatives of the branch taken, exactly as the forward computes it):
gravity, constant forces, wind, drag, magnets, damped springs; explicit and semi-implicit
Euler (and the cloth's fused semi-implicit path); planes and static spheres/capsules with
discrete detection. Contact is differentiated through the projection itself (reflect /
project modes: x' = x + (1 + e) h n or x + h n, v_n' = -e v_n, Coulomb friction) or the penalty
impulse (penalty mode). These are piecewise smooth: the gradient is that of the active piece
and is not defined where the piece changes (h = 0 at touch-down, v_n = 0, the stick/slip limit
of friction, |v_t| = 0); a change of the step in which contact starts moves the result by a
jump that the gradient does not see.

Parameters with gradients after ``backward``: ``states[0].positions.grad`` /
``states[0].velocities.grad`` (initial state), ``model.spring_stiffness.grad``,
``model.spring_damping.grad``, ``model.spring_rest_length.grad`` (per spring),
``mass_gradient()`` (per particle, through m and 1/m), magnets' ``strengths`` / ``centers``, and
``coefficient_gradients(force)`` for gravity g, a constant force, drag (linear, quadratic) and
wind (coefficient): those forces are linear in their coefficients, so
dL/dc = sum_k <F(q_k, v_k, t_k; c = unit), dL/df_k> exactly, from the adjoints of each step's
total force.
"""

from __future__ import annotations

import copy
from typing import Any

import numpy as np
import warp as wp

from ..kernels import autodiff as KD
from .forces import ConstantForce, Drag, Gravity, Magnets, Springs, Wind
from .integrators import ExplicitEuler, SemiImplicitEuler
from .launch import recording
from .model import State

DIFFERENTIABLE_FORCES = (Gravity, ConstantForce, Wind, Drag, Magnets, Springs)
"""Force types a differentiable run accepts."""

# force type -> its coefficients, each (name, attribute, unit values): the force is linear in them
_LINEAR: dict[type, list[tuple[str, str, list[Any]]]] = {
    Gravity: [("g", "g", [(1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)])],
    ConstantForce: [("force", "force", [(1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)])],
    Drag: [("linear", "linear", [1.0]), ("quadratic", "quadratic", [1.0])],
    Wind: [("coefficient", "coefficient", [1.0])],
}

# ClothSemiImplicitEuler.name: matched by name, since warpsim.cloth.solver imports the Simulator, which
# imports this module (tests/test_import_graph.py checks the two agree)
CLOTH_SEMI_IMPLICIT = "cloth_semi_implicit_euler"

_FLUIDS = ("ParticleFluid", "FlipLiquid", "Smoke", "LevelSetLiquid", "LevelSet", "MacGrid", "PressureSolver")


def _refuse(what: str, why: str, fix: str):
    raise ValueError(f"differentiable=True: {what} {why}; {fix}")


def check_differentiable(sim) -> None:
    """Raise ValueError, naming the part and a fix, when ``sim`` cannot run differentiably:
    adaptive sub-stepping, implicit Euler (its Newton / CG loop is not differentiated), RK2/RK4,
    user force fields, continuous collision detection, moving colliders, meshes, quads,
    particle-particle collisions, breakable springs, and fluid solvers."""
    name = type(sim).__name__
    if name in _FLUIDS or not hasattr(sim, "integrator"):
        _refuse(f"{name}", "is not differentiable (fluid solvers project pressure iteratively and rebuild "
                "neighbour grids; no backward pass exists for them)", "use ws.Simulator on a particle/spring model")
    if getattr(sim, "adaptive", False):
        _refuse("adaptive sub-stepping", "picks the number of sub-steps from the state, a choice with no derivative",
                "use adaptive=False and fixed steps")
    integ = sim.integrator
    if not (isinstance(integ, (ExplicitEuler, SemiImplicitEuler)) or integ.name == CLOTH_SEMI_IMPLICIT):
        if "implicit_euler" in integ.name:
            _refuse(f"integrator {integ.name!r}", "solves each step with a Newton / conjugate-gradient loop that "
                    "is not differentiated", "use integrator='semi_implicit_euler' or 'explicit_euler'")
        _refuse(f"integrator {integ.name!r}", "is not supported in differentiable mode (its stage buffers are "
                "reused in place)", "use integrator='semi_implicit_euler' or 'explicit_euler'")
    for k, f in enumerate(sim.forces):
        if not isinstance(f, DIFFERENTIABLE_FORCES):
            _refuse(f"forces[{k}] ({type(f).__name__})", "has no backward pass (its kernels compile without one)",
                    "use Gravity, ConstantForce, Wind, Drag, Magnets or the model's springs")
    for k, c in enumerate(sim.colliders):
        kind = type(c).__name__
        # the colliders with an out-of-place step (``apply_out``: planes, and spheres and capsules, which
        # may move or detect continuously); their classes are a floor up, in warpsim.bodies
        if hasattr(c, "apply_out"):
            if getattr(c, "continuous", False):
                _refuse(f"colliders[{k}] ({kind})", "uses continuous collision detection, which is not differentiated",
                        f"pass ws.{kind}(..., continuous=False)")
            if getattr(c, "motion", None) is not None:
                _refuse(f"colliders[{k}] ({kind})", "moves (motion=...)", "use a static shape")
            continue
        if kind == "SpringFracture":
            _refuse("breakable springs", "switch springs off at a threshold, a step with no derivative",
                    "build the model without break_strain / break_force")
        _refuse(f"colliders[{k}] ({kind})", "is not differentiable (continuous detection or particle pairs)",
                "use ws.Plane / ws.Box / ws.Planes or ws.Sphere(..., continuous=False)")


class Rollout:
    """The differentiable stepping of one Simulator (created by ``differentiable=True``).

    Attributes:
        tape: the ``wp.Tape`` holding every launch since the last ``reset``.
        states: State per step; ``states[0]`` is the initial state, ``states[k]`` the state after
            k steps (``sim.state`` is ``states[step_count]``); each array has a ``.grad``.
        times: per-step clock arrays [s], shape (1,) each (``times[k]`` is t_k).
        step_count: steps taken since the last ``reset``.
    """

    def __init__(self, sim):
        check_differentiable(sim)
        self.sim = sim
        self.model = model = sim.model
        self.device = sim.device
        self.cloth = sim.integrator.name == CLOTH_SEMI_IMPLICIT
        self.tape = wp.Tape()
        for arr in (model.particle_mass, model.particle_inv_mass, model.spring_rest_length, model.spring_stiffness,
                    model.spring_damping):
            arr.requires_grad = True
        for f in sim.forces:
            if isinstance(f, Magnets):
                f._centers.requires_grad = True
                f._strengths.requires_grad = True
        n = model.particle_count
        self._contact_launches = sum(len(c.normals) if hasattr(c, "normals") else 1 for c in sim.colliders)
        first = State(self._vec(), self._vec(), self._vec())
        wp.copy(first.positions, sim.state.positions)
        wp.copy(first.velocities, sim.state.velocities)
        self.states = [first]
        self.times = [wp.zeros(1, dtype=float, device=self.device)]
        self._stages = []  # per step: [(q, qd)] * contact launches
        self.step_count = 0
        self._scratch = wp.zeros(n, dtype=wp.vec3, device=self.device)
        sim.state = first

    def _vec(self):
        return wp.zeros(self.model.particle_count, dtype=wp.vec3, device=self.device, requires_grad=True)

    def reserve(self, steps: int) -> None:
        """Allocate the buffers of ``steps`` steps now (later rollouts of at most that length
        allocate nothing)."""
        while len(self.states) <= steps:
            self.states.append(State(self._vec(), self._vec(), self._vec()))
            self.times.append(wp.zeros(1, dtype=float, device=self.device))
            self._stages.append([(self._vec(), self._vec()) for _ in range(self._contact_launches)])

    def integrated(self, k: int) -> tuple:
        """(positions, velocities) of step k (1 <= k <= step_count) after integration and before
        the contacts (``states[k]`` itself when there are no colliders), e.g. to interpolate where
        a particle crossed a surface."""
        if not 1 <= k <= self.step_count:
            raise ValueError(f"integrated({k}): steps 1..{self.step_count} exist; give one of them")
        stages = self._stages[k - 1]
        return stages[0] if stages else (self.states[k].positions, self.states[k].velocities)

    # ----------------------------------------------------------------------------------
    def advance(self, h: float) -> None:
        """One step of ``h`` [s] from ``states[step_count]``, recorded on the tape."""
        k = self.step_count
        self.reserve(k + 1)
        s_in, s_out, stages = self.states[k], self.states[k + 1], self._stages[k]
        sim, model, d, n = self.sim, self.model, self.device, self.model.particle_count
        wp.launch(KD.advance_time_out, 1, inputs=[self.times[k], float(h), self.times[k + 1]], device=d)
        t = self.times[k]
        q, qd, f = s_in.positions, s_in.velocities, s_out.forces  # f: the force of the step that led to s_out
        q1, qd1 = stages[0] if stages else (s_out.positions, s_out.velocities)
        with recording(self.tape):
            if self.cloth:
                integ = sim.integrator
                integ.prepare(sim.system)
                f.zero_()
                for force in integ.others:
                    force.eval(q, qd, t, 0.0, f)
                if integ.springs is not None:
                    integ.springs.eval(q, qd, t, 0.0, f)
                wp.launch(KD.integrate_cloth_out, n, inputs=[q, qd, f, model.particle_inv_mass, integ.gravity,
                                                             float(h), q1, qd1], device=d)
            else:
                sim.system.eval_forces(q, qd, t, 0.0, f)
                if isinstance(sim.integrator, SemiImplicitEuler):
                    wp.launch(KD.step_semi_implicit_euler, n,
                              inputs=[q, qd, f, sim.system.inv_mass, float(h), q1, qd1], device=d)
                else:
                    wp.launch(KD.rk_stage, n, inputs=[q, qd, qd, f, sim.system.inv_mass, float(h), q1, qd1], device=d)
            # reflect mode reads the step's force; the cloth solver's own step leaves State.forces unset
            f_step = None if self.cloth else f
            j = 0
            for c in sim.colliders:
                for p in range(len(c.normals) if hasattr(c, "normals") else 1):
                    src = stages[j]
                    dst = stages[j + 1] if j + 1 < len(stages) else (s_out.positions, s_out.velocities)
                    if hasattr(c, "normals"):
                        c.apply_out(model, src[0], src[1], dst[0], dst[1], h, p, q_start=q, forces=f_step)
                    else:
                        c.apply_out(model, src[0], src[1], dst[0], dst[1], h, q_start=q, forces=f_step)
                    j += 1
        self.step_count = k + 1
        sim.state = s_out

    def reset(self, positions=None, velocities=None) -> None:
        """Forget the recorded steps (gradients zeroed) and start again from the model's initial
        state, or from ``positions`` [m] / ``velocities`` [m/s] ((n, 3) arrays) when given."""
        self.tape.reset()
        first = self.states[0]
        for arr, given, default in ((first.positions, positions, self.model.particle_q),
                                    (first.velocities, velocities, self.model.particle_qd)):
            if given is None:
                wp.copy(arr, default)
            else:
                arr.assign(np.asarray(given, dtype=np.float32).reshape(-1, 3))
            arr.grad.zero_()
        self.times[0].zero_()
        self.step_count = 0
        self.sim.state = first
        self.sim.time = 0.0
        self.sim.step_count = 0
        for c in self.sim.colliders:
            if hasattr(c, "set_clock"):
                c.set_clock(0.0)

    def backward(self, loss: wp.array) -> None:
        """Propagate d loss / d (everything recorded); ``loss`` is a (1,) float array computed
        under ``with rollout.tape:`` (e.g. by :meth:`trajectory_loss`). Anything else (None, a
        number, a NumPy array) is refused: Warp would do nothing and say nothing."""
        if not isinstance(loss, wp.array):
            raise TypeError(f"backward needs the loss as a Warp array of shape (1,) recorded on the tape, got "
                            f"{type(loss).__name__}; e.g. loss = rollout.trajectory_loss([target]) then "
                            "rollout.backward(loss)")
        if loss.size != 1 or not getattr(loss, "requires_grad", False):
            raise ValueError(f"backward needs a loss array of one element with requires_grad=True (made under "
                             f"'with rollout.tape:'), got shape {loss.shape}, requires_grad="
                             f"{getattr(loss, 'requires_grad', False)}; e.g. loss = rollout.trajectory_loss([target])")
        self.tape.backward(loss)

    def trajectory_loss(self, targets, weight: float = 1.0, loss=None, steps=None) -> wp.array:
        """Record loss = weight sum_k sum_i |q_k,i - target_k,i|^2 [m^2] over the states
        ``steps`` (default: the last one) against ``targets`` (one (n,) vec3 array per step);
        returns the (1,) loss array (zeroed first; allocated when ``loss`` is None)."""
        from . import checks

        given = steps is not None
        steps = [self.step_count] if steps is None else list(steps)
        if isinstance(targets, wp.array) or (isinstance(targets, np.ndarray) and targets.ndim == 2):
            raise TypeError("trajectory_loss targets is one array; give a list with one (n, 3) target per step, "
                            "e.g. [target]")
        targets = list(targets)
        if len(targets) != len(steps):
            which = f"steps={steps}" if given else f"steps=None means the last step only ({self.step_count})"
            raise ValueError(f"trajectory_loss: {len(targets)} targets for {len(steps)} step(s) ({which}); give one "
                             "target per step and name the step of each with steps=[k1, k2, ...] (step k is "
                             "rollout.states[k])")
        steps = [checks.integer(k, "trajectory_loss step", lo=0, hi=self.step_count,
                                fix=f"steps recorded so far: 0..{self.step_count}") for k in steps]
        weight = checks.finite(weight, "trajectory_loss weight")
        n = self.model.particle_count
        for j, target in enumerate(targets):
            if isinstance(target, wp.array):
                if target.dtype != wp.vec3 or target.shape != (n,) or target.device != self.device:
                    raise ValueError(f"trajectory_loss target {j} is a {target.dtype.__name__} array of shape "
                                     f"{target.shape} on {target.device}; give a vec3 array of shape ({n},) on "
                                     f"{self.device} (one position [m] per particle)")
                continue
            try:
                values = np.asarray(target, dtype=np.float32)
            except (TypeError, ValueError):
                raise TypeError(f"trajectory_loss target {j} is {checks.show(target)}; give an ({n}, 3) array of "
                                "positions [m]") from None
            if values.shape != (n, 3) or not np.isfinite(values).all():
                raise ValueError(f"trajectory_loss target {j} has shape {values.shape}"
                                 f"{'' if np.isfinite(values).all() else ' and non-finite values'}; give ({n}, 3) "
                                 "finite positions [m], one per particle")
            targets[j] = wp.array(values, dtype=wp.vec3, device=self.device)
        if loss is None:
            loss = wp.zeros(1, dtype=float, device=self.device, requires_grad=True)
        elif not isinstance(loss, wp.array) or loss.dtype != wp.float32 or loss.shape != (1,):
            raise ValueError(f"trajectory_loss loss must be a (1,) float32 wp.array or None, got {checks.show(loss)}")
        loss.zero_()
        with recording(self.tape):
            for k, target in zip(steps, targets):
                wp.launch(KD.squared_distance, self.model.particle_count,
                          inputs=[self.states[k].positions, target, float(weight), loss], device=self.device)
        return loss

    # ----------------------------------------------------------------------------------
    def mass_gradient(self) -> np.ndarray:
        """dL/dm per particle [loss/kg], through gravity (m) and every 1/m; pinned particles
        (m = 0) report the direct part only."""
        m = self.model
        out = wp.zeros(m.particle_count, dtype=float, device=self.device)
        wp.launch(KD.mass_gradient, m.particle_count,
                  inputs=[m.particle_mass, m.particle_mass.grad, m.particle_inv_mass.grad, out], device=self.device)
        return out.numpy()

    def coefficient_gradients(self, force) -> dict:
        """Gradient of the loss with respect to ``force``'s coefficients, {name: value}:
        Gravity {"g": (3,)}, ConstantForce {"force": (3,)}, Drag {"linear", "quadratic"},
        Wind {"coefficient"}, Magnets {"strengths": (M,), "centers": (M, 3)}. Call after
        ``backward``."""
        if isinstance(force, Magnets):
            return {"strengths": force._strengths.grad.numpy().copy(), "centers": force._centers.grad.numpy().copy()}
        if force not in self.sim.forces or type(force) not in _LINEAR:
            raise ValueError(f"coefficient_gradients: {type(force).__name__} is not one of this simulator's forces "
                             "with coefficients (Gravity, ConstantForce, Drag, Wind, Magnets)")
        units = [(name, attr, value) for name, attr, values in _LINEAR[type(force)] for value in values]
        out = wp.zeros(len(units), dtype=float, device=self.device)
        for slot, (_, attr, value) in enumerate(units):
            unit = copy.copy(force)
            if isinstance(force, Drag):
                unit.linear = unit.quadratic = 0.0
            setattr(unit, attr, value)
            for k in range(self.step_count):
                s = self.states[k]
                self._scratch.zero_()
                unit.eval(s.positions, s.velocities, self.times[k], 0.0, self._scratch)
                wp.launch(KD.dot_accumulate, self.model.particle_count,
                          inputs=[self._scratch, self.states[k + 1].forces.grad, slot, out], device=self.device)
        values = out.numpy().astype(np.float64)
        result = {}
        for slot, (name, _, _) in enumerate(units):
            result.setdefault(name, []).append(values[slot])
        return {name: (np.array(v) if len(v) > 1 else float(v[0])) for name, v in result.items()}
