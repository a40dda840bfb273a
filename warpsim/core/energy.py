"""The blow-up check as an energy balance: energy that appears from nowhere.

Per world, once per frame (``kernels/energy.py``, fixed-order sums, one read-back of an int per
world):

    E = kinetic + gravity + elastic (the model's springs)                         [J]
    W = work of the driving forces so far (trapezoid rule over each frame)        [J]
    gain = (E - E_0 - W) / (scale + sum |W| + allowance)                            relative

``scale`` is the world's energy scale: its initial kinetic and elastic energy plus the potential
energy of its particles above the lowest floor under them (or above its lowest particle), so a
dropped ball's scale is m g h; or, when larger, that initial kinetic and elastic energy plus the most
gravity energy released since frame 0, so a structure that hangs from pins with no floor under it (the
``springs`` chain starts horizontal: its lowest particle is as high as the rest) is judged against the
energy its fall has put into motion. Measured (issue 49): the chain at damping 0 had a scale of
0.0044 J (the 1 mm floor) while its swing moved 2.7 J, so K + U's ordinary 0.006 J swing read 2.16x
at frame 42 (7 mJ at --fps 24: 2.98x at frame 12); against the released energy both read below 0.005.
``allowance`` is the energy moving colliders can hand the world (2 M v_s^2 per
frame, v_s the shape's surface speed bound). A world whose gain exceeds ``margin`` (``MARGIN``), whose
plain energy K + U grew past its runaway threshold, or whose energy is non-finite, is unstable from
that frame; :meth:`EnergyBalance.gains` (the sweep table's ``energy_gain``, ``Simulator.energy_gain``,
the figure of the blow-up message) is the largest gain up to that frame, or K + U's growth where that
tripped the check, ``inf`` when non-finite: unstable exactly when it passes ``margin``.

What is counted where (``Force.energy_role``): ``"potential"`` forces (gravity, the model's springs)
are inside E; ``"dissipative"`` ones (still-air drag, the springs' dampers) only remove energy and
are not tracked; every other force is ``"driving"`` (wind, constant forces, magnets, user fields,
the mouse's drag spring, strands' own forces) and its work enters W. Contact resolved at the time of
impact, zero damping and drags therefore raise no alarm, while a step above the stability limit
grows the energy of its stiffest mode geometrically and trips the check within a frame or two,
even where a box of walls stops the velocities (the springs' strain keeps growing).

For semi-implicit Euler E is the method's modified energy K + U + (dt / 2) v . f (``kernels/energy.py``),
which it conserves exactly for springs and gravity at every stable step: a ballistic flight or an
undamped spring at 0.95x its limit reads as the no-gain it is (K + U alone would swing 5x there).
"""

from __future__ import annotations

import numpy as np
import warp as wp

from ..kernels import energy as K
from .reduction import FixedOrderReduction

RUNAWAY = 1000.0
"""The most the plain energy K + U may grow beyond the work of driving forces, relative to the
energy scale, before it counts as a blow-up whatever the modified energy says (the cap of
:func:`runaway_threshold`)."""


def runaway_threshold(step: float, limit: float) -> float:
    """Relative growth of K + U that counts as a blow-up for steps of ``step`` [s] against the
    stability limit ``limit`` [s]. Inside the limit (r = step / limit < 1) K + U of a stable run swings
    by up to 1 / (1 - r^2) times the stiffest mode's energy (the semi-implicit Euler map of an
    undamped spring, omega dt / 2 = r): the threshold is twice that, at least 2, at most ``RUNAWAY``.
    Past the limit the stiffest mode grows, slowly just past it (its modified energy stays put while
    K + U climbs; explicit Euler and RK2, whose limit damping sets, amplify by 1 + O(zeta^2) a step),
    so any growth beyond ``PAST_LIMIT`` counts: the run was told before its first step that its
    step is past the limit, and growth there is the unstable mode, not a swing."""
    if not (limit > 0.0) or step > limit * (1.0 + 1.0e-6):
        return PAST_LIMIT
    r = step / limit if np.isfinite(limit) else 0.0
    return float(min(RUNAWAY, max(2.0, 2.0 / max(1.0 - r * r, 1.0e-12))))

