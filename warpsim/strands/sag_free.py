"""Sag-free initialization: rest states that make the current shape a static equilibrium.

A model built in its rest shape sags under gravity as soon as it is simulated. ``sag_free``
changes the springs' rest lengths (the model's springs and the strands' stretch springs) and the
strands' bending rest states so that, at the current positions with zero velocity, the forces on
every free particle (inverse mass > 0) sum to zero under the current forces (gravity, wind, ...)
and pins (after Hsu, Wang, Pan, Gao, Yuksel and Wu, "Sag-Free Initialization for Strand-Based
Hybrid Hair Simulation", ACM TOG 2023).

The math. With springs f = k (|d| - L) d_hat and strand bending forces k_b (w - b) (same form,
``warpsim.kernels.strands``), the force on each particle is *linear* in the rest state: with the
tension change t = k (l - L) [N] per length spring and g = k_b (w - b) [N] per bending vertex
(zero at the geometric rest state L = l, w = b), equilibrium at every free particle is the linear
system A [t; g] = -f_ext (3 equations per free particle, local force balance). It is usually
under-determined (hair: a stretch and three bending unknowns per vertex; cloth: more springs than
particles), so the solve picks, among the rest states that balance the load, the one of least
elastic energy of the change, sum t^2 / k + |g|^2 / k_b (minimum complementary energy: the
regularisation toward the geometric rest state, stiff springs carry the load). With u = t /
sqrt(k) this is the minimum-norm solution of A diag(sqrt(k)) u = -f_ext, found globally by CGLS
(conjugate gradients on the normal equations, float64, from u = 0). Bounds: every rest length stays
within ``max_strain`` of its geometric value, |L / l - 1| <= max_strain (< 1, so L > 0), and
every component of a strand bending rest vector within max_strain h of its geometric value
(h: the segment length); unknowns
that leave the bound are held at it and the rest is solved again (an active set), and when the
load cannot be carried within the bounds a ValueError names the particle (and strand) left with
the largest residual force. The result is checked with the simulator's own force kernels.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import warp as wp

from ..core import checks
from ..core.forces import Springs
from ..kernels import sag_free as K
from ..kernels import strands as KS
from .forces import StrandForce

__all__ = ["SagFreeReport", "sag_free"]


@dataclass
class SagFreeReport:
    """What ``sag_free`` did.

    residual_max: largest remaining force on a free particle [N] of the solve (float64 rest
    states); load_max: largest external force on a free particle [N]; residual_relative =
    residual_max / load_max; simulator_residual_max / _relative: the same measured with the
    simulator's float32 force kernels after the rest states are written (rounding positions and
    rest lengths to float32 leaves about k * 1e-8 m per spring); iterations: CGLS iterations in all;
    rounds: active-set rounds; springs_at_bound: model spring indices held at |L / l - 1| =
    max_strain; strand_segments_at_bound: (strand, segment) pairs likewise (per strand group, in
    the order of the forces); strand_vertices_at_bound: (strand, vertex) pairs whose bending rest
    vector change reached max_strain times the segment length (per component); rest_ratio_min / rest_ratio_max: extreme L / l over every length
    spring; bend_change_max: largest change of a bending rest vector [m]."""

    residual_max: float
    load_max: float
    residual_relative: float
    iterations: int
    rounds: int
    max_strain: float
    springs_at_bound: list = field(default_factory=list)
    strand_segments_at_bound: list = field(default_factory=list)
    rest_ratio_min: float = 1.0
    rest_ratio_max: float = 1.0
    bend_change_max: float = 0.0
    simulator_residual_max: float = 0.0
    strand_vertices_at_bound: list = field(default_factory=list)
    simulator_residual_relative: float = 0.0

    def __str__(self):
        bound = len(self.springs_at_bound) + len(self.strand_segments_at_bound)
        return (f"sag-free: residual {self.residual_max:.3g} N ({100 * self.residual_relative:.3g} % of the largest "
                f"load {self.load_max:.3g} N; {100 * self.simulator_residual_relative:.3g} % in the simulator's float32 "
                f"kernels) after {self.iterations} CGLS iterations; rest lengths within "
                f"[{self.rest_ratio_min:.4f}, {self.rest_ratio_max:.4f}] x geometric, {bound} at the bound "
                f"+-{self.max_strain:g}; bending rest change up to {self.bend_change_max:.3g} m")


def _system_of(target, forces):
    from ..core.model import Model
    from ..core.simulator import Simulator
    from ..core.system import ParticleSystem

    if isinstance(target, Simulator):
        if forces is not None:
            raise ValueError("sag_free: give forces only with a Model; a Simulator uses its own")
        return target.model, target.system, target.state.positions
    if isinstance(target, Model):
        from ..core.forces import Gravity

        system = ParticleSystem(target, [Gravity()] if forces is None else list(forces))
        return target, system, target.particle_q
    raise ValueError(f"sag_free needs a ws.Simulator or a ws.Model, got {checks.show(target)}")


class _Group:
    """One StrandForce's strands and their slice of the unknowns."""

    length: np.ndarray  # per-slot rest geometry, filled by sag_free
    bend_geo: np.ndarray
    sqrt_stretch: wp.array
    sqrt_bend: wp.array

    def __init__(self, force, offset):
        st = force.strands
        self.force, self.strands, self.data = force, st, force.data
        self.slots = st.strand_count * st.stride
        self.stretch_offset = offset
        self.bend_offset = offset + self.slots
        self.end = offset + 4 * self.slots


