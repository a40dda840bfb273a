"""The strands' stability limit under each integrator (``Simulator.stable_dt()`` reads it through
``StrandForce.stability_limit``).

A strand's motion about the current positions is linear to first order: M a = -K dx - D v, with
K = -df/dx (stretch and bending including the bending frames: central differences of the
simulator's own force kernel) and D = -df/dv (stretch and bending dampers: exact, the forces are
linear in the velocities, plus linear ``Drag``). The first-order system z' = A z,
A = [[0, I], [-M^-1 K, -M^-1 D]] over the free vertices has eigenvalues lambda. Every explicit
integrator is a polynomial R(h lambda) of it (explicit Euler, RK2, RK4: stable when
|R(h lambda)| <= 1 for every eigenvalue) and semi-implicit Euler is applied per damped mode,
omega = |lambda|, zeta = -Re(lambda) / |lambda| (``warpsim.core.stability.stable_step``), so the
limit is the smallest per-eigenvalue step over the strands examined. With many strands a sample
is examined: the stiffest by the Gershgorin bound, the most curved (largest rest bending
vector) and the rest evenly spaced. Under ``StrandImplicitEuler`` the strands are unrestricted
unless its assembled stiffness misjudges them (``implicit_limit``).
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from ..core import stability as stab
from ..kernels import strands as K

__all__ = ["assembled_stiffness", "band_matrix", "band_to_dense", "implicit_limit", "strand_eigenvalues",
           "strand_jacobians", "strand_limit"]

SAMPLE = 48
"""Strands examined at most."""


def _sample(strands, bend_rest, count):
    n = strands.strand_count
    if n <= count:
        return np.arange(n)
    m = strands.mass / strands.segments
    bound = (4.0 * strands.stretch_stiffness + 16.0 * strands.bend_stiffness) / m
    curved = np.linalg.norm(bend_rest.reshape(n, strands.stride, 3), axis=2).max(axis=1)
    quarter = max(1, count // 4)
    picks = np.concatenate([np.argsort(-bound, kind="stable")[:quarter], np.argsort(-curved, kind="stable")[:quarter],
                            np.linspace(0, n - 1, count - 2 * quarter).round().astype(int)])
    return np.unique(picks)


def strand_jacobians(strands, data, positions, picks, drag: float = 0.0) -> tuple:
    """(K, D) (S, 3 segments, 3 segments) [N/m], [N s/m]: minus the Jacobians of the strand forces
    (plus linear ``drag`` [kg/s]) over the free vertices of strands ``picks`` (S,) about
    ``positions`` (host (particle_count, 3) [m]), by central differences of the force kernel
    (K) and exactly (D: the forces are linear in the velocities); ``data``: ``strands.bind(model)``."""
    bend_rest = data["bend_rest"].numpy()
    picks = np.asarray(picks, dtype=np.int64)
    S, stride, seg = len(picks), strands.stride, strands.segments
    rows = (strands.first + picks[:, None] * stride + np.arange(stride)[None, :]).reshape(-1)
    slots = (picks[:, None] * stride + np.arange(stride)[None, :]).reshape(-1)
    x0 = np.asarray(positions, np.float64)[rows].astype(np.float32)
    dev = data["rest_length"].device  # the model's device (GPU machines may lack the CPU compiler)

    def arr(a, dtype=float):
        return wp.array(np.ascontiguousarray(a), dtype=dtype, device=dev)

    params = [arr(data["rest_length"].numpy()[slots]), arr(bend_rest[slots], wp.vec3)]
    params += [arr(data[k].numpy()[picks]) for k in ("stretch_stiffness", "bend_stiffness", "stretch_damping",
                                                     "bend_damping")]
    normal = arr(data["root_normal"].numpy()[picks], wp.vec3)
    scratch = [wp.zeros(S * stride, dtype=wp.vec3, device=dev) for _ in range(2)]
    q, qd, out = (wp.zeros(S * stride, dtype=wp.vec3, device=dev) for _ in range(3))

    def forces(x, v):
        q.assign(x)
        qd.assign(v)
        out.zero_()
        wp.launch(K.eval_strand_forces, S, inputs=[q, qd, 0, stride, *params, normal, *scratch, out], device=dev)
        return out.numpy().astype(np.float64).reshape(S, stride, 3)[:, 2:].reshape(S, 3 * seg)

    zero = np.zeros_like(x0)
    f0 = forces(x0, zero)
    eps = 1.0e-4 * max(1.0, float(np.abs(x0).max()))
    N = 3 * seg
    Kmat = np.zeros((S, N, N))
    Dmat = np.zeros((S, N, N))
    for j in range(N):
        v, c = 2 + j // 3, j % 3
        xp, xm, vel = x0.copy(), x0.copy(), zero.copy()
        xp.reshape(S, stride, 3)[:, v, c] += eps
        xm.reshape(S, stride, 3)[:, v, c] -= eps
        Kmat[:, :, j] = -(forces(xp, zero) - forces(xm, zero)) / (2.0 * eps)
        vel.reshape(S, stride, 3)[:, v, c] = 1.0
        Dmat[:, :, j] = -(forces(x0, vel) - f0)
    Dmat += drag * np.eye(N)[None]
    return Kmat, Dmat


def strand_eigenvalues(strands, data, positions, drag: float = 0.0, sample: int = SAMPLE) -> tuple:
    """(strand indices (S,), eigenvalues (S, 6 segments) complex [1/s]) of the linearised motion
    z' = A z of a sample of strands about ``positions`` (host (particle_count, 3) [m]); ``data``:
    ``strands.bind(model)``; ``drag``: linear drag [kg/s] on every vertex."""
    picks = _sample(strands, data["bend_rest"].numpy(), sample)
    Kmat, Dmat = strand_jacobians(strands, data, positions, picks, drag)
    S, N = len(picks), 3 * strands.segments
    m = np.repeat(strands.mass[picks] / strands.segments, N).reshape(S, N)
    A = np.zeros((S, 2 * N, 2 * N))
    A[:, :N, N:] = np.eye(N)[None]
    A[:, N:, :N] = -Kmat / m[:, :, None]
    A[:, N:, N:] = -Dmat / m[:, :, None]
    return picks, np.linalg.eigvals(A)


def band_matrix(P, U1, U2) -> np.ndarray:
    """The symmetric matrix (S, 4 stride, 4 stride) of the upper band blocks P, U1, U2
    (S, stride, 4, 4) that ``StrandImplicitEuler`` assembles (factor = 0; x, y, z, twist per vertex)."""
    S, stride = P.shape[0], P.shape[1]
    A = np.zeros((S, 4 * stride, 4 * stride))
    for v in range(stride):
        A[:, 4 * v:4 * v + 4, 4 * v:4 * v + 4] = P[:, v]
        for gap, U in ((1, U1), (2, U2)):
            if v + gap < stride:
                w = 4 * (v + gap)
                A[:, 4 * v:4 * v + 4, w:w + 4] = U[:, v]
                A[:, w:w + 4, 4 * v:4 * v + 4] = np.transpose(U[:, v], (0, 2, 1))
    return A


def band_to_dense(P, U1, U2, free) -> np.ndarray:
    """``band_matrix`` over the positions of the free vertices ``free`` (F local vertex indices),
    (S, 3 F, 3 F), the twists eliminated (the Schur complement onto the positions)."""
    A = band_matrix(P, U1, U2)
    x = np.array([4 * v + c for v in free for c in range(3)])
    t = 4 * np.arange(P.shape[1]) + 3
    Axx, Axt, Att = A[:, x][:, :, x], A[:, x][:, :, t], A[:, t][:, :, t]
    return Axx - Axt @ np.linalg.solve(Att, np.transpose(Axt, (0, 2, 1)))


def assembled_stiffness(strands, data, positions, picks) -> np.ndarray:
    """Ka (S, 3 segments, 3 segments) [N/m]: the stiffness ``StrandImplicitEuler`` assembles
    (stretch with the clamped geometric term, Gauss-Newton bending with the frames' twist, the
    twists eliminated) for strands ``picks`` about ``positions`` (host (particle_count, 3) [m])."""
    from ..kernels import strands_implicit as KI

    picks = np.asarray(picks, dtype=np.int64)
    S, stride, seg = len(picks), strands.stride, strands.segments
    rows = (strands.first + picks[:, None] * stride + np.arange(stride)[None, :]).reshape(-1)
    slots = (picks[:, None] * stride + np.arange(stride)[None, :]).reshape(-1)
    dev = data["rest_length"].device  # the model's device (GPU machines may lack the CPU compiler)

    def arr(a, dtype=float):
        return wp.array(np.ascontiguousarray(a), dtype=dtype, device=dev)

    mass = np.zeros((S, stride))
    mass[:, 2:] = 1.0  # a unit mass: A = M + Ka with h = 1 and no damping
    zero = arr(np.zeros(S))
    q = arr(np.asarray(positions, np.float64)[rows].astype(np.float32), wp.vec3)
    vel = wp.zeros(S * stride, dtype=wp.vec3, device=dev)
    blocks = [wp.zeros(S * stride, dtype=wp.mat44d, device=dev) for _ in range(3)]
    rhs = wp.zeros(S * stride, dtype=wp.vec4d, device=dev)
    wp.launch(KI.strand_implicit_solve, S,
              inputs=[q, vel, vel, arr(mass.reshape(-1)), 0, stride, arr(data["rest_length"].numpy()[slots]),
                      arr(data["bend_rest"].numpy()[slots], wp.vec3), arr(data["stretch_stiffness"].numpy()[picks]),
                      arr(data["bend_stiffness"].numpy()[picks]), zero, zero,
                      arr(data["root_normal"].numpy()[picks], wp.vec3), 0.0, -1, 0.0, 0.0, 1.0, *blocks, rhs, 0, vel],
              device=dev)
    P, U1, U2 = (b.numpy().reshape(S, stride, 4, 4) for b in blocks)
    return band_to_dense(P, U1, U2, range(2, stride)) - np.eye(3 * seg)[None]


def implicit_limit(strands, data, positions, drag: float = 0.0, sample: int = SAMPLE) -> float:
    """Largest stable step [s] of ``StrandImplicitEuler`` on the linearised strands (inf when
    every step is stable). With the exact stiffness K and the assembled Ka, the step maps
    (x, v) by T(h): v1 = v + A^-1 (-h K x - (h D + h^2 Ka) v), x1 = x + h v1,
    A = M + h D + h^2 Ka. In the stiff limit x1 = (I - Ka^-1 K) x, so every step is stable when
    the eigenvalues of Ka^-1 K lie in (0, 2) (measured: 0.68-1.89 on the straight groom at 16-48
    segments, 0.97-1.07 on the wavy and curly grooms at 32 with the frames' twist in Ka; without
    it, up to 8.8); otherwise the largest h with spectral radius of T(h) <= 1 over the sampled
    strands is found by bisection."""
    picks = _sample(strands, data["bend_rest"].numpy(), sample)
    Kmat, Dmat = strand_jacobians(strands, data, positions, picks, drag)
    Ka = assembled_stiffness(strands, data, positions, picks)
    ratio = np.linalg.eigvals(np.linalg.solve(Ka, Kmat))
    if ratio.real.max() < 1.95 and ratio.real.min() > 0.0:
        return math.inf
    S, N = Kmat.shape[0], Kmat.shape[1]
    m = np.repeat(strands.mass[picks] / strands.segments, N).reshape(S, N)
    eye = np.eye(N)[None]

    def radius(h):
        A = m[:, :, None] * eye + h * Dmat + h * h * Ka
        tvx = -h * np.linalg.solve(A, Kmat)
        tvv = eye - np.linalg.solve(A, h * Dmat + h * h * Ka)
        T = np.block([[eye + h * tvx, h * tvv], [tvx, tvv]])
        return float(np.abs(np.linalg.eigvals(T)).max())

    lo, hi = 1.0e-6, 1.0
    if radius(hi) <= 1.0 + 1.0e-9:
        return math.inf
    while hi / lo > 1.05:
        mid = math.sqrt(lo * hi)
        if radius(mid) <= 1.0 + 1.0e-9:
            lo = mid
        else:
            hi = mid
    return lo


def strand_limit(strands, data, positions, integrator, drag: float = 0.0,
                 sample: int = SAMPLE) -> "stab.StabilityLimit | None":
    """``StabilityLimit`` of the strands for ``integrator`` (a name or instance); under
    ``StrandImplicitEuler`` None (unrestricted) or ``implicit_limit``'s step; see the module
    docstring. Integrators with implicit
    Euler's region that do not take the strands' Jacobian (``ws.ImplicitEuler``) get
    semi-implicit Euler's limit: their Newton iterations see the strand forces only through the
    residual."""
    name = integrator if isinstance(integrator, str) else getattr(integrator, "name", "")
    if name == "strand_implicit_euler":
        dt = implicit_limit(strands, data, positions, drag, sample)
        if not math.isfinite(dt):
            return None
        return stab.StabilityLimit(dt=dt, integrator="implicit_euler", limiting="strand", reason=(
            f"the strands' implicit step with its Gauss-Newton Jacobian is stable up to {dt:.4g} s on the "
            "linearised strands"))
    method = stab.method_of(integrator)
    if method == "implicit_euler":
        method = "semi_implicit_euler"
    picks, lam = strand_eigenvalues(strands, data, positions, drag, sample)
    omega = np.abs(lam)
    with np.errstate(divide="ignore", invalid="ignore"):
        zeta = np.where(omega > 0.0, np.maximum(-lam.real, 0.0) / omega, 0.0)
    per = stab.stable_steps(method, omega.reshape(-1), zeta.reshape(-1)).reshape(omega.shape)
    k = np.unravel_index(int(np.argmin(per)), per.shape)
    s = int(picks[k[0]])
    dt = float(per[k])
    w, z = float(omega[k]), float(zeta[k])
    m = float(strands.mass[s] / strands.segments)
    who = f"strand {s}: k_stretch = {strands.stretch_stiffness[s]:.4g} N/m, m = {m:.4g} kg per vertex"
    reason = stab.limit_reason(method, w, z, dt, who) if math.isfinite(dt) else ""
    return stab.StabilityLimit(dt=dt, integrator=method, omega_max=w, damping_ratio=z,
                               limiting="strand", index=s, stiffness=float(strands.stretch_stiffness[s]), mass=m,
                               damping=float(strands.stretch_damping[s]),
                               particle=int(strands.first + s * strands.stride + strands.stride - 1),
                               omega_bound=float(omega.max()), reason=reason)
