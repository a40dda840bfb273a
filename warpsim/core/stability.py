"""Time-step restrictions: the largest stable step of a model with its integrator.

Each integrator is applied to the test equation of a damped oscillator,
``x'' = -omega^2 x - 2 zeta omega x'`` (the stiffest mode of the model), whose eigenvalues are
``lambda = omega (-zeta +- sqrt(zeta^2 - 1))``. A one-step method maps (x, v) by a matrix whose
eigenvalues must stay in the unit disc (|mu| <= 1):

- explicit Euler, R(z) = 1 + z with z = h lambda: |1 + z| <= 1. Complex lambda (zeta < 1):
  |1 + h lambda|^2 = 1 - 2 h omega zeta + h^2 omega^2 <= 1  <=>  h <= 2 zeta / omega (no stable step
  when zeta = 0: |1 + i h omega| > 1 for every h > 0). Real lambda (zeta >= 1): h <= 2 / |lambda|max.
- RK2 (explicit midpoint), R(z) = 1 + z + z^2/2: on the imaginary axis |R(iy)|^2 = 1 + y^4/4 > 1,
  so no stable step without damping; with damping the ray z = h lambda leaves the region at the
  root of |R|^2 = 1 (found numerically); real lambda: h <= 2 / |lambda|.
- RK4, R(z) = 1 + z + z^2/2 + z^3/6 + z^4/24: |R(iy)|^2 = 1 - y^6/72 + y^8/576 <= 1 for
  y <= 2 sqrt(2) (h <= 2.83 / omega undamped); real lambda: h <= 2.785 / |lambda|; in between
  the ray's exit point is found numerically.
- semi-implicit Euler (v1 = v0 + h a(x0, v0), x1 = x0 + h v1) is not a Runge-Kutta method; its
  matrix [[1 - h^2 w^2, h (1 - 2 zeta w h)], [-h w^2, 1 - 2 zeta w h]] (w = omega) has
  det = 1 - 2 zeta w h and trace = 2 - h^2 w^2 - 2 zeta w h. Of the Jury conditions,
  1 - trace + det = h^2 w^2 > 0 always holds, |det| < 1 needs h < 1 / (zeta w) and
  1 + trace + det = 4 - h^2 w^2 - 4 zeta w h > 0 needs h < 2 / (omega (zeta + sqrt(1 + zeta^2))),
  the tighter of the two (2 / omega undamped; damping lowers it).
- implicit Euler, R(z) = 1 / (1 - z): stable in the whole left half-plane, no restriction.

Assumptions of the model estimate (``particle_limits``):
- omega^2 is the largest eigenvalue of M^-1 K, K the stiffness of the model's unbroken springs
  linearised at the current positions (axial k d d^T plus the clamped geometric term
  k max(0, 1 - L/l) (I - d d^T)); pinned particles (mass 0) do not move and are excluded. It is
  estimated by power iteration (a Rayleigh quotient, a lower bound that converges to omega^2) and
  bounded above by a block-Gershgorin row sum (``omega_bound``).
- The mode's damping 2 zeta omega is the Rayleigh quotient of M^-1 D on the same vector, D the
  springs' dampers plus linear ``Drag``; this is exact for a single spring and for damping
  proportional to stiffness (modes then decouple), an estimate otherwise.
- Other forces (magnets, wind, user fields, quadratic drag) are taken as non-stiff.
- A drag spring holding a particle (``ws.DragSpring``) is a separate oscillator k / m of that
  particle in the integrator's region.
- Penalty colliders (``mode="penalty"``) act after every integrator as a velocity impulse, i.e.
  like semi-implicit Euler on a spring k_c to a fixed point, omega_c = sqrt(k_c / m), damping
  ratio from their restitution; they are a separate oscillator (limit taken as the smaller of
  the two), whatever the integrator (implicit Euler too).
- Colliders that resolve a contact only approximately at large steps set a step-size limit of
  their own (``collider.step_distances(model, positions)``: per particle, the most it may move in
  one step, e.g. a plane in ``mode="seed"`` or ``"project"``: the larger of the particle's collision
  thickness and its fall height above the plane; soft contact: its thickness). A particle moving
  at |v| under gravity g covers |v| dt + |g| dt^2 per step (the issue's v dt and g dt^2), so
  dt <= (sqrt(|v|^2 + 4 |g| L) - |v|) / (2 |g|). Planes and shapes in ``"reflect"`` mode resolve
  contact at the time of impact and ``"penalty"`` ones are limited by their stiffness: no
  distance limit.
- Linear theory: a step at the limit is marginal; nonlinear springs, contacts and large
  rotations can need a smaller one, hence the safety factor of ``substeps="auto"``.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field

import numpy as np
import warp as wp

from ..kernels import stability as K
from .energy import gravity_of
from .segments import any_per_world, first_extreme

__all__ = ["AUTO_SAFETY", "StabilityLimit", "StabilityWarning", "SubstepCapWarning", "method_of", "particle_limits", "pendulum_limit",
           "stable_step", "stable_steps", "worlds_warning"]

AUTO_SAFETY = 0.5
"""``substeps="auto"`` steps at most this fraction of the stability limit."""

AUTO_MAX_SUBSTEPS = 100000
"""The most sub-steps ``substeps="auto"`` takes per frame."""

POWER_ITERATIONS = 80
"""Power iterations of the stiffest-mode estimate."""

INCOHERENT_RATIO = 3.0
INCOHERENT_SPEED = 0.5  # [m/s]
INCOHERENT_FRAMES = 2
"""The frame test for instabilities that neither NaN nor the speed bound catch: a particle
INCOHERENT_RATIO x faster (and above INCOHERENT_SPEED) than any particle of its world moved over
the frame, INCOHERENT_FRAMES frames in a row, is a step above the stability limit: the stiffest
mode flips sign every step, so velocities grow while positions barely move (measured on the
teapot: stable runs and scenes stay below 2x, the hidden 40-55 m/s teapots reach 15x)."""

METHODS = {
    "explicit_euler": "explicit_euler",
    "semi_implicit_euler": "semi_implicit_euler",
    "implicit_euler": "implicit_euler",
    "rk2": "rk2",
    "rk4": "rk4",
    "cloth_semi_implicit_euler": "semi_implicit_euler",
    "cloth_implicit_euler": "implicit_euler",
    "strand_implicit_euler": "implicit_euler",
    "fast_mass_spring": "implicit_euler",  # backward Euler's springs (other forces explicit: gravity, drag)
    "vbd": "implicit_euler",  # backward Euler's incremental potential, descended block by block (ws.VBD)
}
"""Integrator name -> the method whose stability region it has."""

STABILITY_NOTES = {"vbd": "vertex block descent is unconditionally stable, accuracy set by iterations"}
"""Integrator name -> what the stability report says of it where its region alone says too little
(``ws.VBD`` stops its descent after a number of iterations: any step is stable, the iterations set
how close it comes to backward Euler)."""


def note_of(integrator) -> str | None:
    """What the stability report says of ``integrator`` (a name or an instance) in its own words: the instance's
    ``stability_note`` where it has one (``ws.VBD``: not unconditional with Chebyshev acceleration on), else
    ``STABILITY_NOTES`` by name; None: its stability region says it all."""
    own = getattr(integrator, "stability_note", None)
    if isinstance(own, str):
        return own
    return STABILITY_NOTES.get(getattr(integrator, "name", integrator))


class StabilityWarning(UserWarning):
    """A time step above the model's stability limit (see ``Simulator.stability()``)."""