MARGIN = 0.25
"""Relative energy gain (beyond the work of driving forces) that counts as a blow-up. Measured
(``tests/test_energy.py``): the teapot at damping 0 over 600 frames, dragged into the walls, stays
below 0.05; a step 1.1x above the limit passes 0.5 within two frames of the first growth."""

PAST_LIMIT = 0.01
"""Relative growth of K + U that counts as a blow-up when the step is past its stability limit
(:func:`runaway_threshold`). Measured (``benchmarks/check_scenes.py --device cpu --small --kinds
blowup``): at 1.2x the limit springs under explicit Euler and RK2 were flagged at frames 69 and 152
of 600, the frames their unchecked twins had gained 1 % (at MARGIN alone, explicit Euler was flagged
near frame 211 and RK2 was not flagged within 120 frames)."""

__all__ = ["MARGIN", "PAST_LIMIT", "RUNAWAY", "EnergyBalance", "energy_role", "gravity_of", "runaway_threshold"]


def energy_role(force) -> str:
    """``"potential"``, ``"dissipative"`` or ``"driving"`` (see the module docstring)."""
    return getattr(force, "energy_role", "driving")


def gravity_of(forces, world_count: int = 1) -> np.ndarray:
    """Gravity [m/s^2] per world, (world_count, 3): the sum of the ``g`` of every ``"potential"`` force
    that has one (``ws.Gravity``; a batch's per-world gravity)."""
    g = np.zeros((max(int(world_count), 1), 3))
    for f in forces or ():
        if energy_role(f) == "potential" and hasattr(f, "g"):
            g = g + np.asarray(f.g, dtype=np.float64).reshape(-1, 3)
    return g


def _floor_heights(colliders, up) -> list:
    """Heights [m] along ``up`` of the static planes facing up (floors), from ``Planes`` colliders."""
    out = []
    for c in colliders:
        normals, offsets = getattr(c, "normals", None), getattr(c, "offsets", None)
        if normals is None or offsets is None or getattr(c, "motion", None) is not None:
            continue
        for n, o in zip(np.asarray(normals, float).reshape(-1, 3), np.atleast_1d(np.asarray(offsets, float))):
            facing = float(np.dot(n, up))
            if facing > 0.7:
                out.append(float(o) / facing)
    return out