def sag_free(target, *, forces=None, max_strain: float = 0.2, tol: float = 1.0e-4, rtol: float = 1.0e-10,
             max_iterations: int = 50000, device_check_every: int = 25) -> SagFreeReport:
    """Make the current positions of ``target`` (a ``ws.Simulator``: its state and forces; or a
    ``ws.Model``: its initial positions under ``forces``, default ``[ws.Gravity()]``) a static
    equilibrium by changing rest lengths and strand bending rest states in place (module
    docstring). Returns a :class:`SagFreeReport`.

    max_strain: bound on |L / l - 1| for every rest length (0 < max_strain < 1). tol: the largest
    residual force accepted, relative to the largest load (ValueError naming the particle and
    strand when the bounds leave more). rtol: CGLS stops when |residual| <= rtol |load|;
    max_iterations: CGLS iterations in all rounds."""
    max_strain = checks.in_range(max_strain, "sag_free max_strain", 0.0, 1.0, lo_open=True, hi_open=True,
                                 fix="a bound on |L / l - 1| such as 0.2")
    tol = checks.positive(tol, "sag_free tol", fix="a relative residual force such as 1e-4")
    rtol = checks.positive(rtol, "sag_free rtol", fix="e.g. 1e-10")
    max_iterations = checks.count(max_iterations, "sag_free max_iterations", fix="e.g. 50000")
    model, system, q = _system_of(target, forces)
    d = model.device
    n = model.particle_count
    inv_mass_host = model.particle_inv_mass.numpy()
    x = q.numpy().astype(np.float64)
    groups_forces = [f for f in system.forces if isinstance(f, StrandForce)]
    has_springs = model.spring_count > 0 and any(isinstance(f, Springs) for f in system.forces)

    # ---- geometric rest state: no internal force at the current positions ---------------------
    m = model.spring_count if has_springs else 0
    if m:
        ij = model.spring_indices.numpy().reshape(-1, 2)
        spring_l = np.linalg.norm(x[ij[:, 0]] - x[ij[:, 1]], axis=1)
        k = model.spring_stiffness.numpy().astype(np.float64)
        broken = model.spring_broken.numpy() != 0 if hasattr(model, "spring_broken") else np.zeros(m, bool)
        k_eff = np.where(broken | (spring_l <= 0.0), 0.0, k)
        spring_rest_before = model.spring_rest_length.numpy()
        model.spring_rest_length.assign(spring_l.astype(np.float32))
    groups, offset = [], m
    for f in groups_forces:
        g = _Group(f, offset)
        offset = g.end
        st, data = g.strands, g.data
        xs = x[st.first: st.first + g.slots].reshape(st.strand_count, st.stride, 3)
        g.length = np.zeros((st.strand_count, st.stride))
        g.length[:, 1:-1] = np.linalg.norm(np.diff(xs[:, 1:], axis=1), axis=2)
        g.bend_geo = np.zeros((st.strand_count, st.stride, 3))
        g.bend_geo[:, 1:-1] = xs[:, :-2] - 2.0 * xs[:, 1:-1] + xs[:, 2:]
        data["rest_length"].assign(g.length.reshape(-1).astype(np.float32))
        wp.launch(KS.bend_rest_from_world, st.strand_count,
                  inputs=[q, st.first, st.stride, data["root_normal"], data["bend_rest"], 1, data["bend_rest"]],
                  device=d)
        groups.append(g)
    unknowns = offset

    # ---- the load -----------------------------------------------------------------------------
    zeros_v = wp.zeros(n, dtype=wp.vec3, device=d)
    time = wp.zeros(1, dtype=float, device=d)
    force = wp.zeros(n, dtype=wp.vec3, device=d)
    system.eval_forces(q, zeros_v, time, 0.0, force)
    load = np.linalg.norm(force.numpy(), axis=1)[inv_mass_host > 0.0]
    load_max = float(load.max()) if len(load) else 0.0
    if unknowns == 0 or load_max == 0.0:
        return _finish(model, system, q, zeros_v, time, force, inv_mass_host, max_strain, load_max, 0, 0, [], [],
                       groups, tol)
    b = wp.zeros(3 * n, dtype=wp.float64, device=d)
    wp.launch(K.external_rhs, n, inputs=[force, model.particle_inv_mass, b], device=d)

    # ---- operators ----------------------------------------------------------------------------
    if m:
        sqrt_k = wp.array(np.sqrt(k_eff), dtype=wp.float64, device=d)
        order = np.argsort(ij.reshape(-1), kind="stable")
        owners = ij.reshape(-1)[order]
        adjacency = wp.array((order // 2).astype(np.int32), dtype=int, device=d)
        offsets = wp.array(np.concatenate([[0], np.cumsum(np.bincount(owners, minlength=n))]).astype(np.int32),
                           dtype=int, device=d)
        spring_indices = model.spring_indices
    else:
        sqrt_k = wp.zeros(0, dtype=wp.float64, device=d)
        adjacency = wp.zeros(0, dtype=int, device=d)
        offsets = wp.zeros(n + 1, dtype=int, device=d)
        spring_indices = wp.zeros(0, dtype=int, device=d)
    for g in groups:
        st = g.strands
        g.sqrt_stretch = wp.array(np.sqrt(st.stretch_stiffness), dtype=wp.float64, device=d)
        g.sqrt_bend = wp.array(np.sqrt(st.bend_stiffness), dtype=wp.float64, device=d)

    def apply(u_in, f_out):
        wp.launch(K.springs_apply, n, inputs=[q, spring_indices, sqrt_k, offsets, adjacency, model.particle_inv_mass,
                                               u_in, 0, f_out], device=d)
        for g in groups:
            wp.launch(K.strands_apply, g.strands.strand_count,
                      inputs=[q, g.strands.first, g.strands.stride, g.sqrt_stretch, g.sqrt_bend,
                              model.particle_inv_mass, u_in, g.stretch_offset, g.bend_offset, f_out], device=d)

    # masks and bounds (host): unused strand slots are fixed at 0; length unknowns are bounded
    mask_host = np.zeros(unknowns, dtype=np.int32)
    bound = np.full(unknowns, np.inf)
    if m:
        bound[:m] = max_strain * spring_l * np.sqrt(k_eff)
        mask_host[:m] = (k_eff == 0.0)
    for g in groups:
        st = g.strands
        unused = np.zeros((st.strand_count, st.stride), bool)
        unused[:, 0] = unused[:, -1] = True
        mask_host[g.stretch_offset: g.bend_offset] = unused.reshape(-1)
        mask_host[g.bend_offset: g.end] = np.repeat(unused.reshape(-1), 3)
        ks: np.ndarray = np.repeat(st.stretch_stiffness, st.stride).reshape(st.strand_count, st.stride)
        bound[g.stretch_offset: g.bend_offset] = (max_strain * g.length * np.sqrt(ks)).reshape(-1)
        kb: np.ndarray = np.repeat(st.bend_stiffness, st.stride).reshape(st.strand_count, st.stride)
        bound[g.bend_offset: g.end] = np.repeat((max_strain * g.length * np.sqrt(kb)).reshape(-1), 3)
        zero_k = np.repeat(st.stretch_stiffness == 0.0, st.stride)
        mask_host[g.stretch_offset: g.bend_offset] |= zero_k
        mask_host[g.bend_offset: g.end] |= np.repeat(np.repeat(st.bend_stiffness == 0.0, st.stride), 3)

    def apply_transpose(r_in, u_out):
        if m:
            wp.launch(K.springs_apply_transpose, m, inputs=[q, spring_indices, sqrt_k, r_in, 0, u_out], device=d)
        for g in groups:
            wp.launch(K.strands_apply_transpose, g.strands.strand_count,
                      inputs=[q, g.strands.first, g.strands.stride, g.sqrt_stretch, g.sqrt_bend, r_in,
                              g.stretch_offset, g.bend_offset, u_out], device=d)
        wp.launch(K.zero_masked, unknowns, inputs=[u_out, mask], device=d)

    # ---- CGLS with an active set of bounded unknowns ------------------------------------------
    u = wp.zeros(unknowns, dtype=wp.float64, device=d)
    mask = wp.array(mask_host, dtype=int, device=d)
    p = wp.zeros_like(u)
    s = wp.zeros_like(u)
    r = wp.zeros(3 * n, dtype=wp.float64, device=d)
    Ap = wp.zeros_like(r)
    scalars = wp.zeros(8, dtype=wp.float64, device=d)  # 0 gamma, 1 delta, 2 gamma_new, 3 |r|^2, 4 |b|^2
    partial = {}

    def dot(a, c, slot):
        size = a.shape[0]
        threads = min(256, size)
        chunk = -(-size // threads)
        buf = partial.get(threads)
        if buf is None:
            buf = partial[threads] = wp.zeros(threads, dtype=wp.float64, device=d)
        wp.launch(K.dot_partial, threads, inputs=[a, c, chunk, buf], device=d)
        wp.launch(K.sum_partials, 1, inputs=[buf, scalars, slot], device=d)

    dot(b, b, 4)
    bb = float(scalars.numpy()[4])
    iterations, rounds = 0, 0
    for rounds in range(1, 64):
        # r = b - A u; s = A^T r; p = s; gamma = |s|^2
        apply(u, Ap)
        wp.launch(K.subtract_masked, 3 * n, inputs=[b, Ap, r], device=d)
        apply_transpose(r, s)
        wp.copy(p, s)
        dot(s, s, 0)
        gamma0 = float(scalars.numpy()[0])
        while iterations < max_iterations:
            for _ in range(device_check_every):
                apply(p, Ap)
                dot(Ap, Ap, 1)
                wp.launch(K.axpy_ratio, unknowns, inputs=[u, p, scalars, 0, 1, wp.float64(1.0)], device=d)
                wp.launch(K.axpy_ratio, 3 * n, inputs=[r, Ap, scalars, 0, 1, wp.float64(-1.0)], device=d)
                apply_transpose(r, s)
                dot(s, s, 2)
                wp.launch(K.cg_direction, unknowns, inputs=[p, s, scalars, 2, 0], device=d)
                wp.launch(K.copy_scalar, 1, inputs=[scalars, 2, 0], device=d)
                iterations += 1
            dot(r, r, 3)
            sc = scalars.numpy()
            if sc[3] <= rtol * rtol * bb or sc[0] <= 1.0e-28 * max(gamma0, 1e-300):
                break
        # unknowns beyond their bound: hold them at it and solve again
        u_host = u.numpy()
        over = (np.abs(u_host) > bound * (1.0 + 1.0e-9)) & (mask_host == 0)
        if not over.any() or iterations >= max_iterations:
            break
        u_host[over] = np.sign(u_host[over]) * bound[over]
        mask_host[over] = 1
        mask.assign(mask_host)
        u.assign(u_host)
    u_host = u.numpy()
    at_bound = (np.abs(np.abs(u_host) - bound) <= 1.0e-9 * bound) & np.isfinite(bound) & (bound > 0.0)

    # ---- write the rest state back (in place: captured graphs keep their arrays) --------------
    ratios = []
    springs_at_bound, segments_at_bound, vertices_at_bound = [], [], []
    if m:
        safe = np.where(k_eff > 0.0, np.sqrt(np.maximum(k_eff, 1e-300)), 1.0)
        rest = np.where(k_eff > 0.0, spring_l - u_host[:m] / safe, spring_rest_before)
        model.spring_rest_length.assign(rest.astype(np.float32))
        live = (k_eff > 0.0) & (spring_l > 0.0)
        ratios.append(rest[live] / spring_l[live])
        springs_at_bound = np.flatnonzero(at_bound[:m]).tolist()
    bend_change = 0.0
    for g in groups:
        st, data = g.strands, g.data
        ks = np.repeat(st.stretch_stiffness, st.stride)
        du = u_host[g.stretch_offset: g.bend_offset]
        rest = g.length.reshape(-1) - np.where(ks > 0.0, du / np.sqrt(np.maximum(ks, 1e-300)), 0.0)
        data["rest_length"].assign(rest.astype(np.float32))
        used = g.length.reshape(-1) > 0.0
        ratios.append(rest[used] / g.length.reshape(-1)[used])
        kb = np.repeat(st.bend_stiffness, st.stride)
        dw = u_host[g.bend_offset: g.end].reshape(-1, 3) / np.where(kb > 0.0, np.sqrt(np.maximum(kb, 1e-300)),
                                                                   np.inf)[:, None]
        bend_change = max(bend_change, float(np.abs(dw).max()) if len(dw) else 0.0)
        world = wp.array((g.bend_geo.reshape(-1, 3) + dw).astype(np.float32), dtype=wp.vec3, device=d)
        wp.launch(KS.bend_rest_from_world, st.strand_count,
                  inputs=[q, st.first, st.stride, data["root_normal"], world, 0, data["bend_rest"]], device=d)
        hit = np.flatnonzero(at_bound[g.stretch_offset: g.bend_offset])
        segments_at_bound += [(int(h // st.stride), int(h % st.stride) - 1) for h in hit]
        hit = np.flatnonzero(at_bound[g.bend_offset: g.end].reshape(-1, 3).any(axis=1))
        vertices_at_bound += [(int(h // st.stride), int(h % st.stride) - 1) for h in hit]
    apply(u, Ap)
    wp.launch(K.subtract_masked, 3 * n, inputs=[b, Ap, r], device=d)
    solve_residual = np.linalg.norm(r.numpy().reshape(n, 3), axis=1)
    report = _finish(model, system, q, zeros_v, time, force, inv_mass_host, max_strain, load_max, iterations, rounds,
                     springs_at_bound, segments_at_bound, groups, tol, solve_residual)
    report.strand_vertices_at_bound = vertices_at_bound
    if ratios:
        allr = np.concatenate(ratios)
        report.rest_ratio_min, report.rest_ratio_max = float(allr.min()), float(allr.max())
    report.bend_change_max = bend_change
    return report


def _finish(model, system, q, zeros_v, time, force, inv_mass, max_strain, load_max, iterations, rounds,
            springs_at_bound, segments_at_bound, groups, tol, solve_residual=None):
    """Measure the residual with the system's own force kernels (float32) and take the solve's
    (float64, ``solve_residual`` (n,) [N]); ValueError when the latter exceeds tol load_max."""
    system.eval_forces(q, zeros_v, time, 0.0, force)
    f = np.linalg.norm(force.numpy(), axis=1)
    f[inv_mass <= 0.0] = 0.0
    exact = f.astype(np.float64) if solve_residual is None else solve_residual
    worst = int(np.argmax(exact)) if len(exact) else 0
    residual = float(exact[worst]) if len(exact) else 0.0
    report = SagFreeReport(residual, load_max, residual / load_max if load_max > 0.0 else 0.0, iterations, rounds,
                           max_strain, springs_at_bound, segments_at_bound)
    report.simulator_residual_max = float(f.max()) if len(f) else 0.0
    report.simulator_residual_relative = report.simulator_residual_max / load_max if load_max > 0.0 else 0.0
    if load_max > 0.0 and residual > tol * load_max:
        where = f"particle {worst}"
        for g in groups:
            found = g.strands.strand_of(worst)
            if found is not None:
                where = f"strand {found[0]} (vertex {found[1] - 1} from the root, particle {worst})"
        bound = len(springs_at_bound) + len(segments_at_bound)
        raise ValueError(
            f"sag_free: the bound max_strain={max_strain:g} cannot be met: {where} keeps a residual force of "
            f"{residual:.3g} N ({100 * residual / load_max:.3g} % of the largest load {load_max:.3g} N, tolerance "
            f"{100 * tol:.3g} %) with {bound} rest lengths held at the bound after {iterations} iterations; raise "
            "max_strain, stiffen the springs or lighten the model")
    return report