def force_method_of(integrator) -> str:
    """The stability region of the forces an integrator takes explicitly (drag springs, ...):
    semi-implicit Euler's for integrators that set ``explicit_forces`` (ws.FastMassSpring: springs
    implicit, other forces at the step's start), else the integrator's own (:func:`method_of`)."""
    return "semi_implicit_euler" if getattr(integrator, "explicit_forces", False) else method_of(integrator)


def method_of(integrator) -> str:
    """The stability-region name of an integrator (name or instance); ValueError if unknown."""
    name = integrator if isinstance(integrator, str) else getattr(integrator, "name", "")
    if name not in METHODS:
        raise ValueError(f"integrator {name or integrator!r} has no known stability region; known: "
                         f"{', '.join(sorted(METHODS))}")
    return METHODS[name]


# ----------------------------------------------------------------------------- regions
_POLYNOMIALS = {"explicit_euler": (1.0, 1.0), "rk2": (1.0, 1.0, 0.5), "rk4": (1.0, 1.0, 0.5, 1.0 / 6.0, 1.0 / 24.0)}


def _ray_exit(method: str, theta: float) -> float:
    """Largest x such that |R(s e^{i theta})| <= 1 for all 0 < s <= x (R the method's stability
    polynomial, theta the direction of lambda in the left half-plane); 0 if the ray starts outside."""
    coeffs = _POLYNOMIALS[method][::-1]
    direction = complex(math.cos(theta), math.sin(theta))
    tol = 1.0e-12

    def outside(x):
        return abs(np.polyval(coeffs, x * direction)) ** 2 > 1.0 + tol

    xs = np.concatenate([np.geomspace(1.0e-7, 1.0e-2, 200, endpoint=False), np.linspace(1.0e-2, 4.0, 4000)])
    values = np.abs(np.polyval(coeffs, xs * direction)) ** 2 > 1.0 + tol
    first = int(np.argmax(values)) if values.any() else -1
    if first < 0:
        return 4.0
    if first == 0:
        return 0.0
    lo, hi = float(xs[first - 1]), float(xs[first])
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if outside(mid):
            hi = mid
        else:
            lo = mid
    return lo


def stable_step(method: str, omega: float, zeta: float = 0.0) -> float:
    """Largest stable step [s] of ``method`` (see module docstring) on a damped oscillator of
    natural frequency ``omega`` [rad/s] and damping ratio ``zeta`` [1]: inf when omega == 0 or the
    method is implicit Euler, 0.0 when no step is stable."""
    method = METHODS.get(method, method)
    omega, zeta = float(omega), max(0.0, float(zeta))
    if method == "implicit_euler" or not omega > 0.0:
        return math.inf
    if not math.isfinite(omega):
        return 0.0
    if method == "semi_implicit_euler":
        return 2.0 / (omega * (zeta + math.sqrt(1.0 + zeta * zeta)))
    if method not in _POLYNOMIALS:
        raise ValueError(f"unknown method {method!r}")
    if zeta >= 1.0:  # two real eigenvalues; the larger one limits
        lam = omega * (zeta + math.sqrt(zeta * zeta - 1.0))
        return _ray_exit(method, math.pi) / lam
    if method == "explicit_euler":
        return 2.0 * zeta / omega
    if zeta == 0.0 and method == "rk2":
        return 0.0
    theta = math.pi - math.acos(zeta)  # lambda = omega (-zeta + i sqrt(1 - zeta^2)), |lambda| = omega
    return _ray_exit(method, theta) / omega


