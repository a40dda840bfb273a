"""The five time integrators. Each advances a DynamicSystem's (q, qd) in place by one step h.

- ``explicit_euler``:       q1 = q0 + h v0,  v1 = v0 + h a(q0, v0)
- ``semi_implicit_euler``:  v1 = v0 + h a(q0, v0), q1 = q0 + h v1 (symplectic)
- ``implicit_euler``:       backward Euler, M (v1 - v0) = h f(q0 + h v1, v1), solved by Newton
                            iterations; each solves (M - h D - h^2 K) dv = h f - M (v - v0) with
                            ``warp.sparse`` block matrices and ``warp.optim.linear.cg``
                            (block-Jacobi preconditioner, pinned coordinates filtered)
- ``rk2``:                  the explicit midpoint method (second order)
- ``rk4``:                  the classic fourth-order Runge-Kutta method

``prepare(system)`` allocates every buffer once; ``step`` allocates nothing.

Stability regions on the damped oscillator x'' = -omega^2 x - 2 zeta omega x' (derived in
``warpsim.core.stability``; ``Simulator.stable_dt()`` applies them to the model's stiffest mode):
explicit Euler h <= 2 zeta / omega (none undamped); semi-implicit Euler
h <= 2 / (omega (zeta + sqrt(1 + zeta^2))) (2 / omega undamped); RK2 none undamped; RK4
h <= 2.83 / omega undamped, 2.785 / |lambda| for real lambda; implicit Euler unrestricted.
"""

from __future__ import annotations

import warp as wp
import warp.optim.linear as wpl
import warp.sparse as wps

from . import checks
from .block_cg import BlockCG
from .forces import Gravity
from .launch import cached_launch
from ..kernels import integrate as K


class Integrator:
    """Base of the time integrators: ``step(system, q, qd, time, dt)`` advances a system's
    coordinates ``q`` and velocities ``qd`` (``wp.array`` of ``system.dtype``, shape
    (system.count,)) by ``dt`` [s] in place, reading forces through ``system.eval_forces`` (and,
    for implicit Euler, ``system.eval_jacobians``), so one integrator drives particles, springs,
    cloth and the angle-form pendulum alike. ``name`` is its key in ``ws.INTEGRATORS``; its
    stability region (``warpsim.core.stability``) gives ``Simulator.stable_dt()``."""

    name = ""

    def __init__(self):
        self._system = None

    def prepare(self, system) -> None:
        """Allocate scratch buffers for ``system`` (idempotent)."""
        if self._system is system:
            return
        self._system = system
        n, T, d = system.count, system.dtype, system.device
        self.f = wp.zeros(n, dtype=T, device=d)
        self._allocate(system)

    def reset(self) -> None:
        """Forget the prepared system: the next ``prepare`` allocates anew (after the system's
        force list changed, or on a copy of this integrator that will drive another system)."""
        self._system = None

    def _allocate(self, system) -> None:
        pass

    def step(self, system, q, qd, time, dt: float, f_out=None) -> None:
        """Advance q, qd (arrays of system.dtype) by dt [s] from time[0]. ``f_out`` (optional)
        receives the force at the start of the step."""
        raise NotImplementedError

    def energy_cause(self, h: float) -> str | None:
        """Why this integrator itself may add energy at steps of ``h`` [s] when the step is inside the model's
        stability limit ("Cause: ... Remedy: ..."), for the blow-up message (``Simulator``); None when it cannot
        (the default: the limit is the whole story)."""
        return None

    def _forces(self, system, q, qd, time, offset, f_out=None):
        f = self.f if f_out is None else f_out
        system.eval_forces(q, qd, time, offset, f)
        return f


def _launch(kernel, system, inputs):
    wp.launch(kernel, system.count, inputs=inputs, device=system.device)


class ExplicitEuler(Integrator):
    """Explicit (forward) Euler: x1 = x0 + h v0, v1 = v0 + h a(x0, v0). Stability region
    |1 + h lambda| <= 1: an undamped spring (lambda = +-i omega) gains energy at every step size,
    a damped one is stable for h <= 2 zeta / omega (zeta its damping ratio)."""

    name = "explicit_euler"

    def step(self, system, q, qd, time, dt, f_out=None):
        self.prepare(system)
        f = self._forces(system, q, qd, time, 0.0, f_out)
        _launch(K.rk_stage, system, [q, qd, qd, f, system.inv_mass, dt, q, qd])


