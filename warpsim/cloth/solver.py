"""Cloth solvers: Baraff-Witkin implicit Euler on ``warp.sparse`` + CG, a fused semi-implicit
Euler, and a Simulator that replays each frame's sub-steps as a captured graph.

- :class:`ClothImplicitEuler`: each step solves ``(M - h D - h^2 K) dv = h (f0 + h K v0)``
  (Baraff & Witkin 1998; ``newton_iterations > 1`` continues with Newton iterations on backward
  Euler). Spring blocks are written by one kernel straight into a fixed-topology BSR matrix;
  block-Jacobi preconditioned CG solves it (``warpsim.core.block_cg.BlockCG``, capturable, by
  default; or ``warp.optim.linear.cg``, preallocated); pinned rows and columns are filtered.
  Per step it reports CG iterations, final residual and tolerance.
- :class:`ClothSemiImplicitEuler`: v += h (f/m + g), x += h v with springs, gravity and the
  update fused ("scatter": spring-force kernels + particle kernel; "owner", the CPU default:
  each spring evaluated once by its lower end's thread + a particle kernel, scatter's sums bit
  for bit; "gather", the CUDA default: one particle-centric kernel). All sum each particle's
  springs in a fixed order without float atomics, as does the implicit solver's assembly and its
  CG dot products, so runs are bit-reproducible on every device.
- :class:`ClothSimulator`: a ``ws.Simulator`` whose ``frame()`` / ``run()`` capture a frame's
  sub-steps (forces, solve, colliders) in a graph (CUDA and CPU) and replay it; no allocation
  and no host read-back inside a frame.

All three accept any ws.Force list: gravity and the model springs are fused; other forces are
evaluated through their own kernels (for the implicit solver they must have per-particle
Jacobian blocks only).
"""

from __future__ import annotations

import numpy as np
import warp as wp
import warp.optim.linear as wpl
import warp.sparse as wps

from ..core import checks
from ..core.block_cg import BlockCG
from ..core.forces import Force, Gravity, Springs
from ..core.integrators import INTEGRATORS, Integrator, make_integrator
from ..core.model import ensure_spring_adjacency
from ..core.simulator import Simulator, check_dt
from ..kernels import cloth as KC
from ..kernels import cloth_lanes as KL
from ..kernels import forces as KF
from ..kernels import integrate as KI
from ..kernels.cloth_lanes import ROW_MAX as LANE_ROW_MAX
from .contact import ContactConstraints
from .lanes import build_lane_blocks

GEOMETRIC_MODES = {"clamped": 0, "full": 1}
CONTACT_MODES = ("constrain", "after")
LINEAR_SOLVERS = ("block_cg", "warp_cg")
GATHER_MAX_PARTICLES = 1 << 24


def _split_forces(system):
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


def _overrides_jacobian(force) -> bool:
    return type(force).eval_jacobian is not Force.eval_jacobian


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
        self.gravity, self.springs, self.others = _split_forces(system)
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