def stable_steps(method: str, omega, zeta) -> np.ndarray:
    """``stable_step`` element-wise over arrays (damping ratios rounded to 6 digits for the
    numerical regions)."""
    omega = np.asarray(omega, dtype=np.float64)
    zeta = np.broadcast_to(np.asarray(zeta, dtype=np.float64), omega.shape)
    method = METHODS.get(method, method)
    out = np.full(omega.shape, np.inf)
    live = omega > 0.0
    if method == "implicit_euler" or not live.any():
        return out
    w, z = omega[live], np.maximum(zeta[live], 0.0)
    if method == "semi_implicit_euler":
        out[live] = 2.0 / (w * (z + np.sqrt(1.0 + z * z)))
        return out
    z = np.round(z, 6)
    unique, inverse = np.unique(z, return_inverse=True)
    unit = np.array([stable_step(method, 1.0, u) for u in unique])  # x_max for omega = 1
    out[live] = unit[inverse] / w
    return out


class SubstepCapWarning(UserWarning):
    """substeps='auto' needs more sub-steps than its cap (:data:`AUTO_MAX_SUBSTEPS`): the run is
    not made stable by sub-stepping; the warning names the figure and the other remedies."""


# ----------------------------------------------------------------------------- the limit
@dataclass
class StabilityLimit:
    """The largest stable step of a model and what sets it.

    Attributes:
        dt: largest stable step [s] (inf: unrestricted; 0.0: no step is stable).
        integrator: the stability region used ("semi_implicit_euler", ...).
        omega_max: angular frequency of the stiffest mode [rad/s].
        damping_ratio: damping ratio zeta of that mode [1].
        limiting: what sets it: "spring", "particle", "collider", "pendulum" or "none".
        index: index of that spring / particle / pendulum (-1 for none).
        stiffness: its stiffness [N/m] (k_c for a collider; g/l [1/s^2] for a pendulum).
        mass: the lightest moving mass it joins [kg].
        damping: its damping [N s/m].
        particle: the particle moving most in the stiffest mode (-1 if none).
        omega_bound: Gershgorin upper bound of omega_max [rad/s].
        reason: one sentence explaining the limit.
        spring_dt: per spring, the limit of that spring alone [s], shape (spring_count,).
        particle_dt: per particle, the limit from its Gershgorin row [s], shape (particle_count,).
    """

    dt: float
    integrator: str
    omega_max: float = 0.0
    damping_ratio: float = 0.0
    limiting: str = "none"
    index: int = -1
    stiffness: float = 0.0
    mass: float = 0.0
    damping: float = 0.0
    particle: int = -1
    omega_bound: float = 0.0
    reason: str = ""
    spring_dt: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)
    particle_dt: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)

    def per_spring(self) -> np.ndarray:
        """Stable step [s] of each spring on its own (its two masses, pins fixed)."""
        return self.spring_dt

    def per_particle(self) -> np.ndarray:
        """Stable step [s] bounded from each particle's Gershgorin row (the modes touching it)."""
        return self.particle_dt

    def exceeded_by(self, dt: float) -> bool:
        """True when a step of ``dt`` [s] is above the limit (beyond float rounding)."""
        return float(dt) > self.dt * (1.0 + 1.0e-6)

    def who(self) -> str:
        """The limiter in words, e.g. "spring 12 (k = 40 N/m, m = 0.0025 kg)"."""
        if self.limiting == "none":
            return "nothing stiff"
        if self.limiting == "pendulum":
            return f"pendulum {self.index} (g/l = {self.stiffness:.4g} 1/s^2)"
        if self.limiting == "collider" and self.stiffness == 0.0:
            return f"collider {self.index} on particle {self.particle} (a step may not carry it past the contact)"
        return f"{self.limiting} {self.index} (k = {self.stiffness:.4g} N/m, m = {self.mass:.4g} kg)"

    def warning(self, dt: float) -> str:
        """One line for a step ``dt`` [s] above the limit: limiter, k, m, limit and remedies."""
        if self.dt == 0.0:
            return (f"dt = {dt:.4g} s is unstable for {self.integrator}: {self.reason}; remedies: "
                    "integrator semi_implicit_euler, rk4 or implicit_euler (or add damping)")
        if self.limiting == "collider" and self.stiffness == 0.0:
            return (f"dt = {dt:.4g} s is above the contact limit {self.dt:.4g} s: {self.reason}; a larger step "
                    f"carries particles past the contact and the collider adds energy; remedies: a step <= "
                    f"{self.dt:.4g} s (substeps='auto' in Python, --substeps auto on the command line) or "
                    "mode='reflect' (resolved at the time of impact)")
        return (f"dt = {dt:.4g} s is above the stability limit {self.dt:.4g} s of {self.integrator} set by "
                f"{self.who()} (omega = {self.omega_max:.4g} rad/s): it will blow up; remedies: a step <= "
                f"{self.dt:.4g} s (more sub-steps: substeps='auto' in Python, --substeps auto on the command line) or "
                "integrator implicit_euler")

    def substeps_for(self, frame_dt: float, safety: float = AUTO_SAFETY, minimum: int = 1) -> int:
        """Sub-steps per frame of ``frame_dt`` [s] that keep each step <= safety x dt."""
        if not math.isfinite(self.dt):
            return int(minimum)
        if self.dt <= 0.0:
            return int(minimum)  # nothing helps; the warning says so
        n = math.ceil(float(frame_dt) / (safety * self.dt) - 1.0e-9)
        if n > AUTO_MAX_SUBSTEPS:  # said, not silent: more sub-steps cannot help at this cost
            import warnings

            warnings.warn(f"substeps='auto' (--substeps auto) needs {n} sub-steps per frame of {float(frame_dt):.4g} s "
                          f"(stable step {self.dt:.3g} s, {self.reason or 'set by the model'}) but stops at its cap of "
                          f"{AUTO_MAX_SUBSTEPS}, so the run will blow up; use integrator implicit_euler, a shorter frame "
                          "(higher fps) or a softer/heavier model", SubstepCapWarning, stacklevel=2)
        return int(min(AUTO_MAX_SUBSTEPS, max(minimum, n)))