class SemiImplicitEuler(Integrator):
    """Semi-implicit (symplectic) Euler. On particle systems (``ParticleSystem``) one pass
    (``step_particles_semi_implicit``) integrates, hands out the step's force, clears the force
    accumulator for the next step seeded with the first force when that is ``ws.Gravity`` (so
    gravity costs no pass of its own), and optionally saves the start-of-step positions, advances
    the device clock and runs the blow-up test (``fused_step``). Results are bit-identical to
    separate passes. Masses are re-read every step; after changing ``model.particle_mass`` in
    place between steps call ``reseed()`` (gravity otherwise lags one step)."""

    name = "semi_implicit_euler"

    def _allocate(self, system):
        d = system.device
        self._fused = system.dtype is wp.vec3 and hasattr(system, "forces") and hasattr(system, "model")
        self._seed_key = None
        self._launches = {}
        self._none_vec3 = wp.zeros(0, dtype=wp.vec3, device=d)
        self._none_float = wp.zeros(0, dtype=float, device=d)
        self._none_int = wp.zeros(0, dtype=int, device=d)

    def fuses(self, system) -> bool:
        """True when ``fused_step`` serves ``system`` in one particle pass."""
        self.prepare(system)
        return self._fused

    def reseed(self) -> None:
        """Re-seed the force accumulator at the next step (after in-place mass changes)."""
        self._seed_key = None

    def step(self, system, q, qd, time, dt, f_out=None):
        self.prepare(system)
        if self._fused:
            self.fused_step(system, q, qd, time, dt, f_out)
            return
        f = self._forces(system, q, qd, time, 0.0, f_out)
        _launch(K.step_semi_implicit_euler, system, [q, qd, f, system.inv_mass, dt, q, qd])

    def fused_step(self, system, q, qd, time, dt, f_out=None, q_prev_out=None, advance_time=False, check=None):
        """One step of a particle system in place. ``q_prev_out`` (n,) receives the start-of-step
        positions; ``advance_time``: time[0] += dt; ``check`` = (max_speed [m/s], first_bad (1,)
        int array): atomic-min the index of a particle whose new state is non-finite or faster
        than max_speed into first_bad (as ``find_blow_up``; the caller keeps it at n otherwise)."""
        self.prepare(system)
        forces = system.forces
        first = forces[0] if forces else None
        seeded = type(first) is Gravity  # exactly uniform gravity (a subclass may override eval)
        g = first.g if seeded else (0.0, 0.0, 0.0)
        rest = forces[1:] if seeded else forces
        gravity = wp.vec3(*g)
        key = (id(first), tuple(g), id(system.mass))
        if key != self._seed_key:
            _launch(K.seed_forces, system, [system.mass, gravity, self.f])
            self._seed_key = key
        for force in rest:
            force.eval(q, qd, time, 0.0, self.f)
        max_speed, first_bad = (0.0, self._none_int) if check is None else check
        inputs = (self.f, system.mass, system.inv_mass, gravity, float(dt), q, qd,
                  self._none_vec3 if f_out is None else f_out, self._none_vec3 if q_prev_out is None else q_prev_out,
                  time if advance_time else self._none_float, int(check is not None), float(max_speed), first_bad)
        key = (system.count, *map(id, inputs[:3]), *map(id, inputs[5:10]), id(first_bad), float(dt), tuple(g),
               inputs[10], inputs[11])
        cached_launch(K.step_particles_semi_implicit, system.count, inputs, system.device, self._launches, key=key)


class RK2(Integrator):
    """Explicit midpoint: k1 at (q0, v0); the step uses the derivative at the half-step state."""

    name = "rk2"

    def _allocate(self, system):
        n, T, d = system.count, system.dtype, system.device
        self.q_mid = wp.zeros(n, dtype=T, device=d)
        self.qd_mid = wp.zeros(n, dtype=T, device=d)

    def step(self, system, q, qd, time, dt, f_out=None):
        self.prepare(system)
        w = system.inv_mass
        f = self._forces(system, q, qd, time, 0.0, f_out)
        _launch(K.rk_stage, system, [q, qd, qd, f, w, 0.5 * dt, self.q_mid, self.qd_mid])
        f = self._forces(system, self.q_mid, self.qd_mid, time, 0.5 * dt)
        _launch(K.rk_stage, system, [q, qd, self.qd_mid, f, w, dt, q, qd])