class ClothImplicitEuler(Integrator):
    """Implicit Euler for cloth after Baraff & Witkin (1998) on ``warp.sparse`` BSR matrices.

    Args:
        newton_iterations: 1 = Baraff-Witkin exactly (one linear solve per step, forces
            linearised at the start of the step); more continue with Newton iterations on
            backward Euler M (v1 - v0) = h f(x0 + h v1, v1) while max |dv| > newton_tol [m/s], at
            most this many: a device-side loop (``wp.capture_while``), so a captured frame stops
            where an eager one does, with no host read-back.
        cg_tol: CG tolerance relative to |b|; cg_atol: absolute floor [kg m/s].
        cg_max_iterations: CG iteration cap.
        geometric: "clamped" (default; (1 - L/l) clamped at 0 under compression, A stays
            positive definite) or "full" (the exact spring stiffness, may be indefinite).
        linear_solver: "block_cg" (default; warpsim.cloth.block_cg.BlockCG: preallocated PCG with
            device-side scalars, capturable, fast on the CPU too) or "warp_cg"
            (``warp.optim.linear.cg`` with the same operator and preconditioner, preallocated
            through ``cg(..., run=False)``; its tile-based dot products are slow on the CPU).
        check_every: "warp_cg" only: convergence test every this many iterations on the host; 0
            tests on the device (used automatically while a graph is being captured). None: 1 on
            the CPU, 10 on CUDA.
        record_history: keep (newton iterations, CG iterations, residual, tolerance) of every
            step in ``history`` (host-checked steps only).
        deterministic: True (default): the system is assembled per particle over the model's CSR
            spring adjacency in a fixed order (no float atomics; BlockCG's dot products are
            fixed-order too), so runs are bit-reproducible on every device. False: the former
            per-spring assembly with float atomics (order varies run to run on GPUs).
        contact: "constrain" (default): particles resting on the simulator's static planes,
            spheres and capsules are constrained inside the solve (``warpsim.cloth.contact``: zero
            normal velocity, friction from the constraint impulse, released when it pulls), so the
            solve cannot pull them into the shape for the collider to push back out, stretching
            the springs (energy from nowhere at large steps); "after": the colliders act after
            the step only. ``ClothSimulator`` hands the integrator its colliders.

    After each step: ``last_newton_iterations``, ``last_cg_iterations`` (summed over Newton
    iterations), ``last_cg_residual`` (final |b - A dv| of the last solve, CG's recursive
    estimate) and ``last_cg_tolerance`` (the absolute tolerance it had to meet).
    """

    name = "cloth_implicit_euler"

    def __init__(self, newton_iterations: int = 1, newton_tol: float = 1.0e-5, cg_tol: float = 1.0e-5,
                 cg_atol: float = 1.0e-12, cg_max_iterations: int = 200, geometric: str = "clamped",
                 linear_solver: str = "block_cg", check_every: int | None = None, record_history: bool = False,
                 deterministic: bool = True, contact: str = "constrain"):
        super().__init__()
        if contact not in CONTACT_MODES:
            raise ValueError(f"contact = {contact!r}; use one of {CONTACT_MODES} ('constrain': contacts with static "
                             "planes and spheres are constraints inside the solve; 'after': colliders act after it only)")
        self.contact = contact
        self._colliders = None
        self._contact: ContactConstraints | None = None
        if not isinstance(deterministic, (bool, np.bool_)):
            raise TypeError(f"deterministic = {deterministic!r}; give True (fixed-order sums) or False")
        self.deterministic = checks.flag(deterministic, f"{type(self).__name__} deterministic")
        if int(newton_iterations) < 1:
            raise ValueError(f"newton_iterations = {newton_iterations}; it must be >= 1")
        if not (cg_tol > 0.0 and cg_atol >= 0.0):
            raise ValueError(f"cg_tol = {cg_tol}, cg_atol = {cg_atol}; need cg_tol > 0 and cg_atol >= 0")
        if int(cg_max_iterations) < 1:
            raise ValueError(f"cg_max_iterations = {cg_max_iterations}; it must be >= 1")
        if geometric not in GEOMETRIC_MODES:
            raise ValueError(f"geometric = {geometric!r}; use one of {sorted(GEOMETRIC_MODES)}")
        if linear_solver not in LINEAR_SOLVERS:
            raise ValueError(f"linear_solver = {linear_solver!r}; use one of {LINEAR_SOLVERS}")
        if check_every is not None and int(check_every) < 0:
            raise ValueError(f"check_every = {check_every}; it must be >= 0 (or None)")
        self.newton_iterations = int(newton_iterations)
        self.newton_tol = float(newton_tol)
        self.cg_tol = float(cg_tol)
        self.cg_atol = float(cg_atol)
        self.cg_max_iterations = int(cg_max_iterations)
        self.geometric = geometric
        self.linear_solver = linear_solver
        self.check_every = check_every
        self.record_history = checks.flag(record_history, "ClothImplicitEuler record_history")
        self.history = []
        self._last_newton_host = 0
        self._block_cg = None
        self._cg_host = None
        self._cg_device = None

    # ----------------------------------------------------------------------------------
    def _allocate(self, system):
        model, n, d = system.model, system.count, system.device
        self.gravity, self.springs, self.others = _split_forces(system)
        for force in self.others:
            if force.jacobian_triplet_count():
                raise ValueError(f"ClothImplicitEuler: force {type(force).__name__} couples particles (it has "
                                 "off-diagonal Jacobian blocks); use ws.ImplicitEuler for it")
        self._position_jacobian_forces = [f for f in self.others if _overrides_jacobian(f)]
        self._others_all = [f for f in system.forces if f is not self.springs]
        self.x0 = wp.zeros(n, dtype=wp.vec3, device=d)
        self.v0 = wp.zeros(n, dtype=wp.vec3, device=d)
        self.rhs = wp.zeros(n, dtype=wp.vec3, device=d)
        self.dv = wp.zeros(n, dtype=wp.vec3, device=d)
        self.f_other = wp.zeros(n, dtype=wp.vec3, device=d)
        self.diag = wp.zeros(n, dtype=wp.mat33, device=d)
        self.position_diag = wp.zeros(n, dtype=wp.mat33, device=d)
        self.inverse = wp.zeros(n, dtype=wp.mat33, device=d)
        self.max_dv = wp.zeros(1, dtype=float, device=d)
        self.newton_count = wp.zeros(1, dtype=int, device=d)
        self.newton_condition = wp.zeros(1, dtype=wp.int32, device=d)
        self._build_matrix(model)
        if self.contact == "constrain" and self._colliders is not None:
            self._contact = ContactConstraints(self._colliders, model, self.A, self.diagonal_slots)
        inverse = self.inverse

        def block_jacobi(x, y, z, alpha, beta):
            wp.launch(KI.apply_block_preconditioner, n, inputs=[inverse, x, y, float(alpha), float(beta), z], device=d)

        self.preconditioner = wpl.LinearOperator((3 * n, 3 * n), wp.float32, d, matvec=block_jacobi)
        self._cg = {}
        if self.linear_solver == "block_cg":
            self._block_cg = BlockCG(self.A, self.rhs, self.dv, self.inverse, self.cg_tol, self.cg_atol,
                                     self.cg_max_iterations)
        else:
            host_every = 1 if d.is_cpu else 10
            for every in {0, host_every if self.check_every is None else int(self.check_every)}:
                self._cg[every] = wpl.cg(self.A, self.rhs, self.dv, tol=self.cg_tol, atol=self.cg_atol,
                                         maxiter=self.cg_max_iterations, M=self.preconditioner, check_every=every,
                                         use_cuda_graph=True, run=False)

    def bind_colliders(self, colliders) -> None:
        """Constrain contacts with ``colliders`` (the simulator's list, read again between frames)
        inside the solve (``contact="constrain"``); call before the first step."""
        self._colliders = colliders
        if self.contact == "constrain" and self._system is not None:
            self._contact = ContactConstraints(colliders, self._system.model, self.A, self.diagonal_slots)

    def _build_matrix(self, model):
        """Fixed BSR topology: diagonal blocks plus (i, j), (j, i) for every spring; slots map each
        block to its place in ``A.values``."""
        n, d = model.particle_count, model.device
        pairs = model.spring_indices.numpy().reshape(-1, 2).astype(np.int64)
        rows = np.concatenate([np.arange(n), pairs[:, 0], pairs[:, 1]]).astype(np.int32)
        cols = np.concatenate([np.arange(n), pairs[:, 1], pairs[:, 0]]).astype(np.int32)
        self.A = wps.bsr_zeros(n, n, wp.mat33, device=d)
        wps.bsr_set_from_triplets(self.A, wp.array(rows, dtype=int, device=d), wp.array(cols, dtype=int, device=d),
                                  wp.zeros(len(rows), dtype=wp.mat33, device=d), prune_numerical_zeros=False)
        nnz = self.A.nnz_sync()
        offsets = self.A.offsets.numpy()[: n + 1].astype(np.int64)
        columns = self.A.columns.numpy()[:nnz].astype(np.int64)
        keys = np.repeat(np.arange(n, dtype=np.int64), np.diff(offsets)) * n + columns
        slots = np.searchsorted(keys, rows.astype(np.int64) * n + cols).astype(np.int32)
        self.diagonal_slots = wp.array(slots[:n], dtype=int, device=d)
        self.spring_slots = wp.array(np.stack([slots[n:n + len(pairs)], slots[n + len(pairs):]], 1).reshape(-1),
                                     dtype=int, device=d)
        self.values = self.A.values[:nnz]

    def _solver(self):
        """(preallocated CG, check_every): device-side checks while a graph is being captured."""
        d = self._system.device
        if d.is_capturing:
            every = 0
        elif self.check_every is None:
            every = 1 if d.is_cpu else 10
        else:
            every = int(self.check_every)
        return self._cg[every], every

    # ----------------------------------------------------------------------------------
    def assemble(self, q, qd, w, time, time_offset, ck, cd, cf, cw, mass_scale=1.0):
        """Fill A = mass_scale M + cd D + ck K (pinned rows and columns -> identity) and
        b = cf f(q, qd) + cw K w - mass_scale M (qd - v0) at (q, qd). The step uses ck = -h^2, cd = -h,
        cf = h, cw = h^2 (first iteration) or 0; tests call it with other coefficients."""
        system = self._system
        model, n, d = system.model, system.count, system.device
        self.diag.zero_()
        self.rhs.zero_()
        self.values.zero_()
        self.f_other.zero_()
        for f in self._others_all:
            f.eval(q, qd, time, time_offset, self.f_other)
            f.eval_jacobian(q, qd, time, time_offset, ck, cd, self.diag, None, None, None)
        if cw != 0.0 and self._position_jacobian_forces:
            self.position_diag.zero_()
            for f in self._position_jacobian_forces:
                f.eval_jacobian(q, qd, time, time_offset, 1.0, 0.0, self.position_diag, None, None, None)
        if model.spring_count and not self.deterministic:  # the opt-out: per-spring float atomics
            wp.launch(KC.assemble_cloth_springs, model.spring_count,
                      inputs=[q, qd, w, model.spring_indices, model.spring_rest_length, model.spring_stiffness,
                              model.spring_damping, model.spring_broken, self.spring_slots, system.inv_mass,
                              float(ck), float(cd), float(cf), float(cw), GEOMETRIC_MODES[self.geometric], self.rhs,
                              self.diag, self.values], device=d)
        elif model.spring_count:  # per particle over its springs in a fixed order (no float atomics)
            ensure_spring_adjacency(model)
            wp.launch(KC.assemble_cloth_springs_gather, n,
                      inputs=[q, qd, w, model.spring_indices, model.spring_rest_length, model.spring_stiffness,
                              model.spring_damping, model.spring_broken, self.spring_slots,
                              model.particle_spring_offsets, model.particle_springs, system.inv_mass,
                              float(ck), float(cd),
                              float(cf), float(cw), GEOMETRIC_MODES[self.geometric], self.rhs, self.diag,
                              self.values], device=d)
        wp.launch(KC.finish_cloth_system, n,
                  inputs=[self.diag, self.position_diag, self.f_other, system.mass, system.inv_mass,
                          self.diagonal_slots, qd, self.v0, w, float(mass_scale), float(cf), float(cw), self.rhs,
                          self.values, self.inverse, self.dv], device=d)

    def _solve(self):
        """Run the linear solve; returns (iterations, residual, tolerance) when known on the host
        without a read-back, else None (device-side results stay in ``self._cg_device``)."""
        if self.linear_solver == "block_cg":
            self._block_cg.solve()
            self._cg_device = self._block_cg
            return None
        cg, every = self._solver()
        result = cg()
        if every > 0:
            return int(result[0]), float(result[1]), float(result[2])
        self._cg_device = result
        return None

    def step(self, system, q, qd, time, dt, f_out=None):
        self.prepare(system)
        h = float(dt)
        if f_out is not None:
            system.eval_forces(q, qd, time, 0.0, f_out)
        wp.copy(self.x0, q)
        wp.copy(self.v0, qd)
        self._cg_host = None
        contact = self._contact
        if contact is not None:
            contact.refresh()
            contact = contact if contact.active else None
        if self.record_history:
            self._step_host_checked(system, q, qd, time, h, contact)
            return
        self._last_newton_host = None  # counted on the device (``last_newton_iterations`` reads it)
        self._iterate(system, q, qd, time, h, contact, True)
        if self.newton_iterations > 1:  # later iterations while max |dv| > newton_tol: a device-side loop
            wp.capture_while(self.newton_condition, self._iterate, system=system, q=q, qd=qd, time=time, h=h,
                             contact=contact, first=False)

    def _iterate(self, system, q, qd, time, h, contact, first):
        """One Newton iteration: iteration 1 at (x0, v0) with b = h (f0 + h K v0), later ones at
        (x0 + h v, v); contact filtered in and out of the solve; then v += dv, x = x0 + h v and (more
        iterations allowed) the device-side test max |dv| > newton_tol that continues the loop.
        Returns the linear solve's (iterations, residual, tolerance) when known on the host, else None."""
        d = system.device
        self.assemble(q, qd, self.v0, time, 0.0 if first else h, -h * h, -h, h, h * h if first else 0.0)
        if contact is not None:
            contact.filter(self.x0, qd, h, self.rhs, self.inverse)
        result = self._solve()
        if contact is not None:
            contact.finish(self.dv)
        wp.launch(KI.implicit_update, system.count, inputs=[self.x0, self.dv, h, qd, q], device=d)
        if self.newton_iterations > 1:
            self.max_dv.zero_()
            wp.launch(KI.max_abs_difference, system.count, inputs=[self.dv, self.max_dv], device=d)
        wp.launch(KC.newton_continue, 1, inputs=[self.max_dv, self.newton_tol, self.newton_iterations, int(first)],
                  outputs=[self.newton_count, self.newton_condition], device=d)
        return result

    def _step_host_checked(self, system, q, qd, time, h, contact):
        """``record_history``: the same iterations with the convergence test and the CG statistics
        read on the host after each (not inside a captured frame), kept in ``history``."""
        iterations, known = 0, True
        capturing = system.device.is_capturing
        for it in range(self.newton_iterations):
            result = self._iterate(system, q, qd, time, h, contact, it == 0)
            if result is None and not capturing:
                result = self._device_stats()
            if result is None:
                known = False
            else:
                iterations += result[0]
                self._cg_host = (iterations, result[1], result[2])
            self._last_newton_host = it + 1
            if self.newton_iterations > 1 and not capturing and float(self.max_dv.numpy()[0]) <= self.newton_tol:
                break
        if not known:
            self._cg_host = None
        else:
            self.history.append((self.last_newton_iterations, *self._cg_host))

    @property
    def last_newton_iterations(self) -> int:
        """Newton iterations of the last step (a host read-back of the device count, except after a
        ``record_history`` step)."""
        if self._last_newton_host is not None:
            return self._last_newton_host
        return int(self.newton_count.numpy()[0]) if self._system is not None else 0

    # ----------------------------------------------------------------------------------
    def _device_stats(self):
        src = self._cg_device
        if src is None:
            return 0, 0.0, 0.0
        if isinstance(src, BlockCG):
            return src.stats()
        it, r2, a2 = (float(a.numpy()[0]) for a in src)
        return int(it), float(np.sqrt(max(r2, 0.0))), float(np.sqrt(max(a2, 0.0)))

    def _cg_stats(self):
        return self._cg_host if self._cg_host is not None else self._device_stats()

    @property
    def last_cg_iterations(self) -> int:
        """CG iterations of the last step (device-checked solves report the last solve)."""
        return self._cg_stats()[0]

    @property
    def last_cg_residual(self) -> float:
        """Final residual norm |b - A dv| of the last CG solve (CG's recursive estimate)."""
        return self._cg_stats()[1]

    @property
    def last_cg_tolerance(self) -> float:
        """Absolute tolerance the last CG solve had to meet: max(cg_atol, cg_tol |b|)."""
        return self._cg_stats()[2]


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
        from ..core.errors import SimulationError

        frame_dt = check_dt(frame_dt)
        if int(frames) < 0:
            raise ValueError(f"frames = {frames}; it must be >= 0")
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
                self.fracture.end_frame(frame)
            if callback is not None:
                callback(frame, self)
            if writer is not None:
                writer.write(frame, self.state)


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