def limit_reason(method, omega, zeta, dt, who, note=None):
    """Why the step limit ``dt`` [s] of integrator ``method`` is what it is, for the stiffest mode
    ``omega`` [rad/s] with damping ratio ``zeta`` that ``who`` names (one sentence for warnings);
    ``note``: the integrator's own words (``STABILITY_NOTES``) in place of the region's."""
    if omega == 0.0:
        return "no spring, penalty contact or other stiff force: no step restriction" + (f"; {note}" if note else "")
    head = f"stiffest mode omega = {omega:.4g} rad/s, zeta = {zeta:.3g} ({who})"
    if note:
        return f"{head}; {note}"
    if method == "implicit_euler":
        return f"{head}; implicit Euler is stable for every step"
    if dt == 0.0:
        return (f"{head}; {method} has no stable step for an undamped oscillator (its amplification "
                f"|R(i h omega)| > 1 for every h > 0)")
    rule = {"semi_implicit_euler": "2 / (omega (zeta + sqrt(1 + zeta^2)))",
            "explicit_euler": "2 zeta / omega" if zeta < 1.0 else "2 / |lambda|",
            "rk2": "the RK2 region's edge", "rk4": "the RK4 region's edge (2.83 / omega undamped)"}[method]
    return f"{head}; {method} is stable for dt <= {rule} = {dt:.4g} s"


def worlds_warning(limits, dt, labels=None):
    """One line when a step ``dt`` [s] (a number, or one per world) is above the limit of some of
    ``limits`` (one per world; ``labels``: text per world, e.g. its varied parameters), naming the
    count and the worst world; None when every world is inside."""
    steps = np.broadcast_to(np.asarray(dt, dtype=np.float64), (len(limits),))
    bad = [w for w, limit in enumerate(limits) if limit.exceeded_by(float(steps[w]))]
    if not bad:
        return None
    worst = min(bad, key=lambda w: limits[w].dt / steps[w])
    label = f" ({labels[worst]})" if labels and labels[worst] else ""
    return f"{len(bad)} of {len(limits)} worlds step above their stability limit; world {worst}{label}: " + \
        limits[worst].warning(float(steps[worst]))


def with_force_limits(limit, forces, positions, integrator) -> StabilityLimit:
    """The smaller of ``limit`` and the limits of forces that estimate their own
    (``force.stability_limit(positions, integrator, forces)`` -> StabilityLimit or None, e.g.
    hair's ``StrandForce``; ``forces``: all of them, for the damping they add)."""
    for f in forces or ():
        own = getattr(f, "stability_limit", None)
        other = own(positions, integrator, forces) if own is not None else None
        if other is not None and other.dt < limit.dt:
            limit = other
    return limit


def pendulum_limit(g_over_l, integrator) -> StabilityLimit:
    """Limit of angle-form pendulums q'' = -(g/l) sin q linearised about the bottom
    (omega = sqrt(g/l), undamped); ``g_over_l`` [1/s^2] per pendulum."""
    method = method_of(integrator)
    g_over_l = np.atleast_1d(np.asarray(g_over_l, dtype=np.float64))
    per = stable_steps(method, np.sqrt(g_over_l), 0.0)
    k = int(np.argmax(g_over_l))
    omega = math.sqrt(float(g_over_l[k]))
    dt = stable_step(method, omega, 0.0)
    return StabilityLimit(dt=dt, integrator=method, omega_max=omega, limiting="pendulum", index=k,
                          stiffness=float(g_over_l[k]), omega_bound=omega, particle=k,
                          reason=limit_reason(method, omega, 0.0, dt, f"pendulum {k}, omega = sqrt(g/l)"),
                          particle_dt=per)


def _adjacency(model):
    """CSR (offsets, spring, other particle) of the model's springs per particle, in spring order,
    and the springs' ends (S, 2) on the host (:func:`_device_adjacency`, :func:`_spring_ends`)."""
    return (*_device_adjacency(model), _spring_ends(model))