class EnergyBalance:
    """Per-world energy balance of a particle system (module docstring).

    Args:
        model: the model (particle arrays; ``world_count`` and ``particle_world`` for batches; worlds
            are contiguous blocks of ``particle_count / world_count`` particles and
            ``spring_count / world_count`` springs).
        forces: the simulator's forces (their ``energy_role`` decides what is counted where).
        colliders: its colliders (floors set the potential's reference; moving ones an allowance).
        gravity: (world_count, 3) [m/s^2] per world.
        synchronise: True for semi-implicit Euler (kinetic energy from the synchronised velocity).
        springs: the model whose springs hold the elastic energy (default ``model``).
        shared: a batch's ``SharedSprings`` (``kernels/world_step.py``: springs stored once for every
            world) read in place of ``springs``.
        per_world: sum each world in one thread even when there is one (a sweep: a world's sums, and
            so its table row, must not depend on how many worlds share its batch); False lets a lone
            simulation use the parallel fixed-order reduction.
        margin: relative gain that counts as unstable.
    """

    def __init__(self, model, forces, colliders, gravity, *, synchronise=True, springs=None, shared=None,
                 per_world=False, margin=MARGIN):
        self.model = model
        self.device = model.device
        self.forces = list(forces)
        self.colliders = list(colliders)
        self.driving = [f for f in self.forces if energy_role(f) == "driving"]
        self.synchronise = bool(synchronise)
        self.springs = model if springs is None else springs
        self.shared = shared
        self.margin = float(margin)
        n = int(getattr(model, "world_count", 1) or 1)
        self.world_count = n
        d = self.device
        count = model.particle_count
        self.gravity = np.asarray(gravity, dtype=np.float64).reshape(-1, 3)
        if len(self.gravity) == 1 and n > 1:
            self.gravity = np.tile(self.gravity, (n, 1))
        self.world_gravity = wp.array(self.gravity.astype(np.float32), dtype=wp.vec3, device=d)
        self.q_start = wp.zeros(count, dtype=wp.vec3, device=d)
        size = count if self.driving else 0
        self.drive = [wp.zeros(size, dtype=wp.vec3, device=d), wp.zeros(size, dtype=wp.vec3, device=d)]
        self._zeros = wp.zeros(count, dtype=wp.vec3, device=d)
        self._no_int = wp.zeros(0, dtype=int, device=d)
        self._zero_time = wp.zeros(1, dtype=float, device=d)  # the clock of driving forces when none is given
        self.sums = wp.zeros((n, 6), dtype=float, device=d)
        self.half_dt = wp.zeros(n, dtype=float, device=d)  # each world's dt / 2 [s] (0 unless synchronised)
        self._half_dt_host = np.zeros(n, dtype=np.float32)
        lone = n == 1 and shared is None and not per_world
        self._reduction = FixedOrderReduction(6, first_max_column=4, device=d) if lone else None
        self.reference = wp.zeros((n, 3), dtype=float, device=d)  # modified, plain and gravity energy at frame 0
        self.scale = wp.ones(n, dtype=float, device=d)
        self.motion = wp.zeros(n, dtype=float, device=d)  # frame 0's kinetic and elastic energy [J]
        self.released = wp.zeros(n, dtype=float, device=d)  # the most gravity energy released since frame 0 [J]
        self.work = wp.zeros(n, dtype=float, device=d)
        self.abs_work = wp.zeros(n, dtype=float, device=d)
        self.allowance = wp.zeros(n, dtype=float, device=d)
        self.runaway = wp.full(n, RUNAWAY, dtype=float, device=d)
        self.energy = wp.zeros(n, dtype=float, device=d)
        self.gain = wp.full(n, -1.0e30, dtype=float, device=d)
        self.plain_gain = wp.full(n, -1.0e30, dtype=float, device=d)
        self.unstable_frame = wp.full(n, -1, dtype=int, device=d)
        self._allowance_host = np.zeros(n)
        self._world_mass = None
        self.frame_counter = wp.zeros(1, dtype=int, device=d)
        self.frame = 0

    # ------------------------------------------------------------------ sums
    def _eval_driving(self, state, time, out) -> None:
        if not self.driving:
            return
        out.zero_()
        for f in self.driving:
            f.eval(state.positions, state.velocities, self._zero_time if time is None else time, 0.0, out)

    def _set_steps(self, dt) -> None:
        """Each world's dt / 2 from ``dt`` [s] (a number, or one per world); copied to the device only
        when it changes (never inside a captured frame, whose step stays the same)."""
        half = 0.5 * np.broadcast_to(np.asarray(dt, dtype=np.float64), (self.world_count,)) if self.synchronise \
            else np.zeros(self.world_count)
        half = half.astype(np.float32)
        if not np.array_equal(half, self._half_dt_host):
            self._half_dt_host = half
            self.half_dt.assign(half)

    def _launch_sums(self, state, dt) -> wp.array:
        m, s, d, n = self.model, self.springs, self.device, self.world_count
        self._set_steps(dt)
        d0, d1 = (self.drive if self.driving else (self._zeros, self._zeros))
        inputs = K.EnergyInputs()
        inputs.q, inputs.q_frame_start, inputs.qd = state.positions, self.q_start, state.velocities
        inputs.drive_start, inputs.drive_end = d0, d1
        inputs.mass, inputs.inv_mass, inputs.world_gravity = m.particle_mass, m.particle_inv_mass, self.world_gravity
        inputs.half_dt = self.half_dt
        common = [inputs]
        if self.shared is not None:
            wp.launch(K.world_energy_sums_shared, n, inputs=[*common, m.particle_count // n, self.shared],
                      outputs=[self.sums], device=d)
            return self.sums
        broken = getattr(s, "spring_broken", None)
        broken = self._no_int if broken is None or s.spring_count == 0 else broken
        springs = [s.spring_indices, s.spring_rest_length, s.spring_stiffness, broken]
        if self._reduction is not None:
            wp.launch(K.energy_sums_strided, self._reduction.slots,
                      inputs=[*common, *springs, int(s.spring_count)], outputs=[self._reduction.partials], device=d)
            return self._reduction.finish().reshape((1, 6))
        wp.launch(K.world_energy_sums, n, inputs=[*common, m.particle_count // n, *springs, int(s.spring_count) // n],
                  outputs=[self.sums], device=d)
        return self.sums

    # ------------------------------------------------------------------ public
    def start(self, state, dt, time=None) -> None:
        """Take the reference energy and scale from ``state`` (frame 0) for steps of ``dt`` [s] (a
        number, or one per world)."""
        m = self.model
        wp.copy(self.q_start, state.positions)
        self._eval_driving(state, time, self.drive[0])
        sums = self._launch_sums(state, dt).numpy().astype(np.float64)
        n = self.world_count
        # host work is per world row (slices, row sums, minima), so a world's scale does not depend on
        # which other worlds share its batch (a sweep split over devices writes the same table)
        q = state.positions.numpy().astype(np.float64)
        moving = m.particle_inv_mass.numpy() > 0
        mass = np.where(moving, m.particle_mass.numpy().astype(np.float64), 0.0)
        P = len(q) // n
        q, mass, moving = q.reshape(n, P, 3), mass.reshape(n, P), moving.reshape(n, P)
        total_mass = mass.sum(axis=1)
        self._world_mass = total_mass
        g_norm = np.linalg.norm(self.gravity, axis=1)
        up = -self.gravity / np.where(g_norm > 0, g_norm, 1.0)[:, None]
        heights = (q * up[:, None, :]).sum(axis=2)  # (n, P) [m] along each world's up
        low = np.where(moving, heights, np.inf).min(axis=1)
        ref = low.copy()
        for direction in np.unique(up, axis=0):  # floors (static planes facing up) under the lowest particle
            floors = np.asarray(_floor_heights(self.colliders, direction), dtype=np.float64)
            rows = np.all(up == direction, axis=1)
            if len(floors):
                under = np.where(floors[None, :] <= low[rows, None] + 1e-9, floors[None, :], -np.inf).max(axis=1)
                ref[rows] = np.where(np.isfinite(under), under, low[rows])
        # sums[:, 3] = sum m |g| h: the potential above the reference is that minus M |g| ref
        potential = np.where((g_norm > 0) & moving.any(axis=1) & np.isfinite(ref),
                             sums[:, 3] - total_mass * g_norm * np.where(np.isfinite(ref), ref, 0.0), 0.0)
        kinetic_elastic = sums[:, 0] - sums[:, 3]
        # a floor of 1 mm of the world's weight (or 1 nJ) keeps a ball at rest on the floor judgeable
        floor = total_mass * np.maximum(g_norm, 1e-3) * 1e-3 + 1e-9
        # semi-implicit Euler's samples from rest lie on a parabola g dt^2 / 8 above the release point
        step = np.broadcast_to(np.asarray(dt, dtype=np.float64), (n,))
        offset = total_mass * g_norm**2 * step**2 / 8.0 if self.synchronise else 0.0
        scale = np.maximum(kinetic_elastic + np.maximum(potential, 0.0) + offset, floor)
        self.scale.assign(scale.astype(np.float32))
        self.motion.assign(np.maximum(kinetic_elastic + offset, 0.0).astype(np.float32))
        self.released.zero_()
        self.reference.assign(np.stack([sums[:, 0] + sums[:, 1], sums[:, 0], sums[:, 3]], axis=1).astype(np.float32))
        self.work.zero_()
        self.abs_work.zero_()
        self.allowance.zero_()
        self._allowance_host[:] = 0.0
        self.gain.fill_(-1.0e30)
        self.plain_gain.fill_(-1.0e30)
        self.unstable_frame.fill_(-1)
        self.frame_counter.zero_()
        self.frame = 0

    def update(self, state, dt, frame_dt, time=None, world_bad=None) -> None:
        """Fold one finished frame (``dt``: its step [s], a number or one per world; ``frame_dt`` [s];
        ``time``: the simulation's device clock, (1,) [s], that driving forces read) into the balance; launches
        only (no read-back, no allocation), so a sweep can capture it in its frame graph (moving
        colliders' allowance is then left out: it is taken on the host)."""
        self.frame += 1
        d = self.device
        wp.launch(K.count_frame, 1, inputs=[self.frame_counter], device=d)
        self._eval_driving(state, time, self.drive[1])
        sums = self._launch_sums(state, dt)
        if not wp.get_device(d).is_capturing:
            speed = max((getattr(c, "frame_surface_speed", lambda: 0.0)() for c in self.colliders), default=0.0)
            if speed > 0.0 and self._world_mass is not None:
                self._allowance_host += 2.0 * self._world_mass * speed * speed
                self.allowance.assign(self._allowance_host.astype(np.float32))
        wp.launch(K.judge_worlds, self.world_count,
                  inputs=[sums, self.frame_counter, self.margin, self.runaway,
                          self._no_int if world_bad is None else world_bad,
                          self.reference, self.scale, self.motion, self.work, self.abs_work, self.released,
                          self.allowance],
                  outputs=[self.energy, self.gain, self.plain_gain, self.unstable_frame], device=d)
        wp.copy(self.q_start, state.positions)
        if self.driving:
            wp.copy(self.drive[0], self.drive[1])

    def set_limits(self, step: float, limits) -> None:
        """Runaway thresholds per world from the step [s] and each world's stability limit [s]
        (:func:`runaway_threshold`)."""
        limits = np.atleast_1d(np.asarray(limits, dtype=np.float64))
        steps = np.broadcast_to(np.asarray(step, dtype=np.float64), limits.shape)  # a number, or one per world
        values = [runaway_threshold(float(h), float(lim)) for h, lim in zip(steps, limits)]
        if len(values) == 1 and self.world_count > 1:
            values = values * self.world_count
        self.runaway.assign(np.asarray(values, dtype=np.float32))

    def plain_gains(self) -> np.ndarray:
        """Largest growth of the plain energy K + U so far per world, relative (the runaway guard)."""
        return np.maximum(self.plain_gain.numpy().astype(np.float64), 0.0) if self.frame else np.zeros(self.world_count)

    def modified_gains(self) -> np.ndarray:
        """Largest gain of the balanced energy (semi-implicit Euler's modified energy) so far per world,
        relative (0 before any frame)."""
        return np.maximum(self.gain.numpy().astype(np.float64), 0.0) if self.frame else np.zeros(self.world_count)

    def gains(self) -> np.ndarray:
        """The energy gain per world, relative to its energy scale (0 before any frame): the largest gain
        of the balanced energy, or the plain energy's growth where that passed its runaway threshold
        (past the stability limit K + U grows while the modified energy stays put), up to the frame the
        world was flagged at; ``inf`` for a non-finite energy. One definition for the sweep table's
        ``energy_gain``, ``Simulator.energy_gain`` and the blow-up message: a world is unstable exactly
        when this passes ``margin`` (every runaway threshold is at least ``MARGIN``)."""
        if not self.frame:
            return np.zeros(self.world_count)
        gain = self.modified_gains()
        plain = self.plain_gains()
        runaway = self.runaway.numpy().astype(np.float64)
        out = np.where(plain > runaway, np.maximum(gain, plain), gain)
        return np.where(out >= 1.0e29, np.inf, out)

    def unstable(self) -> np.ndarray:
        """Whether each world was flagged (its gain passed ``margin``, or its energy became non-finite)."""
        return self.unstable_frame.numpy() >= 0
