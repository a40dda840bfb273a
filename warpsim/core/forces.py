"""Forces acting on particles. Each launches kernels from ``warpsim.kernels.forces``.

A force is bound to a model once (``bind``: validation and device buffers), then evaluated any
number of times without allocating. Forces only accumulate; the caller zeroes ``f_out`` first.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from . import checks
from .builder import check_indices
from .launch import cached_launch, recording_tape
from .model import ensure_spring_adjacency
from ..kernels import forces as K


class Force:
    """Base class. Subclasses implement ``eval`` and, when the force depends on positions or
    velocities, ``eval_jacobian`` (diagonal blocks into ``diag``, couplings as triplets)."""

    energy_role = "driving"
    """How the energy balance counts this force (``warpsim.core.energy``): ``"potential"`` (its
    energy is summed: gravity, springs), ``"dissipative"`` (only removes energy) or ``"driving"``
    (its work is tracked)."""

    def bind(self, model) -> None:
        """Validate against ``model`` and allocate device data (called once by the Simulator)."""
        self.model = model

    def eval(self, q, qd, time, time_offset: float, f_out) -> None:
        raise NotImplementedError

    def jacobian_triplet_count(self) -> int:
        """Number of off-diagonal 3x3 blocks this force writes."""
        return 0

    def eval_jacobian(self, q, qd, time, time_offset, ck, cd, diag, rows, cols, values) -> None:
        """Add ck df/dx + cd df/dv: per-particle blocks into ``diag`` (n,), coupling blocks into
        the triplet slices ``rows``/``cols``/``values`` (length jacobian_triplet_count())."""


class Gravity(Force):
    """Uniform gravity: f = m g, g [m/s^2] (default (0, -9.81, 0))."""

    energy_role = "potential"

    def __init__(self, g=(0.0, -9.81, 0.0)):
        self.g = checks.vec3(g, "Gravity g")

    def eval(self, q, qd, time, time_offset, f_out) -> None:
        m = self.model
        wp.launch(K.eval_gravity, m.particle_count, inputs=[m.particle_mass, wp.vec3(self.g), f_out], device=m.device)


class ConstantForce(Force):
    """A constant force [N] on chosen particles (None: every particle)."""

    def __init__(self, force, particles=None):
        self.force = checks.vec3(force, "ConstantForce force")
        self.particles = particles

    def bind(self, model) -> None:
        super().bind(model)
        n = model.particle_count
        idx = np.arange(n) if self.particles is None else check_indices(self.particles, n, "ConstantForce")
        self._indices = wp.array(idx.astype(np.int32), dtype=int, device=model.device)

    def eval(self, q, qd, time, time_offset, f_out) -> None:
        wp.launch(
            K.eval_constant_force, self._indices.shape[0], inputs=[self._indices, wp.vec3(self.force), f_out],
            device=self.model.device,
        )


class Wind(Force):
    """Wind that varies in time: f = c (w(t) - v) with air velocity
    w(t) = speed (1 + gust_amplitude gust(t)) dir(t).

    direction: unit vector (normalised here); speed [m/s]; gust(t) in [-1, 1] is a sum of three
    incommensurate sines at ``gust_frequency`` [Hz] with phases from ``seed``; the direction turns
    about +Y by ``turn_amplitude`` [rad] at ``turn_frequency`` [Hz]; coefficient c [kg/s].
    ``air_velocity(t)`` gives w(t) on the host (same formula as the kernel)."""

    def __init__(self, direction=(1.0, 0.0, 0.0), speed=5.0, gust_amplitude=0.3, gust_frequency=0.5,
                 turn_amplitude=0.0, turn_frequency=0.1, coefficient=0.1, seed=0):
        d = np.asarray(checks.vec3(direction, "Wind direction"))
        if np.linalg.norm(d) == 0.0:
            raise ValueError("Wind direction is the zero vector; give a direction")
        self.direction = tuple(d / np.linalg.norm(d))
        fix = "give a finite number"
        self.speed = checks.finite(speed, "Wind speed", fix=fix)
        self.gust_amplitude = checks.finite(gust_amplitude, "Wind gust_amplitude", fix=fix)
        self.gust_frequency = checks.finite(gust_frequency, "Wind gust_frequency", fix=fix)
        self.turn_amplitude = checks.finite(turn_amplitude, "Wind turn_amplitude", fix=fix)
        self.turn_frequency = checks.finite(turn_frequency, "Wind turn_frequency", fix=fix)
        self.coefficient = checks.finite(coefficient, "Wind coefficient", fix=fix)
        if self.coefficient < 0.0:
            raise ValueError(f"Wind coefficient {self.coefficient} < 0; give c >= 0 [kg/s]")
        self.gust_phase = tuple(np.random.default_rng(seed).uniform(0.0, 2.0 * np.pi, 3))

    def air_velocity(self, t: float) -> np.ndarray:
        two_pi = 2.0 * np.pi
        f, p = self.gust_frequency, self.gust_phase
        g = (np.sin(two_pi * f * t + p[0]) + 0.5 * np.sin(two_pi * 2.13 * f * t + p[1])
             + 0.25 * np.sin(two_pi * 4.37 * f * t + p[2])) / 1.75
        a = self.turn_amplitude * np.sin(two_pi * self.turn_frequency * t)
        d = self.direction
        turned = np.array([np.cos(a) * d[0] + np.sin(a) * d[2], d[1], -np.sin(a) * d[0] + np.cos(a) * d[2]])
        return self.speed * (1.0 + self.gust_amplitude * g) * turned

    def eval(self, q, qd, time, time_offset, f_out) -> None:
        m = self.model
        wp.launch(
            K.eval_wind, m.particle_count,
            inputs=[qd, m.particle_inv_mass, time, float(time_offset), wp.vec3(self.direction), self.speed,
                    self.gust_amplitude, self.gust_frequency, wp.vec3(self.gust_phase), self.turn_amplitude,
                    self.turn_frequency, self.coefficient, f_out],
            device=m.device,
        )

    def eval_jacobian(self, q, qd, time, time_offset, ck, cd, diag, rows, cols, values) -> None:
        wp.launch(K.eval_scaled_identity_jacobian, self.model.particle_count,
                  inputs=[-self.coefficient, float(cd), diag], device=self.model.device)


class Magnets(Force):
    """Point attractors (strength > 0) and repellers (< 0):
    f = s d / (|d|^2 + softening^2)^(3/2), d = center - x, strength s [N m^2], softening [m];
    particles farther than ``cutoff`` [m] feel nothing (None: no cutoff)."""

    def __init__(self, centers, strengths, softening=0.05, cutoff=None):
        c = checks.vectors(centers, "Magnets centers", item="center", unit="m")
        s = np.asarray(strengths, dtype=object)
        if s.ndim == 0:  # one strength for every center
            s = checks.numbers_array(checks.finite(strengths, "Magnets strengths", "N m^2"), "Magnets strengths",
                                     len(c))
        else:
            s = checks.numbers_array(strengths, "Magnets strengths", item="strength", unit="N m^2")
            if len(s) != len(c):
                raise ValueError(f"Magnets has {len(c)} centers but {len(s)} strengths; give one strength per "
                                 "center (or a single number for all)")
        softening = checks.positive(softening, "Magnets softening", "m", "it keeps the force finite at the center")
        if cutoff is not None:
            cutoff = checks.positive(cutoff, "Magnets cutoff", "m", "or None for no cutoff")
        self.centers, self.strengths = c, s
        self.softening = float(softening)
        self.cutoff = 0.0 if cutoff is None else float(cutoff)

    def bind(self, model) -> None:
        super().bind(model)
        self._centers = wp.array(self.centers.astype(np.float32), dtype=wp.vec3, device=model.device)
        self._strengths = wp.array(self.strengths.astype(np.float32), dtype=float, device=model.device)

    def eval(self, q, qd, time, time_offset, f_out) -> None:
        m = self.model
        wp.launch(K.eval_magnets, m.particle_count,
                  inputs=[q, m.particle_inv_mass, self._centers, self._strengths, self.softening, self.cutoff, f_out],
                  device=m.device)

    def eval_jacobian(self, q, qd, time, time_offset, ck, cd, diag, rows, cols, values) -> None:
        m = self.model
        wp.launch(K.eval_magnets_jacobian, m.particle_count,
                  inputs=[q, m.particle_inv_mass, self._centers, self._strengths, self.softening, self.cutoff,
                          float(ck), diag],
                  device=m.device)


class Drag(Force):
    """Velocity-dependent drag f = -linear v - quadratic |v| v; linear [kg/s], quadratic [kg/m]."""

    energy_role = "dissipative"

    def __init__(self, linear=0.0, quadratic=0.0):
        self.linear = checks.nonnegative(linear, "Drag linear coefficient", "kg/s")
        self.quadratic = checks.nonnegative(quadratic, "Drag quadratic coefficient", "kg/m")

    def eval(self, q, qd, time, time_offset, f_out) -> None:
        m = self.model
        wp.launch(K.eval_drag, m.particle_count, inputs=[qd, self.linear, self.quadratic, f_out], device=m.device)

    def eval_jacobian(self, q, qd, time, time_offset, ck, cd, diag, rows, cols, values) -> None:
        m = self.model
        wp.launch(K.eval_drag_jacobian, m.particle_count, inputs=[qd, self.linear, self.quadratic, float(cd), diag],
                  device=m.device)


class Springs(Force):
    """The model's damped springs, f_i = -(k (l - L) + kd dl/dt) d_hat, f_j = -f_i.

    The Simulator adds this force automatically when the model has springs. Broken springs
    (``model.spring_broken``, see ``warpsim.core.fracture``) exert nothing and have no Jacobian. ``exact_jacobian``
    selects the true Jacobian (tests) instead of the solver's symmetric, clamped form.

    ``deterministic`` (default True): forces and Jacobian blocks are gathered per particle over
    the model's CSR adjacency (``model.particle_springs``) in a fixed order, so two runs give the
    same bits on any device (on the CPU each spring is evaluated once, its force and minus it
    written to its two entries of the CSR list, and each particle then sums its entries
    contiguously: the same sums, bit for bit, faster there). False: the former per-spring scatter with float atomics, whose
    summation order (and so the last bits, which chaotic scenes amplify) varies run to run on
    GPUs; an opt-out for speed measurements. Under a recording ``wp.Tape`` the gather computes
    the forces and the tape records the scatter kernel for the backward pass (the adjoint of
    the same sum)."""

    energy_role = "potential"

    def __init__(self, exact_jacobian: bool = False, deterministic: bool = True):
        if not isinstance(deterministic, (bool, np.bool_)):
            raise TypeError(f"Springs deterministic = {deterministic!r}; give True (fixed-order sums) or False")
        self.exact_jacobian = exact_jacobian
        self.deterministic = bool(deterministic)
        self._launches: dict = {}
        self._entries = None  # the CPU's two-pass gather buffers (_spring_entries)

    def bind(self, model) -> None:
        super().bind(model)
        ensure_spring_adjacency(model)

    def _gathers(self) -> bool:
        return self.deterministic

    def eval(self, q, qd, time, time_offset, f_out) -> None:
        m = self.model
        if m.spring_count == 0:
            return
        launches = self._launches
        scatter = (q, qd, m.spring_indices, m.spring_rest_length, m.spring_stiffness, m.spring_damping,
                   m.spring_broken, f_out)
        if not self._gathers():  # the same launch every step: replayed recorded
            cached_launch(K.eval_springs, m.spring_count, scatter, m.device, launches,
                          key=(m.spring_count, *map(id, scatter)))
            return
        ensure_spring_adjacency(m)
        inputs = (*scatter[:7], m.particle_spring_offsets, m.particle_springs, f_out)
        tape = recording_tape()
        if tape is None and any(a.requires_grad for a in scatter[:6]):
            # a plain wp.Tape (not entered through warpsim.core.launch.recording) may record: the
            # scatter kernel, whose adjoint it can take (float atomics: the last bits may differ)
            wp.launch(K.eval_springs, m.spring_count, inputs=list(scatter), device=m.device)
            return
        if tape is None and m.device.is_cpu:  # each spring once, then the same fixed-order sums
            entries, entry_f = self._spring_entries(m)
            first = (*scatter[:7], entries, entry_f)
            cached_launch(K.eval_spring_force_entries, m.spring_count, first, m.device, launches,
                          key=("springs", m.spring_count, *map(id, first)))
            second = (m.particle_spring_offsets, entry_f, f_out)
            cached_launch(K.sum_spring_entries, m.particle_count, second, m.device, launches,
                          key=("sums", m.particle_count, *map(id, second)))
            return
        if tape is None:
            cached_launch(K.eval_springs_gather, m.particle_count, inputs, m.device, launches,
                          key=("gather", m.particle_count, *map(id, inputs)))
            return
        # recording: the gather computes the forward result, the tape differentiates the same sum
        # through the scatter kernel's adjoint (a loop-carried gather has none in Warp)
        wp.launch(K.eval_springs_gather, m.particle_count, inputs=list(inputs), device=m.device, record_tape=False)
        tape.record_launch(K.eval_springs, m.spring_count, 0, list(scatter), [], m.device)

    def _spring_entries(self, model):
        """(entries (spring_count,) vec2i: the positions of (end 2s, s) and (end 2s+1, s) in the
        model's CSR list ``particle_springs``; per-entry force buffer (2 spring_count,)) of the
        CPU's two-pass gather, built once per model and CSR list."""
        cached = self._entries
        if cached is not None and cached[0] is model.particle_springs and cached[1].device == model.device:
            return cached[1], cached[2]
        ends = model.spring_indices.numpy().reshape(-1, 2)
        offsets, springs = model.particle_spring_offsets.numpy(), model.particle_springs.numpy()
        owner = np.repeat(np.arange(model.particle_count), np.diff(offsets))  # particle of each CSR entry
        order = np.argsort(springs, kind="stable")  # each spring's two entries, in CSR order
        first, second = order[0::2], order[1::2]
        swap = owner[first] != ends[:, 0]  # the first entry belongs to end 2s+1 (a self-loop keeps the order)
        entries = np.stack([np.where(swap, second, first), np.where(swap, first, second)], axis=1)
        d = model.device
        buffers = (wp.array(entries.astype(np.int32).reshape(-1, 2), dtype=wp.vec2i, device=d),
                   wp.zeros(max(len(springs), 1), dtype=wp.vec3, device=d))
        self._entries = (model.particle_springs, *buffers)  # keeps the CSR list it was built from
        return buffers

    def jacobian_triplet_count(self) -> int:
        return 2 * self.model.spring_count

    def eval_jacobian(self, q, qd, time, time_offset, ck, cd, diag, rows, cols, values) -> None:
        m = self.model
        if m.spring_count == 0:
            return
        common = [q, qd, m.spring_indices, m.spring_rest_length, m.spring_stiffness, m.spring_damping, m.spring_broken]
        tail = [float(ck), float(cd), int(self.exact_jacobian), diag, rows, cols, values]
        if self._gathers():
            ensure_spring_adjacency(m)
            wp.launch(K.eval_springs_jacobian_gather, m.particle_count,
                      inputs=[*common, m.particle_spring_offsets, m.particle_springs, *tail], device=m.device)
        else:
            wp.launch(K.eval_springs_jacobian, m.spring_count, inputs=[*common, *tail], device=m.device)


class ForceField(Force):
    """A user force field: ``field`` is a ``@wp.func`` of (x: wp.vec3 [m], v: wp.vec3 [m/s],
    t: float [s]) -> wp.vec3 [N], applied to every dynamic particle. Its Jacobian for implicit
    Euler is taken by central differences with step ``eps`` and symmetrised."""

    def __init__(self, field, eps: float = 1.0e-3):
        if not isinstance(field, wp.Function):
            raise ValueError("ForceField needs a @wp.func of (wp.vec3, wp.vec3, float) -> wp.vec3; decorate it with @wp.func")
        self.field = field
        self.eps = checks.positive(eps, "ForceField eps", "m", "the finite-difference step, e.g. 1e-3")
        self._eval_kernel, self._jacobian_kernel = K.force_field_kernels(field)

    def eval(self, q, qd, time, time_offset, f_out) -> None:
        m = self.model
        wp.launch(self._eval_kernel, m.particle_count,
                  inputs=[q, qd, m.particle_inv_mass, time, float(time_offset), f_out], device=m.device)

    def eval_jacobian(self, q, qd, time, time_offset, ck, cd, diag, rows, cols, values) -> None:
        m = self.model
        wp.launch(self._jacobian_kernel, m.particle_count,
                  inputs=[q, qd, m.particle_inv_mass, time, float(time_offset), self.eps, float(ck), float(cd), diag],
                  device=m.device)