def _device_adjacency(model):
    """CSR (offsets, spring, other particle) of the model's springs per particle, in spring order:
    the model's own CSR (``particle_spring_offsets``, ``particle_springs``: a batch tiles world 0's
    on the device), each entry's other end found on the device (cached on the model)."""
    from .model import ensure_spring_adjacency

    n, S = model.particle_count, model.spring_count
    cached = getattr(model, "_stability_adjacency", None)
    if cached is not None and cached[0] == (n, S):
        return cached[1]
    d = model.device
    if S:
        ensure_spring_adjacency(model)
        offsets, springs = model.particle_spring_offsets, model.particle_springs
        other = wp.empty(2 * S, dtype=int, device=d)
        wp.launch(K.other_ends, n, inputs=[offsets, springs, model.spring_indices, other], device=d)
        value = (offsets, springs, other)
    else:
        value = (wp.zeros(n + 1, dtype=int, device=d), wp.zeros(1, dtype=int, device=d), wp.zeros(1, dtype=int, device=d))
    model._stability_adjacency = ((n, S), value)
    return value


def _spring_ends(model, count=None):
    """The ends (count, 2) int64 of the model's first ``count`` springs (None: all) on the host."""
    S = model.spring_count if count is None else int(count)
    return model.spring_indices[:2 * S].numpy().reshape(-1, 2).astype(np.int64) if S else np.zeros((0, 2), np.int64)


SPRING_BLOCK = 1 << 16
"""Springs per host block of the per-spring estimates of a batch's worlds: temporaries of a few MB
that stay in the caches (arrays of every world's springs went through memory once an operation)."""
HOST_THREADS = 8
"""Threads at most that work on those blocks side by side."""


