"""FastMassSpring: backward Euler for copies of one spring body, by local-global iterations with
one prefactored matrix (Liu et al. 2013; the derivation is in ``warpsim.kernels.fast_mass_spring``).

Where ``implicit_euler`` solves each Newton iteration with CG (iterations growing with h^2 k / m:
60-80 a Newton iteration for the donuts' tori at 1/240 s), this step inverts the constant matrix
A = M + h C_L + h^2 K_L once, at the first step of a step size, and every iteration is a local pass
over the springs and one dense product per copy. No host read-back, no allocation: a CUDA graph can
hold the step. Converged, it is backward Euler (``ImplicitEuler``'s solution, tested); each
iteration lowers the step's incremental potential.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import warp as wp

from . import checks
from .forces import Springs
from .integrators import Integrator
from .model import ensure_spring_adjacency
from .stability import StabilityWarning
from ..kernels import fast_mass_spring as K

ERROR_LEFT = 0.2
"""FastMassSpring warns (``StabilityWarning``, before the first step of a step size) when its iterations
leave more than this fraction of a step's error, ``contraction() ** iterations``. Measured on the donuts'
heaps at 1/240 s (CPU and H100, ``benchmarks/RESULTS.md``): tori of 344 particles (rho 0.911) held with 20
iterations (0.16 left) and let edges through with 10 (0.40); tori of 2,124 (rho 0.980) let 7 edges through
with 40 (0.44) and 33 with 20 (0.66), and squashed with 10 (0.81)."""

MAX_BODY_PARTICLES = 8192
"""Largest body (particles of one copy) whose dense inverse is stored: 8192^2 float32 = 256 MiB."""


class FastMassSpring(Integrator):
    """Backward Euler for a model whose springs join copies of one body.

    Args:
        iterations: local-global iterations a step (default 10, as Liu et al.; more come closer to
            backward Euler's solution; each lowers the step's incremental potential, but a step stopped
            far from converged can gain energy: a torus of 1e5 N/m springs at 1/60 s went from 0.34
            to 46 J in its first step with 10 iterations; at 150 N/m, rises under 1 %).
        body_size: particles of one copy (P): copy t holds particles t P .. t P + P - 1, with the
            same springs, masses, stiffnesses and damping as copy 0 (checked at the first step).
            None: the whole model is one body.
        contacts: SoftContact objects (also among the Simulator's colliders) whose stored pairs are
            pushed apart inside the iterations; their contact vertices get the proximal pull.
        contact_passes: position passes of those pushes after each global step (default 4).
        contact_stiffness: k_c [N/m] of the proximal pull h^2 k_c that draws each contact vertex toward
            its pushed position in the next global step (default 2,000; stiffer slows the iterations:
            measured in ``benchmarks/RESULTS.md``).
        chebyshev: accelerate the iterations (Wang 2015) with weights from :meth:`contraction` rho:
            linear theory leaves 1 / T_N(1 / rho) of the error after N iterations instead of rho^N
            (T_N the Chebyshev polynomial); the same fixed point (tested), but the incremental
            potential no longer falls at every iteration. Off by default.

    Springs enter implicitly, with isotropic damping c_s (v_j - v_i); every other force of the
    system (gravity, drag, ...) at the start of the step, explicitly. ``contacts`` (SoftContact
    objects, also among the Simulator's colliders) push the pairs their last search found apart
    after every global step (``contact_passes`` position passes, ``SoftContact.project_positions``),
    so the springs of later iterations adapt to contact; the colliders then resolve the step's end
    as usual. Before the first step of a step size it warns (``StabilityWarning``) when the
    iterations leave more than ``ERROR_LEFT`` of a step's error (:meth:`contraction`). Pinned particles and
    breakable springs are refused (the matrix is constant). ``A^-1`` is computed on the host in
    float64 when the step size changes (0.40 s for P = 2,124 on the 2-core development machine).
    """

    name = "fast_mass_spring"
    explicit_forces = True
    """Forces other than the springs are taken at the step's start: the stability check gives a
    drag spring semi-implicit Euler's limit (``warpsim.core.stability.force_method_of``)."""

    def __init__(self, iterations: int = 10, body_size: int | None = None, contacts=(), contact_passes: int = 4,
                 contact_stiffness: float = 2000.0, chebyshev: bool = False):
        super().__init__()
        self.chebyshev = checks.flag(chebyshev, "FastMassSpring chebyshev")
        self.contacts = list(contacts)
        for k, c in enumerate(self.contacts):
            if not hasattr(c, "project_positions"):
                raise ValueError(f"FastMassSpring contacts[{k}] is {type(c).__name__}; give ws.SoftContact objects "
                                 "(also among the Simulator's colliders)")
        self.contact_stiffness = checks.nonnegative(contact_stiffness, "FastMassSpring contact_stiffness", unit="N/m",
                                                    fix="e.g. 2000")
        self.contact_passes = checks.integer(contact_passes, "FastMassSpring contact_passes", lo=1, hi=1000,
                                             fix="e.g. 1")
        self.iterations = checks.integer(iterations, "FastMassSpring iterations", lo=1, hi=10_000, fix="e.g. 10")
        self.body_size = None if body_size is None else checks.integer(
            body_size, "FastMassSpring body_size", lo=1, hi=1 << 40, fix="the particles of one copy, or None")
        self._h: float | None = None  # the step of the stored inverse [s]

    def _allocate(self, system):
        model = getattr(system, "model", None)
        if model is None or system.dtype is not wp.vec3:
            raise ValueError("FastMassSpring steps particle systems (springs of a Model); use implicit_euler for "
                             f"{type(system).__name__}")
        n, d = system.count, system.device
        P = n if self.body_size is None else self.body_size
        if n % P:
            raise ValueError(f"FastMassSpring body_size = {P} does not divide the model's {n} particles; give the "
                             "particles of one copy")
        if P > MAX_BODY_PARTICLES:
            raise ValueError(f"FastMassSpring: a body of {P} particles needs a {P} x {P} dense inverse "
                             f"({P * P * 4 / 2**20:.0f} MiB); at most {MAX_BODY_PARTICLES} particles a body: give "
                             "body_size (copies of one body) or use implicit_euler")
        self.P, self.T = P, n // P
        ensure_spring_adjacency(model)
        self._check_copies(model)
        self._other_forces = [f for f in system.forces if not isinstance(f, Springs)]
        self.f_ext = wp.zeros(n, dtype=wp.vec3, device=d)
        self.q0 = wp.zeros(n, dtype=wp.vec3, device=d)
        self.y = wp.zeros(n, dtype=wp.vec3, device=d)
        self.rhs = wp.zeros((3 * self.T, P), dtype=float, device=d)
        self.x = wp.zeros((3 * self.T, P), dtype=float, device=d)
        self.inverse = wp.zeros((P, P), dtype=float, device=d)
        self._contact_columns = np.zeros(P, dtype=bool)  # copy columns of contact vertices (proximal pull)
        for contact in self.contacts:
            self._contact_columns[contact.vertex_particles % P] = True
        self.proximal = wp.zeros(P, dtype=float, device=d)
        self._older = wp.zeros(n if self.chebyshev else 0, dtype=wp.vec3, device=d)
        self._old = wp.zeros(n if self.chebyshev else 0, dtype=wp.vec3, device=d)
        self._omegas: list = []
        self._h = None

    def _check_copies(self, model) -> None:
        """ValueError unless every copy has copy 0's springs, masses, stiffnesses and damping
        (and no particle is pinned, no spring breakable)."""
        P, T = self.P, self.T
        inv_mass = model.particle_inv_mass.numpy()
        pinned = np.flatnonzero(inv_mass == 0.0)
        if len(pinned):
            raise ValueError(f"FastMassSpring: particle {int(pinned[0])} is pinned (inverse mass 0); the step's "
                             "constant matrix has no pins: use implicit_euler")
        if model.breakable_spring_count:
            raise ValueError(f"FastMassSpring: the model has {model.breakable_spring_count} breakable springs; the "
                             "step's matrix is constant: use implicit_euler or semi_implicit_euler")
        S = model.spring_count
        if S % T:
            raise ValueError(f"FastMassSpring: {S} springs are not {T} equal copies; give body_size=None (one body)")
        ends = model.spring_indices.numpy().reshape(T, -1) if S else np.zeros((T, 0), dtype=np.int64)
        local = ends - (np.arange(T) * P)[:, None]
        per_spring = [model.spring_rest_length.numpy(), model.spring_stiffness.numpy(), model.spring_damping.numpy()]
        tables = [("spring ends", local)] + [(name, a.reshape(T, -1)) for name, a in
                                             zip(("rest lengths", "stiffnesses", "spring damping"), per_spring)]
        tables.append(("masses", model.particle_mass.numpy().reshape(T, P)))
        for name, table in tables:
            differs = np.flatnonzero((table != table[:1]).any(axis=1))
            if len(differs):
                raise ValueError(f"FastMassSpring: copy {int(differs[0])} (particles from {int(differs[0]) * P}) has "
                                 f"other {name} than copy 0; give body_size=None (one body) or identical copies")
        if S and (local.min() < 0 or local.max() >= P):
            raise ValueError(f"FastMassSpring: a spring of copy 0 joins particle {int(local.max())} outside the copy "
                             f"of {P} particles; give the body_size of one copy")
        self._x_first = model.particle_q.numpy()[:P].astype(np.float64)  # copy 0 where the run starts
        self._template = (local[0].reshape(-1, 2), per_spring[1][: S // T].astype(np.float64),
                          per_spring[2][: S // T].astype(np.float64),
                          model.particle_mass.numpy()[:P].astype(np.float64))
        # copy 0's CSR rows (its springs, in the model's fixed order) with each entry's other end
        offsets = model.particle_spring_offsets.numpy()[: P + 1]
        springs = model.particle_springs.numpy()[: offsets[-1]]
        ends = local[0].reshape(-1, 2)[springs]
        rows = np.repeat(np.arange(P), np.diff(offsets))
        d = model.device
        self._entry_offsets = wp.array(offsets, dtype=int, device=d)
        self._entry_other = wp.array(np.where(ends[:, 0] == rows, ends[:, 1], ends[:, 0]), dtype=int, device=d)
        self._entry_rest = wp.array(per_spring[0][springs], dtype=float, device=d)
        self._entry_springs = springs
        self._entry_stiffness = wp.zeros(len(springs), dtype=float, device=d)
        self._entry_damping = wp.zeros(len(springs), dtype=float, device=d)

    def system_matrix(self, h: float) -> np.ndarray:
        """A = M + h C_L + h^2 K_L of one copy (P x P, float64) for the step h [s]."""
        ends, k, c, mass = self._template
        w = h * h * k + h * c
        A = np.diag(mass)
        i, j = ends[:, 0], ends[:, 1]
        np.add.at(A, (i, i), w)
        np.add.at(A, (j, j), w)
        np.add.at(A, (i, j), -w)
        np.add.at(A, (j, i), -w)
        return A

    def _step_inverse(self, h: float) -> np.ndarray:
        """(A + W)^-1 for the step h (float64, P x P), W the contact vertices' proximal pull h^2 k_c."""
        w = h * h * self.contact_stiffness * self._contact_columns
        return np.linalg.inv(self.system_matrix(h) + np.diag(w))

    def contraction(self, h: float, iterations: int = 60, inverse: np.ndarray | None = None) -> float:
        """rho: the factor by which one iteration shrinks the error of a step of h [s], linearised at
        copy 0's positions at the first step: the largest eigenvalue (power iteration) of
        A^-1 (h^2 L_perp + W), L_perp the springs' stiffness across their directions (the part the
        local step leaves to the next iteration) and W the contact vertices' proximal pull. A spring
        of stiffness k between two particles of mass m: rho = 2 h^2 k / (m + 2 h^2 k) (tested)."""
        ends, k, _, _ = self._template
        x = self._x_first
        d = x[ends[:, 0]] - x[ends[:, 1]]
        d /= np.maximum(np.linalg.norm(d, axis=1), 1e-12)[:, None]
        w = h * h * self.contact_stiffness * self._contact_columns
        inverse = self._step_inverse(h) if inverse is None else inverse
        v = np.random.default_rng(0).normal(size=x.shape)
        rho = 0.0
        for _ in range(iterations):
            u = v[ends[:, 0]] - v[ends[:, 1]]
            u = (h * h * k)[:, None] * (u - (u * d).sum(1)[:, None] * d)
            f = w[:, None] * v
            for c in range(3):
                f[:, c] += np.bincount(ends[:, 0], u[:, c], len(x)) - np.bincount(ends[:, 1], u[:, c], len(x))
            v_next = inverse @ f
            size = float(np.linalg.norm(v_next))
            rho = size / float(np.linalg.norm(v))
            if size == 0.0:
                return 0.0
            v = v_next / size
        return rho

    def error_left(self, rho: float, iterations: int) -> float:
        """Linearised fraction of a step's error left after ``iterations``: rho^N, or with Chebyshev
        acceleration 1 / T_N(1 / rho) = 1 / cosh(N arccosh(1 / rho))."""
        if rho <= 0.0:
            return 0.0
        if not self.chebyshev:
            return rho ** iterations
        if rho >= 1.0:
            return 1.0
        return 1.0 / math.cosh(min(iterations * math.acosh(1.0 / rho), 700.0))

    def chebyshev_weights(self, rho: float) -> list:
        """Weights omega_k of the ``iterations`` accelerated iterations for contraction rho:
        omega_1 = 1, omega_2 = 2 / (2 - rho^2), omega_{k+1} = 4 / (4 - rho^2 omega_k) (Wang 2015)."""
        omegas = [1.0]
        for k in range(1, self.iterations):
            omegas.append(2.0 / (2.0 - rho * rho) if k == 1 else 4.0 / (4.0 - rho * rho * omegas[-1]))
        return omegas

    def _unconverged(self, h: float, rho: float) -> str | None:
        """What the iterations leave at step ``h`` [s] with contraction ``rho``, in words, when more than
        ``ERROR_LEFT`` of a step's error; else None."""
        left = self.error_left(rho, self.iterations)
        if left <= ERROR_LEFT:
            return None
        needed = next((n for n in range(1, 100_000) if self.error_left(rho, n) <= ERROR_LEFT), None) \
            if rho < 1.0 else None
        return (f"FastMassSpring: {self.iterations} iterations a step leave {left:.2g} of a step's error at "
                f"dt = {h:.4g} s (each iteration shrinks it by {rho:.3f}, linearised); under {ERROR_LEFT} "
                + (f"takes {needed}" if needed else "is out of reach"))

    def _warn_if_unconverged(self, h: float, rho: float) -> None:
        self._contraction_at = (h, rho)
        left = self._unconverged(h, rho)
        if left is not None:
            warnings.warn(left + ": with fewer the bodies come out softer than backward Euler and the energy "
                          "can rise; remedies: more iterations, a smaller step, or implicit_euler", StabilityWarning,
                          stacklevel=4)

    def energy_cause(self, h: float) -> str | None:
        """The iterations, when they leave more than ``ERROR_LEFT`` of a step's error at ``h`` [s] (the warning
        before the first step of that size said so): a step stopped that far from backward Euler's can gain
        energy."""
        known = getattr(self, "_contraction_at", None)  # (h, rho) of the step size set last
        left = None if known is None or known[0] != h else self._unconverged(h, known[1])
        if left is None:
            return None
        return (f"Cause: {left}, and a step stopped that far from backward Euler's can gain energy. Remedy: more "
                "iterations (FastMassSpring iterations, a scene's solver_iterations), a smaller step, or "
                "implicit_euler.")

    def _set_step(self, h: float) -> None:
        """Invert the matrix for the step h (host, float64; only when h changes) and warn when the
        iterations leave more than ``ERROR_LEFT`` of a step's error."""
        if self._h == h:
            return
        inverse = self._step_inverse(h)
        rho = self.contraction(h, inverse=inverse)
        self._omegas = self.chebyshev_weights(rho) if self.chebyshev else []
        self._warn_if_unconverged(h, rho)
        self.proximal.assign(h * h * self.contact_stiffness * self._contact_columns)
        _, k, c, _ = self._template
        self._entry_stiffness.assign(h * h * k[self._entry_springs])
        self._entry_damping.assign(h * c[self._entry_springs])
        self.inverse.assign(0.5 * (inverse + inverse.T))  # symmetric to the last bit: X = B A^-1 = (A^-1 B^T)^T
        self._h = h

    def step(self, system, q, qd, time, dt, f_out=None) -> None:
        self.prepare(system)
        h = float(dt)
        self._set_step(h)
        d, n = system.device, system.count
        if f_out is not None:
            f_out.zero_()  # a straight path within the step (see ImplicitEuler.step)
        self.f_ext.zero_()
        for force in self._other_forces:
            force.eval(q, qd, time, 0.0, self.f_ext)
        wp.launch(K.predict, n, inputs=[q, qd, self.f_ext, system.inv_mass, h, self.q0, self.y], device=d)
        springs = [self._entry_offsets, self._entry_other, self._entry_rest, self._entry_stiffness, self._entry_damping]
        # 64-wide tiles on CUDA once the batch fills them (H100, 1,000 tori: 1.08 ms a product against 1.45;
        # 12 tori, 36 rows: 0.16 against 0.12 ms); 32 on the CPU
        tile = 64 if d.is_cuda and 3 * self.T >= 128 else 32
        tiles = ((3 * self.T + tile - 1) // tile, (self.P + tile - 1) // tile)
        if self.chebyshev:
            wp.copy(self._older, q)
            wp.copy(self._old, q)
        for k in range(self.iterations):
            wp.launch(K.local_rhs, n, inputs=[q, self.q0, self.y, system.mass, *springs, self.proximal, self.P,
                                              self.rhs],
                      device=d)
            wp.launch_tiled(K.GLOBAL_SOLVE[tile], dim=tiles, inputs=[self.rhs, self.inverse, self.x], block_dim=K.TILE_THREADS,
                            device=d)
            wp.launch(K.scatter_positions, n, inputs=[self.x, self.P, q], device=d)
            if self.chebyshev:
                wp.launch(K.chebyshev_step, n, inputs=[q, self._omegas[k], self._older, self._old], device=d)
            for contact in self.contacts:
                contact.project_positions(q, self.contact_passes)
        wp.launch(K.finish_step, n, inputs=[q, self.q0, 1.0 / h, qd], device=d)
