"""The cloth solver's fused semi-implicit Euler (:class:`ClothSemiImplicitEuler`): v += h (f/m + g),
x += h v with springs, gravity and the update fused ("scatter": spring-force kernels + particle
kernel; "owner", the CPU default: each spring evaluated once by its lower end's thread + a particle
kernel, scatter's sums bit for bit; "gather", the CUDA default: one particle-centric kernel;
"lanes": eight particles a thread). All sum each particle's springs in a fixed order without float
atomics, so runs are bit-reproducible on every device. ``split_forces`` sorts a system's forces into
the fused ones (gravity, the model springs) and the others, for both cloth integrators.
``warpsim.cloth.solver`` re-exports the class and drives it in ``ClothSimulator``.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from ..core import checks
from ..core.forces import Gravity, Springs
from ..core.integrators import Integrator
from ..core.model import ensure_spring_adjacency
from ..kernels import cloth as KC
from ..kernels import cloth_lanes as KL
from ..kernels import forces as KF
from ..kernels.cloth_lanes import ROW_MAX as LANE_ROW_MAX
from .lanes import build_lane_blocks

GATHER_MAX_PARTICLES = 1 << 24


def split_forces(system):
    """(summed gravity vector, springs force or None, other forces) of a ParticleSystem."""
    g = np.zeros(3)
    springs, others = None, []
    for f in system.forces:
        if isinstance(f, Gravity):
            g += np.asarray(f.g)
        elif isinstance(f, Springs) and springs is None:
            springs = f
        else:
            others.append(f)
    return wp.vec3(*g.tolist()), springs, others



class ClothSemiImplicitEuler(Integrator):
    """Semi-implicit (symplectic) Euler for cloth with the spring, gravity and update kernels
    fused. ``mode``: "scatter" (a spring-force kernel, per particle over the model's CSR
    adjacency in spring order, + a particle kernel; handles breakable springs), "gather" (one
    particle-centric kernel per step over packed adjacency lists, each spring evaluated at both
    ends), "owner" (two particle kernels per step: each spring evaluated once, by its lower end's
    thread, which writes its force on both ends to their entries of the model's CSR spring list;
    then each particle sums its CSR row in order and is updated: the scatter mode's sums, bit for
    bit), "lanes" (one kernel per step, eight particles a thread whose CSR rows share a neighbour
    pattern, their springs in SIMD lanes: the scatter mode's sums bit for bit, rows of at most
    12 springs; ``warpsim.cloth.lanes``) or None: gather on CUDA (measured faster there on an
    H100 from 32^2 to 1024^2 particles, see benchmarks/bench_cloth.py), lanes on the CPU where
    at least half of its lanes hold distinct particles, else owner (scatter where springs can
    break). "gather", "owner" and "lanes" step out of place (ClothSimulator ping-pongs its state
    arrays); lanes reads spring parameters from the model's arrays once per ClothSimulator frame
    (once per step otherwise). None uses float
    atomics: all are bit-reproducible (gather sums in another order than scatter and owner, so it
    agrees with them to float rounding). ``deterministic=False`` (scatter mode only): the former per-spring kernel
    with float atomics, whose summation order varies run to run on GPUs (an opt-out for speed
    comparisons)."""

    name = "cloth_semi_implicit_euler"

    def __init__(self, mode: str | None = None, deterministic: bool = True):
        super().__init__()
        if mode not in (None, "scatter", "gather", "owner", "lanes"):
            raise ValueError(f"mode = {mode!r}; use 'scatter', 'gather', 'owner', 'lanes' or None (automatic)")
        if not isinstance(deterministic, (bool, np.bool_)):
            raise TypeError(f"deterministic = {deterministic!r}; give True (fixed-order sums) or False")
        self.requested_mode = mode
        self.deterministic = checks.flag(deterministic, f"{type(self).__name__} deterministic")

    def _allocate(self, system):
        model, d = system.model, system.device
        breakable = getattr(model, "breakable_spring_count", 0)
        if breakable:
            auto = "scatter"
        else:
            auto = "gather" if d.is_cuda and system.count < GATHER_MAX_PARTICLES else "owner"
        self.lane_blocks = None
        if self.requested_mode == "lanes" or (self.requested_mode is None and auto == "owner"):
            self.lane_blocks = self._lane_blocks(model, required=self.requested_mode == "lanes")
            if self.lane_blocks is not None:
                auto = "lanes"
        self.mode = self.requested_mode or auto
        if self.mode in ("gather", "owner", "lanes") and breakable:
            raise ValueError(f"mode={self.mode!r} cannot break springs (its adjacency lists carry no spring index) "
                             f"and this model has {breakable} breakable springs; use mode='scatter' or None")
        if self.mode == "gather" and system.count >= GATHER_MAX_PARTICLES:
            raise ValueError(f"mode='gather' handles fewer than {GATHER_MAX_PARTICLES} particles (indices are packed "
                             f"in 24 bits), this model has {system.count}; use mode='scatter'")
        self.gravity, self.springs, self.others = split_forces(system)
        self.f.zero_()
        self.f_ext = wp.zeros(system.count if self.others else 1, dtype=wp.vec3, device=d)
        if self.out_of_place:
            self.q_tmp = wp.zeros(system.count, dtype=wp.vec3, device=d)
            self.qd_tmp = wp.zeros(system.count, dtype=wp.vec3, device=d)
        if self.mode == "gather":
            self._build_adjacency(model)
        elif self.mode == "owner":
            self._build_owned(model)
        elif self.mode == "lanes":
            self._upload_lanes(system)

    @property
    def out_of_place(self) -> bool:
        """True when a step reads (q, qd) and writes other arrays (``step_to``): "gather", "owner",
        "lanes"."""
        return getattr(self, "mode", None) in ("gather", "owner", "lanes")

    @staticmethod
    def _lane_blocks(model, required: bool):
        """The lanes mode's blocks, or None (automatic choice) where a row is too long or fewer than
        half of the lanes would hold distinct particles."""
        ensure_spring_adjacency(model)
        offsets = model.particle_spring_offsets.numpy()
        if not required and (model.particle_count == 0 or np.diff(offsets).max() > LANE_ROW_MAX):
            return None
        blocks = build_lane_blocks(offsets, model.particle_springs.numpy(), model.spring_indices.numpy(),
                                   model.particle_count)
        return blocks if required or blocks.utilisation >= 0.5 else None

    def _upload_lanes(self, system):
        d, b = system.device, self.lane_blocks
        self.lane_particles = wp.array(b.particles, dtype=KL.lane8i, device=d)
        self.lane_info = wp.array(b.info, dtype=wp.vec4i, device=d)
        self.lane_deltas = wp.array(b.deltas, dtype=int, device=d)
        self.lane_slot_springs = wp.array(b.slot_springs, dtype=KL.lane8i, device=d)
        self.lane_params = wp.zeros(3 * len(b.slot_springs), dtype=KL.lane8, device=d)
        blocks = (system.count + KL.LANES - 1) // KL.LANES
        self.planar8 = [wp.zeros(blocks, dtype=KL.lane8, device=d) for _ in range(6)]
        self.planar = [a.view(float).flatten() for a in self.planar8]  # float views of the same memory
        self._params_fresh = False

    def begin_frame(self, system) -> None:
        """Lanes mode: read the spring parameters once for the frame's steps (ClothSimulator calls
        this before a frame's sub-steps and ``end_frame`` after them)."""
        if getattr(self, "mode", None) == "lanes":
            self._pack_lane_params(system)
            self._params_fresh = True

    def end_frame(self) -> None:
        self._params_fresh = False

    def _pack_lane_params(self, system):
        model = system.model
        wp.launch(KL.pack_lane_params, len(self.lane_slot_springs),
                  inputs=[self.lane_slot_springs, model.spring_rest_length, model.spring_stiffness,
                          model.spring_damping, self.lane_params], device=system.device)

    def _step_lanes(self, system, q, qd, dt, q_out, qd_out):
        if not self._params_fresh:
            self._pack_lane_params(system)
        n, runs = system.count, self.lane_blocks.runs
        wp.launch(KL.pack_planar, (n + KL.LANES - 1) // KL.LANES, inputs=[q, qd, n, *self.planar8], device=system.device)
        for kernel, first, count in ((KL.step_cloth_lanes_run, 0, runs),
                                     (KL.step_cloth_lanes_any, runs, len(self.lane_particles) - runs)):
            if count:
                wp.launch(kernel, count,
                          inputs=[*self.planar, self.f_ext, int(bool(self.others)), first, self.lane_particles,
                                  self.lane_info, self.lane_deltas, self.lane_params, system.inv_mass, self.gravity,
                                  float(dt), q_out, qd_out], device=system.device)

    def _build_owned(self, model):
        """"owner" mode's lists: each spring s is owned by its lower end i: entries (other end j,
        s, i's and j's positions in the model's CSR list ``particle_springs``), grouped by i, by j
        within a group (an order fixed at build time)."""
        n, d = model.particle_count, model.device
        ensure_spring_adjacency(model)
        ends = model.spring_indices.numpy().reshape(-1, 2).astype(np.int64)
        count = len(ends)
        offsets, springs = model.particle_spring_offsets.numpy(), model.particle_springs.numpy()
        row = np.repeat(np.arange(n), np.diff(offsets))  # particle of each CSR entry
        order = np.argsort(springs, kind="stable")  # each spring's two CSR entries
        first, second = order[0::2], order[1::2]
        swap = row[first] != ends[:, 0]
        entry = np.stack([np.where(swap, second, first), np.where(swap, first, second)], axis=1)  # ends 2s, 2s+1
        flip = ends[:, 1] < ends[:, 0]  # end 2s+1 owns the spring
        lo, hi = np.where(flip, ends[:, 1], ends[:, 0]), np.where(flip, ends[:, 0], ends[:, 1])
        own_entry, other_entry = np.where(flip, entry[:, 1], entry[:, 0]), np.where(flip, entry[:, 0], entry[:, 1])
        own = np.lexsort((hi, lo))  # by lower end, then upper end
        self.owned_offsets = wp.array(np.concatenate([[0], np.cumsum(np.bincount(lo, minlength=n))]).astype(np.int32),
                                      dtype=int, device=d)
        entries = np.stack([hi[own], own, own_entry[own], other_entry[own]], axis=1).astype(np.int32)
        self.owned = wp.array(entries.reshape(-1, 4), dtype=wp.vec4i, device=d)
        self.entry_f = wp.zeros(max(2 * count, 1), dtype=wp.vec3, device=d)

    def _build_adjacency(self, model):
        """Per-particle spring lists for the gather kernel, grouped by particle. Packed (4 bytes an
        entry: other end << 8 | index into a table of distinct (rest, k, kd)) when the model has
        at most 256 distinct spring parameter triples, else wide (16 bytes: the triple and the
        other end)."""
        n, d = model.particle_count, model.device
        pairs = model.spring_indices.numpy().reshape(-1, 2)
        ends = np.concatenate([pairs, pairs[:, ::-1]])
        spring = np.concatenate([np.arange(len(pairs))] * 2)
        order = np.lexsort((ends[:, 1], ends[:, 0]))
        ends, spring = ends[order], spring[order]
        offsets = np.zeros(n + 1, dtype=np.int64)
        np.add.at(offsets, ends[:, 0] + 1, 1)
        self.adjacency_offsets = wp.array(np.cumsum(offsets).astype(np.int32), dtype=int, device=d)
        params = np.stack([model.spring_rest_length.numpy(), model.spring_stiffness.numpy(),
                           model.spring_damping.numpy()], axis=1).astype(np.float32)
        table, kind = np.unique(params, axis=0, return_inverse=True)
        kind = kind.reshape(-1)
        if len(table) <= 256:
            packed = (ends[:, 1].astype(np.uint32) << np.uint32(8)) | kind[spring].astype(np.uint32)
            self.adjacency = wp.array(packed, dtype=wp.uint32, device=d)
            self.adjacency_table = wp.array(table.reshape(-1, 3), dtype=wp.vec3, device=d)
        else:
            wide = np.concatenate([params[spring], ends[:, 1:2].astype(np.float32)], axis=1)
            self.adjacency = wp.array(wide.reshape(-1, 4), dtype=wp.vec4, device=d)
            self.adjacency_table = wp.zeros(1, dtype=wp.vec3, device=d)

    def _external(self, system, q, qd, time, f):
        for force in self.others:
            force.eval(q, qd, time, 0.0, f)

    def step_to(self, system, q, qd, time, dt, q_out, qd_out) -> None:
        """Gather and owner modes: read (q, qd), write the stepped state to (q_out, qd_out) (other
        arrays)."""
        self.prepare(system)
        if self.others:
            self.f_ext.zero_()
            self._external(system, q, qd, time, self.f_ext)
        if self.mode == "lanes":
            self._step_lanes(system, q, qd, dt, q_out, qd_out)
            return
        if self.mode == "owner":
            model = system.model
            wp.launch(KC.eval_cloth_owned_springs, system.count,
                      inputs=[q, qd, self.owned_offsets, self.owned, model.spring_rest_length, model.spring_stiffness,
                              model.spring_damping, self.entry_f],
                      device=system.device)
            wp.launch(KC.step_cloth_owned, system.count,
                      inputs=[q, qd, self.f_ext, int(bool(self.others)), model.particle_spring_offsets, self.entry_f,
                              system.inv_mass, self.gravity, float(dt), q_out, qd_out],
                      device=system.device)
            return
        wp.launch(KC.step_cloth_gather, system.count,
                  inputs=[q, qd, self.f_ext, int(bool(self.others)), self.adjacency_offsets, self.adjacency,
                          self.adjacency_table, system.inv_mass, self.gravity, float(dt), q_out, qd_out],
                  device=system.device)

    def step(self, system, q, qd, time, dt, f_out=None):
        self.prepare(system)
        if self.out_of_place:
            if f_out is not None:
                system.eval_forces(q, qd, time, 0.0, f_out)
            self.step_to(system, q, qd, time, dt, self.q_tmp, self.qd_tmp)
            wp.copy(q, self.q_tmp)
            wp.copy(qd, self.qd_tmp)
            return
        model = system.model
        f = self.f  # zero on entry: the particle kernel clears it
        self._external(system, q, qd, time, f)
        if model.spring_count and not self.deterministic:  # the opt-out: per-spring float atomics
            wp.launch(KF.eval_springs, model.spring_count,
                      inputs=[q, qd, model.spring_indices, model.spring_rest_length, model.spring_stiffness,
                              model.spring_damping, model.spring_broken, f], device=system.device)
        elif model.spring_count:  # gathered per particle in a fixed order (breakable springs included)
            springs = self.springs if self.springs is not None else Springs()
            if springs is not self.springs:
                springs.bind(model)
                self.springs = springs
            springs.eval(q, qd, time, 0.0, f)
        if f_out is not None:
            wp.copy(f_out, f)
            wp.launch(KF.eval_gravity, system.count, inputs=[system.mass, self.gravity, f_out], device=system.device)
        wp.launch(KC.integrate_cloth_particles, system.count,
                  inputs=[f, system.inv_mass, self.gravity, float(dt), q, qd], device=system.device)