class RK4(Integrator):
    """Classical fourth-order Runge-Kutta (four force evaluations per step). Stability region
    |1 + z + z^2/2 + z^3/6 + z^4/24| <= 1 with z = h lambda: an undamped spring is stable for
    h omega <= 2 sqrt(2) (2.83), a purely damped mode for h |lambda| <= 2.785."""

    name = "rk4"

    def _allocate(self, system):
        n, T, d = system.count, system.dtype, system.device
        self.q_stage = wp.zeros(n, dtype=T, device=d)
        self.qd_stage = wp.zeros(n, dtype=T, device=d)
        self.v_sum = wp.zeros(n, dtype=T, device=d)
        self.f_sum = wp.zeros(n, dtype=T, device=d)

    def step(self, system, q, qd, time, dt, f_out=None):
        self.prepare(system)
        w, qs, qds = system.inv_mass, self.q_stage, self.qd_stage
        f = self._forces(system, q, qd, time, 0.0, f_out)
        _launch(K.rk_accumulate, system, [qd, f, 1.0, 0.0, self.v_sum, self.f_sum])
        _launch(K.rk_stage, system, [q, qd, qd, f, w, 0.5 * dt, qs, qds])
        for weight, offset, next_h in ((2.0, 0.5, 0.5), (2.0, 0.5, 1.0), (1.0, 1.0, None)):
            f = self._forces(system, qs, qds, time, offset * dt)
            _launch(K.rk_accumulate, system, [qds, f, weight, 1.0, self.v_sum, self.f_sum])
            if next_h is not None:
                _launch(K.rk_stage, system, [q, qd, qds, f, w, next_h * dt, qs, qds])
        _launch(K.rk_stage, system, [q, qd, self.v_sum, self.f_sum, w, dt / 6.0, q, qd])


