"""The cloth solver's implicit Euler (:class:`ClothImplicitEuler`): each step solves
``(M - h D - h^2 K) dv = h (f0 + h K v0)`` (Baraff & Witkin 1998; ``newton_iterations > 1``
continues with Newton iterations on backward Euler). Spring blocks are written by one kernel straight
into a fixed-topology BSR matrix; block-Jacobi preconditioned CG solves it
(``warpsim.core.block_cg.BlockCG``, capturable, by default; or ``warp.optim.linear.cg``,
preallocated); pinned rows and columns are filtered, contacts constrained inside the solve
(``warpsim.cloth.contact``). Per step it reports CG iterations, final residual and tolerance. The
assembly sums each particle's springs in a fixed order and BlockCG's dot products are fixed trees,
so runs are bit-reproducible. ``warpsim.cloth.solver`` re-exports the class and drives it in
``ClothSimulator``.
"""

from __future__ import annotations

import numpy as np
import warp as wp
import warp.optim.linear as wpl
import warp.sparse as wps

from ..core import checks
from ..core.block_cg import BlockCG
from ..core.forces import Force
from ..core.integrators import Integrator
from ..core.model import ensure_spring_adjacency
from ..kernels import cloth as KC
from ..kernels import integrate as KI
from .contact import ContactConstraints
from .semi_implicit import split_forces

GEOMETRIC_MODES = {"clamped": 0, "full": 1}
CONTACT_MODES = ("constrain", "after")
LINEAR_SOLVERS = ("block_cg", "warp_cg")


def _overrides_jacobian(force) -> bool:
    return type(force).eval_jacobian is not Force.eval_jacobian


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
        self.gravity, self.springs, self.others = split_forces(system)
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