class _HostSprings:
    """The per-spring host work of :func:`particle_limits`: each spring's own limit and, after the
    power iteration, each world's spring storing most of the mode's energy. ``tiled`` (P, S): the
    model is ``W`` copies of one world (world w's particles w P.., springs w S.., ends world 0's
    + w P): the work goes by blocks of whole worlds from world 0's ends; else all springs at once,
    each world's springs found by one stable sort. Both give every value the same bits (the same
    element-wise operations on the same elements)."""

    def __init__(self, model, tiled, world, W):
        S, n = model.spring_count, model.particle_count
        self.tiled = tiled is not None and tiled[1] > 0 and S == W * tiled[1] and n == W * tiled[0]
        self.W = W
        if self.tiled:
            self.P0, self.S0 = int(tiled[0]), int(tiled[1])
            self.ends0 = _spring_ends(model, self.S0)
            per = max(1, SPRING_BLOCK // self.S0)
            self.blocks = [(w0, min(W, w0 + per)) for w0 in range(0, W, per)]
        else:
            self.ends0 = _spring_ends(model)
            self.blocks = [(0, W)]
            spring_world = world[self.ends0[:, 0]] if S else np.zeros(0, dtype=np.int64)
            self.order = np.argsort(spring_world, kind="stable")
            self.start = np.searchsorted(spring_world[self.order], np.arange(W + 1))
        self.best = np.zeros(W, dtype=np.int64)  # (find_strongest: per world, tiled)
        self.energy = np.zeros(S)  # (find_strongest: per spring, not tiled)

    def _span(self, block):
        """The springs of ``block`` as a slice."""
        return slice(block[0] * self.S0, block[1] * self.S0) if self.tiled else slice(0, len(self.ends0))

    def _take(self, a, block, end):
        """``a[ends[:, end]]`` of ``block``'s springs (a: per particle, (n,) or (n, 3)): np.take of
        world 0's ends from the block's rows (the same values, without the block's ends array)."""
        if not self.tiled:
            return np.take(a, self.ends0[:, end], axis=0)
        w0, w1 = block
        rows = a[w0 * self.P0:w1 * self.P0].reshape(w1 - w0, self.P0, *a.shape[1:])
        return np.take(rows, self.ends0[:, end], axis=1).reshape(-1, *a.shape[1:])

    def ends(self, s):
        """The two particles of spring ``s``."""
        if not self.tiled:
            return self.ends0[s]
        return self.ends0[s % self.S0] + (s // self.S0) * self.P0

    def _each_block(self, fn):
        """``fn(block)`` for every block, in threads when there are several (NumPy lets go of the
        GIL in its loops; each block writes its own slices: the same values in any order)."""
        from concurrent.futures import ThreadPoolExecutor

        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
        threads = min(len(self.blocks), HOST_THREADS, cores)
        if threads < 2:
            for block in self.blocks:
                fn(block)
            return
        with ThreadPoolExecutor(threads) as pool:
            for _ in pool.map(fn, self.blocks):  # (raises the first block's error, if any)
                pass

    def steps(self, method, k32, c32, broken, inv_mass, drag):
        """Each spring's own limit [s] (per spring on its own: omega_s^2 = k (1/m_i + 1/m_j),
        zeta_s = c (1/m_i + 1/m_j) / (2 omega_s)); ``k32``, ``c32``: host arrays as stored."""
        out = np.empty(len(k32))

        def block_steps(block):
            span = self._span(block)
            k, c = k32[span].astype(np.float64), c32[span].astype(np.float64)
            w_sum = self._take(inv_mass, block, 0) + self._take(inv_mass, block, 1)
            omega_s = np.sqrt(np.maximum(k, 0.0) * w_sum)
            with np.errstate(divide="ignore", invalid="ignore"):
                zeta_s = np.where(omega_s > 0, (c * w_sum + drag * w_sum / 2) / (2.0 * omega_s), 0.0)
            out[span] = stable_steps(method, omega_s, zeta_s)

        self._each_block(block_steps)
        out[broken] = np.inf
        return out

    def find_strongest(self, q, vh, k32, broken):
        """Note each world's spring of most energy k (strain along it)^2 in the mode ``vh`` (n, 3)
        about the positions ``q`` (n, 3) [float64] (:meth:`strongest`)."""

        def block_strongest(block):
            span = self._span(block)
            dirs = self._take(q, block, 1) - self._take(q, block, 0)
            lengths = dirs[:, 0] * dirs[:, 0]  # np.linalg.norm(dirs, axis=1): the squares summed in order
            lengths += dirs[:, 1] * dirs[:, 1]
            lengths += dirs[:, 2] * dirs[:, 2]
            lengths = np.sqrt(lengths)
            dirs /= np.where(lengths > 0, lengths, 1.0)[:, None]
            strain = np.einsum("ij,ij->i", self._take(vh, block, 0) - self._take(vh, block, 1), dirs)
            energy = np.where(broken[span], 0.0, k32[span].astype(np.float64) * strain * strain)
            if not self.tiled:  # (one block)
                self.energy = energy
                return
            w0, w1 = block  # the first of equal energies, as np.argmax over the world's springs
            self.best[w0:w1] = energy.reshape(w1 - w0, self.S0).argmax(axis=1) + np.arange(w0, w1) * self.S0

        self._each_block(block_strongest)

    def strongest(self, w) -> int:
        """World ``w``'s spring of most energy (after :meth:`find_strongest`)."""
        if self.tiled:
            return int(self.best[w])
        springs = self.order[self.start[w]:self.start[w + 1]]
        return int(springs[np.argmax(self.energy[springs])])

    def world_steps(self, spring_dt, w):
        """World ``w``'s springs' own limits (all of them for one world)."""
        if self.W == 1:
            return spring_dt
        if self.tiled:
            return spring_dt[w * self.S0:(w + 1) * self.S0]
        return spring_dt[self.order[self.start[w]:self.start[w + 1]]]


def synchronised_energy(integrator) -> bool:
    """True when ``integrator`` has semi-implicit Euler's stability region (cloth's fused one too): the
    energy balance then reads its modified energy (``warpsim.core.energy``)."""
    try:
        return method_of(integrator) == "semi_implicit_euler"
    except ValueError:
        return False


def _penalty(colliders):
    """(stiffness [N/m], damping ratio) of the stiffest penalty collider, or (0, 0)."""
    best = (0.0, 0.0)
    for c in colliders or ():
        if getattr(c, "mode_name", None) == "penalty" and float(getattr(c, "stiffness", 0.0)) > best[0]:
            best = (float(c.stiffness), float(getattr(c, "damping_ratio", 0.0)))
    return best


def _point_springs(forces):
    """(particle, stiffness [N/m], damping [N s/m]) of springs pulling one particle to a target
    (``ws.DragSpring`` while it holds a particle)."""
    out = []
    for f in forces or ():
        particle = getattr(f, "particle", None)
        if isinstance(particle, (int, np.integer)) and particle >= 0 and hasattr(f, "stiffness") \
                and hasattr(f, "target_at"):
            out.append((int(particle), float(f.stiffness), float(getattr(f, "damping", 0.0))))
    return out


def _linear_drag(forces):
    from .forces import Drag

    return float(sum(f.linear for f in forces or () if isinstance(f, Drag)))


def _collider_steps(model, positions, velocities, colliders, gravity, world):
    """Per particle: the step-size limit [s] from the colliders' step distances (module docstring),
    inf where none applies, and the collider setting it (index into ``colliders``, -1 none), and L [m].
    ``velocities`` [m/s] (None: the model's initial ones), ``gravity`` [m/s^2] per world (W, 3),
    ``world`` each particle's: read only once a collider has step distances."""
    n = model.particle_count
    dt = np.full(n, np.inf)
    which = np.full(n, -1, dtype=np.int64)
    dist = np.zeros(n)
    q = speed = None
    v = None if velocities is None else np.asarray(velocities, dtype=np.float64).reshape(n, 3)
    for c_index, c in enumerate(colliders):
        own = getattr(c, "step_distances", None)
        if own is not None and q is None:
            q = positions.numpy().astype(np.float64) if hasattr(positions, "numpy") else np.asarray(positions, float)
        L = own(model, q) if own is not None else None
        if L is None:
            continue
        if speed is None:
            if v is None:  # the initial velocities
                v = model.particle_qd.numpy().astype(np.float64).reshape(n, 3)
            speed = np.linalg.norm(v, axis=1)
            g = np.linalg.norm(np.asarray(gravity[world], dtype=np.float64).reshape(-1, 3), axis=1)
            if len(g) != n:
                g = np.full(n, float(g[0]) if len(g) else 0.0)
            moving = model.particle_inv_mass.numpy() > 0.0
        L = np.asarray(L, dtype=np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            limit = np.where(g > 0, (np.sqrt(speed * speed + 4.0 * g * L) - speed) / (2.0 * np.where(g > 0, g, 1.0)),
                             np.where(speed > 0, L / np.where(speed > 0, speed, 1.0), np.inf))
        limit = np.where(moving & (L > 0) & np.isfinite(L), limit, np.inf)
        better = limit < dt
        dt[better], which[better], dist[better] = limit[better], c_index, L[better]
    return dt, which, dist


def particle_limits(model, positions, integrator, forces=(), colliders=(), *, particle_world=None,
                    world_count: int = 1, iterations: int = POWER_ITERATIONS, velocities=None, tiled=None) -> list:
    """One :class:`StabilityLimit` per world of a particle model (see module docstring).

    ``positions``: wp.array of vec3 (particle_count,) about which springs are linearised;
    ``particle_world``: host int array (particle_count,) of world indices (None: one world);
    ``velocities``: (particle_count, 3) [m/s] for the colliders' distance limits (None: the model's
    initial velocities); ``tiled``: (P, S) when the model is ``world_count`` copies of one world of P
    particles and S springs (a batch's: particles and springs world by world, each world's ends world
    0's + w P, ``particle_world`` = particle // P): the per-spring host work then goes by blocks of
    whole worlds, the same values (None: any model)."""
    method = method_of(integrator)
    force_method = force_method_of(integrator)
    n, S, d = model.particle_count, model.spring_count, model.device
    host_q = positions.numpy() if hasattr(positions, "numpy") else np.asarray(positions, dtype=np.float64)
    q64 = np.asarray(host_q, dtype=np.float64).reshape(-1, 3)  # (also find_strongest's)
    bad = np.flatnonzero(~np.isfinite(q64).all(axis=1))
    if len(bad):
        raise ValueError(f"particle {int(bad[0])} has a non-finite position {host_q[bad[0]]}: the stability limit "
                         "is taken about finite positions; give finite values (or restore the state from before "
                         "the blow-up)")
    inv_mass = model.particle_inv_mass.numpy().astype(np.float64)
    mass = model.particle_mass.numpy().astype(np.float64)
    moving = inv_mass > 0.0
    world = np.zeros(n, dtype=np.int64) if particle_world is None else np.asarray(particle_world, dtype=np.int64)
    W = int(world_count)
    offsets, adj_spring, adj_other = _device_adjacency(model)
    springs = _HostSprings(model, tiled, world, W)
    k = model.spring_stiffness.numpy() if S else np.zeros(0)  # (as stored: float64 block by block)
    c = model.spring_damping.numpy() if S else np.zeros(0)
    broken = model.spring_broken.numpy() != 0 if S and hasattr(model, "spring_broken") else np.zeros(S, bool)
    broken_arr = model.spring_broken if S and hasattr(model, "spring_broken") else wp.zeros(max(S, 1), dtype=int,
                                                                                              device=d)
    drag = _linear_drag(forces)

    spring_dt = springs.steps(method, k, c, broken, inv_mass, drag) if S else np.zeros(0)

    omega2 = np.zeros(W)
    damp = np.zeros(W)
    bound = np.zeros(W)
    particle_dt = np.full(n, np.inf)
    amplitude = np.zeros(n)
    if S and n and moving.any():
        rest = model.spring_rest_length
        stiff, damper = model.spring_stiffness, model.spring_damping
        zeros = wp.zeros(n, dtype=float, device=d)
        world_arr = wp.array(world.astype(np.int32), dtype=int, device=d)
        # the start vector by index within the world: every world of a batch starts where it starts
        # run alone, so its estimate (and its automatic step count) is the one of its own run
        order = np.argsort(world, kind="stable")
        first = np.searchsorted(world[order], np.arange(W + 1))
        local = np.empty(n, dtype=np.int64)
        local[order] = np.arange(n) - np.repeat(first[:-1], np.diff(first))
        start = np.random.default_rng(2026).uniform(-1.0, 1.0, (int(local.max()) + 1, 3))[local]
        v = wp.array((start * moving[:, None]).astype(np.float32), dtype=wp.vec3, device=d)
        y = wp.zeros(n, dtype=wp.vec3, device=d)
        z = wp.zeros(n, dtype=wp.vec3, device=d)
        world_max = wp.zeros(W, dtype=float, device=d)
        op = (positions, offsets, adj_spring, adj_other, rest)
        for _ in range(int(iterations)):
            wp.launch(K.apply_spring_operator, n, inputs=[v, *op, stiff, broken_arr, 1, zeros, y], device=d)
            world_max.zero_()
            wp.launch(K.scale_and_world_max, n, inputs=[y, model.particle_inv_mass, world_arr, z, world_max], device=d)
            wp.launch(K.normalize_per_world, n, inputs=[z, world_arr, world_max, v], device=d)
        wp.launch(K.apply_spring_operator, n, inputs=[v, *op, stiff, broken_arr, 1, zeros, y], device=d)
        drag_diag = wp.array(np.where(moving, drag, 0.0).astype(np.float32), dtype=float, device=d)
        wp.launch(K.apply_spring_operator, n, inputs=[v, *op, damper, broken_arr, 0, drag_diag, z], device=d)
        rows = wp.zeros(n, dtype=float, device=d)
        wp.launch(K.gershgorin_rows, n, inputs=[offsets, adj_spring, adj_other, stiff, broken_arr,
                                                model.particle_inv_mass, zeros, rows], device=d)
        vh = v.numpy().astype(np.float64) * moving[:, None]
        kv, dv = y.numpy().astype(np.float64), z.numpy().astype(np.float64)
        den = np.bincount(world, weights=mass * np.einsum("ij,ij->i", vh, vh), minlength=W)
        num = np.bincount(world, weights=np.einsum("ij,ij->i", vh, kv), minlength=W)
        dnum = np.bincount(world, weights=np.einsum("ij,ij->i", vh, dv), minlength=W)
        with np.errstate(divide="ignore", invalid="ignore"):
            omega2 = np.where(den > 0, np.maximum(num, 0.0) / den, 0.0)
            damp = np.where(den > 0, np.maximum(dnum, 0.0) / den, 0.0)
        row = rows.numpy().astype(np.float64)
        np.maximum.at(bound, world, row)
        particle_dt = stable_steps(method, np.sqrt(np.maximum(row, 0.0)), 0.0)
        springs.find_strongest(q64, vh, k, broken)
        amplitude = np.einsum("ij,ij->i", vh, vh)

    k_c, zeta_c = _penalty(colliders)
    collider_dt, collider_of, collider_L = _collider_steps(model, positions, velocities, colliders,
                                                           gravity_of(forces, W), world)
    # each world's particles (and springs: _HostSprings) as slices of one stable sort (W x n scans cost minutes
    # at 10^5 worlds)
    p_order = np.argsort(world, kind="stable")
    p_start = np.searchsorted(world[p_order], np.arange(W + 1))
    loudest, amplitude_max = first_extreme(amplitude, p_order, p_start)  # per world, at once
    if k_c > 0.0:  # (penalty contact: each world's lightest moving particle)
        lightest_of, _ = first_extreme(np.where(moving, mass, np.inf), p_order, p_start, largest=False)
        has_moving = any_per_world(moving, p_order, p_start)
    finite = np.isfinite(collider_dt)
    any_finite = any_per_world(finite, p_order, p_start) if finite.any() else np.zeros(W, dtype=bool)
    fastest = first_extreme(collider_dt, p_order, p_start, largest=False)[0] if finite.any() else np.full(W, -1)
    held = _point_springs(forces)
    limits = []
    for w in range(W):
        omega = math.sqrt(omega2[w])
        zeta = damp[w] / (2.0 * omega) if omega > 0 else 0.0
        dt = stable_step(method, omega, zeta)
        kind, index, stiffness, m, damping, particle = "none", -1, 0.0, 0.0, 0.0, -1
        region = method  # the stability region of what sets the limit
        in_world = p_order[p_start[w]:p_start[w + 1]]
        if amplitude_max[w] > 0:
            particle = int(loudest[w])
        if omega > 0:
            s = springs.strongest(w)
            ends = [e for e in springs.ends(s) if moving[e]]
            kind, index, stiffness, damping = "spring", s, float(k[s]), float(c[s])
            m = float(min(mass[e] for e in ends)) if ends else 0.0
        who = "none" if kind == "none" else f"{kind} {index}: k = {stiffness:.4g} N/m, m = {m:.4g} kg"
        reason = limit_reason(method, omega, zeta, dt, who, note_of(integrator))
        if k_c > 0.0 and has_moving[w] and lightest_of[w] >= 0:
            lightest = int(lightest_of[w])
            omega_c = math.sqrt(k_c / mass[lightest])
            dt_c = stable_step("semi_implicit_euler", omega_c, zeta_c)
            if dt_c < dt:
                dt, omega, zeta = dt_c, omega_c, zeta_c
                kind, index, stiffness, m, damping, particle = "collider", lightest, k_c, float(mass[lightest]), 0.0, \
                    lightest
                reason = (f"penalty contact k = {k_c:.4g} N/m on particle {lightest} (m = {m:.4g} kg): omega = "
                          f"{omega_c:.4g} rad/s, zeta = {zeta_c:.3g}; contact impulses act like semi-implicit Euler, "
                          f"stable for dt <= 2 / (omega (zeta + sqrt(1 + zeta^2))) = {dt_c:.4g} s")
        for p, k_d, c_d in held:  # a particle held by a drag spring: an oscillator of its own
            if world[p] != w or not moving[p] or k_d <= 0.0:
                continue
            omega_d = math.sqrt(k_d * inv_mass[p])
            zeta_d = c_d * inv_mass[p] / (2.0 * omega_d)
            dt_d = stable_step(force_method, omega_d, zeta_d)
            if dt_d < dt:
                dt, omega, zeta = dt_d, omega_d, zeta_d
                kind, index, stiffness, m, damping, particle = "particle", p, k_d, float(mass[p]), c_d, p
                region = force_method
                reason = limit_reason(force_method, omega_d, zeta_d, dt_d,
                                      f"particle {p} held by a drag spring: k = {k_d:.4g} N/m, m = {m:.4g} kg")
        if any_finite[w] and fastest[w] >= 0:
            p = int(fastest[w])
            if collider_dt[p] < dt:
                collider = colliders[int(collider_of[p])]
                name = getattr(collider, "name", type(collider).__name__)
                dt, kind, index, particle = float(collider_dt[p]), "collider", int(collider_of[p]), p
                stiffness, m, damping = 0.0, float(mass[p]), 0.0
                reason = (f"{name} ({getattr(collider, 'mode_name', 'contact')}) on particle {p}: it may move at most "
                          f"{collider_L[p]:.4g} m per step (its collision thickness or fall height) and covers "
                          f"|v| dt + |g| dt^2 per step, so dt <= {dt:.4g} s")
        limits.append(StabilityLimit(
            dt=dt, integrator=region, omega_max=omega, damping_ratio=zeta, limiting=kind, index=index,
            stiffness=stiffness, mass=m, damping=damping, particle=particle, omega_bound=math.sqrt(bound[w]),
            reason=reason, spring_dt=springs.world_steps(spring_dt, w),
            particle_dt=particle_dt if W == 1 else particle_dt[in_world]))
    return limits