class ImplicitEuler(Integrator):
    """Backward Euler with Newton iterations.

    newton_iterations: maximum Newton iterations per step; newton_tol: stop when
    max |dv| <= newton_tol [m/s] (checked on the host after each iteration, skipped when
    newton_iterations == 1); cg_tol: CG tolerance relative to |rhs|; cg_max_iterations: CG cap.
    linear_solver: "warp_cg" (``warp.optim.linear.cg``, stateful, block-Jacobi preconditioned),
    "block_cg" (warpsim's preallocated block-Jacobi CG with device-side scalars, ``BlockCG``;
    particle systems only) or "auto" (default): warp_cg on CUDA devices, block_cg for particle
    systems on the CPU, where warp_cg's tiled dot products cost ~10 ms per iteration (measured
    25x slower per step on a 520-particle soft body, same iterations and result).
    After each step ``last_newton_iterations``, ``last_cg_iterations`` and ``last_cg_residual``
    report what the solve did."""

    name = "implicit_euler"

    def __init__(self, newton_iterations: int = 4, newton_tol: float = 1.0e-6, cg_tol: float = 1.0e-7,
                 cg_max_iterations: int = 400, linear_solver: str = "auto"):
        super().__init__()
        if linear_solver not in ("auto", "warp_cg", "block_cg"):
            raise ValueError(f"linear_solver {linear_solver!r} is unknown; use 'auto', 'warp_cg' or 'block_cg'")
        self.linear_solver = linear_solver
        self.newton_iterations = checks.count(newton_iterations, "ImplicitEuler newton_iterations")
        self.newton_tol = checks.nonnegative(newton_tol, "ImplicitEuler newton_tol")
        self.cg_tol = checks.positive(cg_tol, "ImplicitEuler cg_tol", fix="a relative residual, e.g. 1e-7")
        self.cg_max_iterations = checks.count(cg_max_iterations, "ImplicitEuler cg_max_iterations")
        self.last_newton_iterations = 0
        self._cg_iterations = 0
        self._cg_residual = 0.0
        self._cg_unread = None  # a BlockCG whose stats were not read back (one Newton iteration)

    @property
    def last_cg_iterations(self) -> int:
        """CG iterations of the last step (summed over its Newton iterations)."""
        self._read_cg()
        return self._cg_iterations

    @property
    def last_cg_residual(self) -> float:
        """Final residual |b - A dv| of the last step's last CG solve (CG's recursive estimate)."""
        self._read_cg()
        return self._cg_residual

    def _read_cg(self) -> None:
        if self._cg_unread is not None:
            iterations, residual, _ = self._cg_unread.stats()
            self._cg_iterations, self._cg_residual = int(iterations), float(residual)
            self._cg_unread = None

    def _allocate(self, system):
        n, T, B, d = system.count, system.dtype, system.block_type, system.device
        self.q0 = wp.zeros(n, dtype=T, device=d)
        self.v0 = wp.zeros(n, dtype=T, device=d)
        self.rhs = wp.zeros(n, dtype=T, device=d)
        self.dv = wp.zeros(n, dtype=T, device=d)
        self.diag = wp.zeros(n, dtype=B, device=d)
        self.inverse = wp.zeros(n, dtype=B, device=d)
        self.max_dv = wp.zeros(1, dtype=float, device=d)
        m = n + system.jacobian_triplet_count()
        self.rows = wp.zeros(m, dtype=int, device=d)
        self.cols = wp.zeros(m, dtype=int, device=d)
        self.values = wp.zeros(m, dtype=B, device=d)
        self.A = wps.bsr_zeros(n, n, B, device=d)
        self._diagonal_slots = (self.rows[:n], self.cols[:n], self.values[:n])
        self._coupling_slots = (self.rows[n:], self.cols[n:], self.values[n:]) if m > n else (None, None, None)
        self._topology_built = False
        block = 3 if B is wp.mat33 else 1
        inverse = self.inverse

        def block_jacobi(x, y, z, alpha, beta):
            wp.launch(K.apply_block_preconditioner, n, inputs=[inverse, x, y, float(alpha), float(beta), z], device=d)

        self.preconditioner = wpl.LinearOperator((n * block, n * block), wp.float32, d, matvec=block_jacobi)
        # Stateful CG: its work buffers are allocated here, once. On the CPU the residual is
        # checked every iteration (a read-back costs nothing there); on GPUs every 10.
        solver = self.linear_solver
        if solver == "auto":
            solver = "block_cg" if d.is_cpu else "warp_cg"
        self.active_linear_solver = solver if B is wp.mat33 else "warp_cg"
        """The CG actually used ("warp_cg" or "block_cg")."""
        if self.active_linear_solver == "block_cg":
            block_cg = BlockCG(self.A, self.rhs, self.dv, self.inverse, rtol=self.cg_tol, atol=1.0e-12,
                               max_iterations=self.cg_max_iterations)

            def solve():
                block_cg.solve()
                if self.newton_iterations == 1:
                    # no host read-back inside the step (a CUDA graph can hold it): the stats are
                    # read when asked for (``last_cg_iterations``)
                    self._cg_unread = block_cg
                    return None
                return block_cg.stats()

            self.cg = solve
        else:
            self.cg = wpl.cg(self.A, self.rhs, self.dv, tol=self.cg_tol, atol=1.0e-12,
                             maxiter=self.cg_max_iterations, M=self.preconditioner,
                             check_every=1 if d.is_cpu else 10, use_cuda_graph=False, run=False)

    def assemble(self, system, q, qd, time, time_offset, h):
        """Fill the sparse system matrix A = M - h D - h^2 K at (q, qd) and its block-Jacobi inverse."""
        rows, cols, values = self._coupling_slots
        system.eval_jacobians(q, qd, time, time_offset, -h * h, -h, self.diag, rows, cols, values)
        _launch(K.implicit_system_diagonal, system,
                [self.diag, system.mass, system.inv_mass, *self._diagonal_slots, self.inverse])
        if rows is not None:
            wp.launch(K.filter_pinned_triplets, rows.shape[0], inputs=[rows, cols, system.inv_mass, values],
                      device=system.device)
        if not self._topology_built:
            wps.bsr_set_from_triplets(self.A, self.rows, self.cols, self.values, prune_numerical_zeros=False)
            self._topology_built = True
        else:
            wps.bsr_set_from_triplets(self.A, self.rows, self.cols, self.values, prune_numerical_zeros=False,
                                      topology="masked")

    def step(self, system, q, qd, time, dt, f_out=None):
        self.prepare(system)
        h = float(dt)
        if f_out is not None:
            # a backward Euler step moves along the straight line x0 + t v1 (no acceleration within
            # the step): the colliders' time of impact (reflect mode, ``kernels/collide.py``) reads
            # the path's acceleration from here. The start force's parabola, with spring forces of
            # thousands of m/s^2, gave a torus vertex 103 m/s at a floor impact at 1/240 s.
            f_out.zero_()
        wp.copy(self.q0, q)
        wp.copy(self.v0, qd)
        self.dv.zero_()
        _launch(K.implicit_update, system, [self.q0, self.dv, h, qd, q])  # q = q0 + h v0
        self._cg_iterations = 0
        self._cg_unread = None
        for it in range(self.newton_iterations):
            f = self._forces(system, q, qd, time, h)
            _launch(K.implicit_residual, system, [qd, self.v0, f, system.mass, system.inv_mass, h, self.rhs, self.dv])
            self.assemble(system, q, qd, time, h, h)
            stats = self.cg()
            if stats is not None:
                iterations, residual, _ = stats
                self._cg_iterations += int(iterations)
                self._cg_residual = float(residual)
            _launch(K.implicit_update, system, [self.q0, self.dv, h, qd, q])
            self.last_newton_iterations = it + 1
            if self.newton_iterations > 1:
                self.max_dv.zero_()
                _launch(K.max_abs_difference, system, [self.dv, self.max_dv])
                if float(self.max_dv.numpy()[0]) <= self.newton_tol:
                    break


INTEGRATORS = {
    cls.name: cls for cls in (ExplicitEuler, SemiImplicitEuler, ImplicitEuler, RK2, RK4)
}


def make_integrator(integrator) -> Integrator:
    """An Integrator from a name (see INTEGRATORS) or an Integrator instance."""
    if isinstance(integrator, Integrator):
        return integrator
    if isinstance(integrator, str) and integrator in INTEGRATORS:
        return INTEGRATORS[integrator]()
    valid = ", ".join(sorted(INTEGRATORS))
    raise ValueError(f"unknown integrator {integrator!r}; valid integrators: {valid}")
