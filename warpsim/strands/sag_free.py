"""Sag-free initialization: rest states that make the current shape a static equilibrium.

A model built in its rest shape sags under gravity as soon as it is simulated. ``sag_free``
changes the springs' rest lengths (the model's springs and the strands' stretch springs) and the
strands' bending rest states so that, at the current positions with zero velocity, the forces on
every free particle (inverse mass > 0) sum to zero under the current forces (gravity, wind, ...)
and pins (after Hsu, Wang, Pan, Gao, Yuksel and Wu, "Sag-Free Initialization for Strand-Based
Hybrid Hair Simulation", ACM TOG 2023).

The math. With springs f = k (|d| - L) d_hat and the strands' bending forces (energy
k_b / 2 |b - w|^2, ``warpsim.kernels.strands``), the force on each particle is linear in the rest
state, up to the bending frames' own gradient: with the tension change t = k (l - L) [N] per
length spring and g = k_b (w - b) [N] per bending vertex (zero at the geometric rest state L = l,
w = b), equilibrium at every free particle is the linear system A [t; g] = -f (3 equations per
free particle: the local force balance). It is usually under-determined (hair: a stretch and three
bending unknowns per vertex; cloth: more springs than particles), so the global step picks, among
the rest states that balance the load, the one of least elastic energy of the change,
sum t^2 / k + |g|^2 / k_b (minimum complementary energy: the regularisation toward the geometric
rest state; stiff springs carry the load). With u = t / sqrt(k) this is the minimum-norm solution
of A diag(sqrt(k)) u = -f. For strands alone (no springs, no supports) it is found directly, one
thread per strand: A A^T over a strand's free vertices is the Gauss-Newton stiffness of the
implicit strand step without mass, solved by its block band Cholesky (``_Solver.solve_direct``;
150 strands x 32 segments on the CPU: 0.23 s instead of 5,475 CGLS iterations); otherwise, and
for a round whose direct solution leaves its bounds, by CGLS (conjugate gradients on the normal
equations, float64, from u = 0). The frames of curved strands add a force that depends on the rest state too; it is
handled global-local: the local step measures every particle's residual force with the
simulator's own force kernels at the current rest state, the global step solves A du = -residual
for a correction, until the residual stops falling (a few rounds).

Bounds: every rest length stays within ``max_strain`` of its geometric value, |L / l - 1| <=
max_strain (< 1, so L > 0), and every component of a strand bending rest vector within
max_strain h of its geometric value (h: the segment length). Unknowns that leave their bound are
held at it and the rest solved again (an active set); when the load cannot be carried within the
bounds a ValueError names the particle (and strand) left with the largest residual force.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import warp as wp

from ..core import checks
from ..core.forces import Springs
from ..kernels import sag_free as K
from ..kernels import strands as KS
from ..kernels import strands_implicit as KI
from .forces import StrandForce

__all__ = ["SagFreeReport", "sag_free"]


@dataclass
class SagFreeReport:
    """What ``sag_free`` did.

    residual_max: largest force left on a free particle [N], measured with the simulator's float32
    force kernels after the rest states are written (rounding positions and rest lengths to float32
    leaves about k * 1e-8 m worth per spring); load_max: largest external force on a free particle
    [N]; residual_relative = residual_max / load_max; rounds: global-local rounds; iterations: CGLS
    iterations in all; springs_at_bound: model spring indices held at |L / l - 1| = max_strain;
    strand_segments_at_bound: (strand, segment) pairs likewise; strand_vertices_at_bound: (strand,
    vertex) pairs whose bending rest change reached max_strain h; rest_ratio_min / _max: extreme
    L / l over every length spring; bend_change_max: largest change of a bending rest vector [m];
    support_particles / support_forces: particles resting on a plane collider and the normal force
    [N] the plane takes there."""

    residual_max: float
    load_max: float
    residual_relative: float
    rounds: int
    iterations: int
    max_strain: float
    springs_at_bound: list = field(default_factory=list)
    strand_segments_at_bound: list = field(default_factory=list)
    strand_vertices_at_bound: list = field(default_factory=list)
    rest_ratio_min: float = 1.0
    rest_ratio_max: float = 1.0
    bend_change_max: float = 0.0
    support_particles: list = field(default_factory=list)
    support_forces: list = field(default_factory=list)

    def __str__(self):
        bound = len(self.springs_at_bound) + len(self.strand_segments_at_bound) + len(self.strand_vertices_at_bound)
        return (f"sag-free: residual {self.residual_max:.3g} N ({100 * self.residual_relative:.3g} % of the largest "
                f"load {self.load_max:.3g} N) after {self.rounds} rounds, {self.iterations} CGLS iterations; rest "
                f"lengths within [{self.rest_ratio_min:.4f}, {self.rest_ratio_max:.4f}] x geometric, bending rest "
                f"change up to {self.bend_change_max:.3g} m; {bound} unknowns at the bound {self.max_strain:g}")


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


def _plane_contacts(target, model, x, inv_mass, offset, m, k_eff, tol=1.0e-4):
    """(unknown offset, particles (C,), normals (C, 3), scale) of the free particles resting on a
    plane collider of a Simulator (within ``tol`` [m] of touching), one plane per particle; None
    when there are none. A support force is scale u along the normal, u >= 0; scale = sqrt(k) of
    the median spring makes its weight in the least-energy objective comparable to a spring's."""
    from ..bodies.colliders import Planes

    colliders = getattr(target, "colliders", None) or []
    particles, normals = [], []
    taken = np.zeros(len(x), bool)
    radius = model.particle_radius.numpy().astype(np.float64)
    for c in colliders:
        if not isinstance(c, Planes):
            continue
        for nrm, off in zip(c.normals, c.offsets):
            gap = x @ nrm - off - radius - c.thickness
            hit = np.flatnonzero((gap <= tol) & (inv_mass > 0.0) & ~taken)
            taken[hit] = True
            particles.append(hit)
            normals.append(np.repeat(np.asarray(nrm, np.float64)[None], len(hit), axis=0))
    if not particles or not sum(len(p) for p in particles):
        return None
    k = k_eff[k_eff > 0.0] if m else np.zeros(0)
    scale = float(np.sqrt(np.median(k))) if len(k) else 1.0
    return offset, np.concatenate(particles), np.concatenate(normals), scale


class _Group:
    """One StrandForce's strands and their slice of the unknowns: stretch (one per slot) then
    bending (three per slot); slots 0 and stride - 1 of each strand are unused."""

    def __init__(self, force, offset, x, d):
        st = self.strands = force.strands
        self.data = force.data
        self.slots = st.strand_count * st.stride
        self.stretch_offset = offset
        self.bend_offset = offset + self.slots
        self.end = offset + 4 * self.slots
        xs = x[st.first: st.first + self.slots].reshape(st.strand_count, st.stride, 3)
        self.length = np.zeros((st.strand_count, st.stride))
        self.length[:, 1:-1] = np.linalg.norm(np.diff(xs[:, 1:], axis=1), axis=2)
        self.bend_geo = np.zeros((st.strand_count, st.stride, 3))
        self.bend_geo[:, 1:-1] = xs[:, :-2] - 2.0 * xs[:, 1:-1] + xs[:, 2:]
        self.length32 = wp.array(self.length.reshape(-1).astype(np.float32), dtype=float, device=d)  # geometric
        self.zero_s = wp.zeros(st.strand_count, dtype=float, device=d)
        self.sqrt_stretch = wp.array(np.sqrt(st.stretch_stiffness), dtype=wp.float64, device=d)
        self.sqrt_bend = wp.array(np.sqrt(st.bend_stiffness), dtype=wp.float64, device=d)
        self.world = wp.zeros(self.slots, dtype=wp.vec3, device=d)
        self.frame_t = wp.zeros(self.slots, dtype=wp.vec3d, device=d)
        self.frame_n = wp.zeros(self.slots, dtype=wp.vec3d, device=d)

    def unused(self):
        st = self.strands
        out = np.zeros((st.strand_count, st.stride), bool)
        out[:, 0] = out[:, -1] = True
        return out.reshape(-1)

    def bounds(self, max_strain):
        """(stretch, bending) bounds on |u|: max_strain l sqrt(k) and max_strain h sqrt(k_b)."""
        st = self.strands
        ks = np.repeat(st.stretch_stiffness, st.stride).reshape(st.strand_count, st.stride)
        kb = np.repeat(st.bend_stiffness, st.stride).reshape(st.strand_count, st.stride)
        return ((max_strain * self.length * np.sqrt(ks)).reshape(-1),
                np.repeat((max_strain * self.length * np.sqrt(kb)).reshape(-1), 3))

    def write(self, u, q, d):
        """Rest lengths l - u / sqrt(k) and bending rest vectors (b + u / sqrt(k_b) in world space,
        stored in the vertex frames) from the unknowns ``u`` (host float64); returns (L / l of the
        used slots, largest bending change [m])."""
        st, data = self.strands, self.data
        ks = np.repeat(st.stretch_stiffness, st.stride)
        kb = np.repeat(st.bend_stiffness, st.stride)
        du = u[self.stretch_offset: self.bend_offset]
        length = self.length.reshape(-1)
        rest = length - np.where(ks > 0.0, du / np.sqrt(np.where(ks > 0.0, ks, 1.0)), 0.0)
        data["rest_length"].assign(rest.astype(np.float32))
        dw = u[self.bend_offset: self.end].reshape(-1, 3) * np.where(kb > 0.0, 1.0 / np.sqrt(np.where(
            kb > 0.0, kb, 1.0)), 0.0)[:, None]
        self.world.assign((self.bend_geo.reshape(-1, 3) + dw).astype(np.float32))
        wp.launch(KS.bend_rest_from_world, st.strand_count,
                  inputs=[q, st.first, st.stride, data["root_normal"], self.world, 0, data["bend_rest"]], device=d)
        used = length > 0.0
        return rest[used] / length[used], float(np.abs(dw).max()) if len(dw) else 0.0


class _Solver:
    """CGLS for A u = b over the unknowns not masked, with an active set for bounds lo <= u <= hi."""

    def __init__(self, model, q, springs, groups, contacts, unknowns, device_check_every):
        d = self.device = model.device
        n = self.n = model.particle_count
        self.model, self.q, self.groups, self.unknowns = model, q, groups, unknowns
        self.check_every = device_check_every
        m, ij, k_eff = springs
        self.m = m
        if m:
            self.sqrt_k = wp.array(np.sqrt(k_eff), dtype=wp.float64, device=d)
            order = np.argsort(ij.reshape(-1), kind="stable")
            owners = ij.reshape(-1)[order]
            self.adjacency = wp.array((order // 2).astype(np.int32), dtype=int, device=d)
            counts = np.bincount(owners, minlength=n)
            self.offsets = wp.array(np.concatenate([[0], np.cumsum(counts)]).astype(np.int32), dtype=int, device=d)
            self.spring_indices = model.spring_indices
        else:
            self.sqrt_k = wp.zeros(0, dtype=wp.float64, device=d)
            self.adjacency = wp.zeros(0, dtype=int, device=d)
            self.offsets = wp.zeros(n + 1, dtype=int, device=d)
            self.spring_indices = wp.zeros(0, dtype=int, device=d)
        self.contacts = contacts  # (offset, particles (C,), normals (C, 3), scale) or None
        if contacts is not None:
            self.contact_particle = wp.array(contacts[1].astype(np.int32), dtype=int, device=d)
            self.contact_normal = wp.array(contacts[2], dtype=wp.vec3d, device=d)
        self.u = wp.zeros(unknowns, dtype=wp.float64, device=d)
        self.mask = wp.zeros(unknowns, dtype=int, device=d)
        self.p = wp.zeros_like(self.u)
        self.s = wp.zeros_like(self.u)
        self.b = wp.zeros(3 * n, dtype=wp.float64, device=d)
        self.r = wp.zeros_like(self.b)
        self.Ap = wp.zeros_like(self.b)
        self.scalars = wp.zeros(8, dtype=wp.float64, device=d)  # 0 gamma, 1 delta, 2 gamma_new, 3 |r|^2, 4 |b|^2
        self.partial = {}
        self.direct = not m and contacts is None and bool(groups)
        if self.direct:  # strands alone: a direct solve per strand (``solve_direct``)
            inv_mass = model.particle_inv_mass.numpy()
            self.tiny_mass = wp.array(np.where(inv_mass > 0.0, 1.0e-30, 0.0).astype(np.float32), dtype=float, device=d)
            self.zero_v = wp.zeros(n, dtype=wp.vec3, device=d)
            self.y = wp.zeros(n, dtype=wp.vec3, device=d)
            slots = max(g.slots for g in groups)
            self.factors = [wp.zeros(slots, dtype=wp.mat44d, device=d) for _ in range(3)]
            self.factor_rhs = wp.zeros(slots, dtype=wp.vec4d, device=d)

    def apply(self, u_in, f_out):
        """f_out = A u_in (3 per particle, 0 at pinned particles)."""
        d, q, inv_mass = self.device, self.q, self.model.particle_inv_mass
        wp.launch(K.springs_apply, self.n, inputs=[q, self.spring_indices, self.sqrt_k, self.offsets, self.adjacency,
                                                    inv_mass, u_in, 0, f_out], device=d)
        for g in self.groups:
            st = g.strands
            wp.launch(K.strands_apply, st.strand_count,
                      inputs=[q, st.first, st.stride, g.sqrt_stretch, g.sqrt_bend, g.data["root_normal"],
                              g.data["bend_rest"], g.frame_t, g.frame_n, inv_mass, u_in, g.stretch_offset,
                              g.bend_offset, f_out], device=d)
        if self.contacts is not None:
            wp.launch(K.contacts_apply, len(self.contacts[1]),
                      inputs=[self.contact_particle, self.contact_normal, wp.float64(self.contacts[3]), u_in,
                              self.contacts[0], f_out], device=d)

    def apply_transpose(self, r_in, u_out):
        """u_out = A^T r_in, masked unknowns 0."""
        d, q = self.device, self.q
        if self.m:
            wp.launch(K.springs_apply_transpose, self.m, inputs=[q, self.spring_indices, self.sqrt_k, r_in, 0, u_out],
                      device=d)
        for g in self.groups:
            st = g.strands
            wp.launch(K.strands_apply_transpose, st.strand_count,
                      inputs=[q, st.first, st.stride, g.sqrt_stretch, g.sqrt_bend, g.data["root_normal"],
                              g.data["bend_rest"], g.frame_t, g.frame_n, r_in, g.stretch_offset, g.bend_offset, u_out],
                      device=d)
        if self.contacts is not None:
            wp.launch(K.contacts_apply_transpose, len(self.contacts[1]),
                      inputs=[self.contact_particle, self.contact_normal, wp.float64(self.contacts[3]), r_in,
                              self.contacts[0], u_out], device=d)
        wp.launch(K.zero_masked, self.unknowns, inputs=[u_out, self.mask], device=d)

    def dot(self, a, c, slot):
        """scalars[slot] = a . c in a fixed order, the same split on every device: up to 65,536
        strided partial sums, folded into up to 256, summed by one thread (with 1,024 partials of
        ~10,000 terms each, 32 warps kept too few loads in flight: at 3.4 M particles the dot
        products were most of a CGLS iteration on an H100)."""
        threads = max(1, min(65536, a.shape[0]))
        middle = max(1, min(256, threads))
        buf = self.partial.get(threads)
        if buf is None:
            buf = self.partial[threads] = (wp.zeros(threads, dtype=wp.float64, device=self.device),
                                           wp.zeros(middle, dtype=wp.float64, device=self.device))
        wp.launch(K.dot_partial, threads, inputs=[a, c, threads, buf[0]], device=self.device)
        wp.launch(K.fold_partials, middle, inputs=[buf[0], middle, buf[1]], device=self.device)
        wp.launch(K.sum_partials, 1, inputs=[buf[1], self.scalars, slot], device=self.device)

    def solve_direct(self, force, fixed, lo, hi):
        """The least-norm u with A u = -force (strands alone), directly: A A^T over a strand's free
        vertices is the Gauss-Newton stiffness of ``StrandImplicitEuler`` without mass (stretch
        k d d^T, bending k_b J^T J with the frames' twist), so its per-strand block band Cholesky
        (one thread per strand, float64) gives y = -(A A^T)^-1 force and u = A^T y (the exact
        transpose, frames included). Returns (u host, 0 iterations), or None when u leaves its
        bounds (CGLS with its active set takes the round)."""
        d = self.device
        for g in self.groups:
            st, data = g.strands, g.data
            wp.launch(KI.strand_implicit_solve, st.strand_count,
                      inputs=[self.q, self.zero_v, force, self.tiny_mass, st.first, st.stride, g.length32,
                              data["bend_rest"], data["stretch_stiffness"], data["bend_stiffness"], g.zero_s, g.zero_s,
                              data["root_normal"], 0.0, -1, 0.0, 0.0, 1.0, *self.factors, self.factor_rhs, 1, self.y],
                      device=d)
        wp.launch(K.flat_from_vec3, self.n, inputs=[self.y, self.model.particle_inv_mass, wp.float64(-1.0), self.r],
                  device=d)
        self.mask.assign(fixed.astype(np.int32))
        self.apply_transpose(self.r, self.u)
        u = self.u.numpy()
        if (((u < lo) | (u > hi)) & ~fixed).any():
            return None
        return u, 0

    def solve(self, fixed, lo, hi, rtol, max_iterations):
        """u with A u ~ b (self.b) of least norm, lo <= u <= hi; ``fixed`` (bool) unknowns stay 0.
        Returns (u host float64, CGLS iterations)."""
        d, n, unknowns = self.device, self.n, self.unknowns
        mask_host = fixed.astype(np.int32)
        u_host = np.zeros(unknowns)
        self.u.zero_()
        self.mask.assign(mask_host)
        self.dot(self.b, self.b, 4)
        bb = float(self.scalars.numpy()[4])
        iterations = 0
        sc = self.scalars
        for _ in range(64):
            self.apply(self.u, self.Ap)
            wp.launch(K.subtract_masked, 3 * n, inputs=[self.b, self.Ap, self.r], device=d)
            self.apply_transpose(self.r, self.s)
            wp.copy(self.p, self.s)
            self.dot(self.s, self.s, 0)
            gamma0 = float(sc.numpy()[0])
            while iterations < max_iterations and gamma0 > 0.0:
                for _ in range(self.check_every):
                    self.apply(self.p, self.Ap)
                    self.dot(self.Ap, self.Ap, 1)
                    wp.launch(K.axpy_ratio, unknowns, inputs=[self.u, self.p, sc, 0, 1, wp.float64(1.0)], device=d)
                    wp.launch(K.axpy_ratio, 3 * n, inputs=[self.r, self.Ap, sc, 0, 1, wp.float64(-1.0)], device=d)
                    self.apply_transpose(self.r, self.s)
                    self.dot(self.s, self.s, 2)
                    wp.launch(K.cg_direction, unknowns, inputs=[self.p, self.s, sc, 2, 0], device=d)
                    wp.launch(K.copy_scalar, 1, inputs=[sc, 2, 0], device=d)
                    iterations += 1
                self.dot(self.r, self.r, 3)
                values = sc.numpy()
                if values[3] <= rtol * rtol * bb or values[0] <= 1.0e-28 * gamma0:
                    break
            u_host = self.u.numpy()
            over = ((u_host < lo) | (u_host > hi)) & (mask_host == 0)
            if not over.any() or iterations >= max_iterations:
                break
            u_host[over] = np.clip(u_host[over], lo[over], hi[over])  # held at the bound from now on
            mask_host[over] = 1
            self.mask.assign(mask_host)
            self.u.assign(u_host)
        return np.clip(u_host, lo, hi), iterations


def sag_free(target, *, forces=None, max_strain: float = 0.2, tol: float = 1.0e-2, rounds: int = 12,
             rtol: float = 1.0e-10, max_iterations: int = 50000, device_check_every: int = 25) -> SagFreeReport:
    """Make the current positions of ``target`` (a ``ws.Simulator``: its state and forces; or a
    ``ws.Model``: its initial positions under ``forces``, default ``[ws.Gravity()]``) a static
    equilibrium by changing rest lengths and strand bending rest states in place (module
    docstring). Returns a :class:`SagFreeReport`.

    max_strain: bound on |L / l - 1| (0 < max_strain < 1) and on the bending rest change per
    segment length. tol: the largest residual force accepted, relative to the largest load
    (ValueError naming the particle and strand when the bounds leave more; a warning when more is
    left with no bound hit). rounds: global-local
    rounds at most (they stop when the residual stops falling). rtol: a CGLS solve stops when
    |residual| <= rtol |load|; max_iterations: CGLS iterations per round."""
    max_strain = checks.in_range(max_strain, "sag_free max_strain", 0.0, 1.0, lo_open=True, hi_open=True,
                                 fix="a bound on |L / l - 1| such as 0.2")
    tol = checks.positive(tol, "sag_free tol", fix="a relative residual force such as 1e-2")
    rounds = checks.count(rounds, "sag_free rounds", fix="e.g. 12")
    rtol = checks.positive(rtol, "sag_free rtol", fix="e.g. 1e-10")
    max_iterations = checks.count(max_iterations, "sag_free max_iterations", fix="e.g. 50000")
    device_check_every = checks.count(device_check_every, "sag_free device_check_every", fix="e.g. 25")
    model, system, q = _system_of(target, forces)
    d = model.device
    n = model.particle_count
    inv_mass = model.particle_inv_mass.numpy()
    x = q.numpy().astype(np.float64)
    bad = np.flatnonzero(~np.isfinite(x).all(axis=1))
    if len(bad):  # NaN in, NaN residuals out: "converged" with residual 0 would be a lie
        more = f" ({len(bad)} particles in all)" if len(bad) > 1 else ""
        raise ValueError(f"sag_free: particle {int(bad[0])} has position {x[bad[0]].tolist()}, not finite{more}; give "
                         "finite positions (a simulation that blew up must be rebuilt first)")
    has_springs = model.spring_count > 0 and any(isinstance(f, Springs) for f in system.forces)

    # ---- unknowns, the geometric rest state (no internal force at the current positions), bounds --
    m = model.spring_count if has_springs else 0
    ij: Any = None  # set with the springs below (m > 0)
    k_eff: Any = None
    spring_l: Any = None
    if m:
        ij = model.spring_indices.numpy().reshape(-1, 2)
        spring_l = np.linalg.norm(x[ij[:, 0]] - x[ij[:, 1]], axis=1)
        broken = model.spring_broken.numpy() != 0 if hasattr(model, "spring_broken") else np.zeros(m, bool)
        k_eff = np.where(broken | (spring_l <= 0.0), 0.0, model.spring_stiffness.numpy().astype(np.float64))
        spring_rest_before = model.spring_rest_length.numpy().astype(np.float64)
    groups, offset = [], m
    for f in system.forces:
        if isinstance(f, StrandForce):
            groups.append(_Group(f, offset, x, d))
            offset = groups[-1].end
    contacts = _plane_contacts(target, model, x, inv_mass, offset, m, k_eff)
    if contacts is not None:
        offset += len(contacts[1])
    unknowns = offset
    fixed = np.zeros(unknowns, bool)
    bound = np.full(unknowns, np.inf)
    lower = np.full(unknowns, -np.inf)  # the supports push only: lower bound 0 on their unknowns
    if m:
        fixed[:m] = k_eff == 0.0
        bound[:m] = max_strain * spring_l * np.sqrt(k_eff)
    for g in groups:
        st = g.strands
        unused = g.unused()
        fixed[g.stretch_offset: g.bend_offset] = unused | np.repeat(st.stretch_stiffness == 0.0, st.stride)
        fixed[g.bend_offset: g.end] = np.repeat(unused | np.repeat(st.bend_stiffness == 0.0, st.stride), 3)
        bound[g.stretch_offset: g.bend_offset], bound[g.bend_offset: g.end] = g.bounds(max_strain)
    lower = np.maximum(lower, -bound)
    if contacts is not None:
        lower[contacts[0]:] = 0.0

    def write(u):
        ratios, bend_change = [], 0.0
        if m:
            safe = np.sqrt(np.where(k_eff > 0.0, k_eff, 1.0))
            rest = np.where(k_eff > 0.0, spring_l - u[:m] / safe, spring_rest_before)
            model.spring_rest_length.assign(rest.astype(np.float32))
            live = (k_eff > 0.0) & (spring_l > 0.0)
            ratios.append(rest[live] / spring_l[live])
        for g in groups:
            r, b = g.write(u, q, d)
            ratios.append(r)
            bend_change = max(bend_change, b)
        return ratios, bend_change

    u = np.zeros(unknowns)
    write(u)
    zeros_v = wp.zeros(n, dtype=wp.vec3, device=d)
    time = wp.zeros(1, dtype=float, device=d)
    force = wp.zeros(n, dtype=wp.vec3, device=d)

    def residual():
        """|force| per particle (0 at pinned ones): the simulator's forces plus the supports; the
        total is left in ``force`` for the next global step."""
        system.eval_forces(q, zeros_v, time, 0.0, force)
        if contacts is not None and u.any():
            total = force.numpy()
            c0, particles, normals, scale = contacts
            total[particles] += (scale * u[c0: c0 + len(particles)])[:, None] * normals
            force.assign(total)
        f = np.linalg.norm(force.numpy(), axis=1)
        f[inv_mass <= 0.0] = 0.0
        return f

    f = residual()  # the load: external forces alone at the geometric rest state
    load_max = float(f.max()) if len(f) else 0.0
    iterations, done_rounds, limited = 0, 0, False
    if unknowns and load_max > 0.0:
        solver = _Solver(model, q, (m, ij, k_eff), groups, contacts, unknowns, device_check_every)
        best = (float(f.max()), u.copy())
        for done_rounds in range(1, rounds + 1):
            # global step: the least-energy correction that cancels the measured residual force
            wp.launch(K.external_rhs, n, inputs=[force, model.particle_inv_mass, solver.b], device=d)
            direct = solver.solve_direct(force, fixed, lower - u, bound - u) if solver.direct else None
            du, its = direct if direct is not None else solver.solve(fixed, lower - u, bound - u, rtol, max_iterations)
            iterations += its
            u = u + du
            at = np.isfinite(bound) & (bound > 0.0) & (np.abs(np.abs(u) - bound) <= 1.0e-9 * bound)
            limited |= bool(at.any())
            write(u)
            f = residual()  # local step: every particle's force balance at the new rest state
            if f.max() < best[0]:
                improved = f.max() < 0.5 * best[0]
                best = (float(f.max()), u.copy())
                if not improved:
                    break
            else:
                break
        u = best[1]
    ratios, bend_change = write(u)
    f = residual()
    worst = int(np.argmax(f)) if len(f) else 0
    residual_max = float(f[worst]) if len(f) else 0.0
    at_bound = np.isfinite(bound) & (bound > 0.0) & (np.abs(np.abs(u) - bound) <= 1.0e-9 * bound)
    report = SagFreeReport(residual_max, load_max, residual_max / load_max if load_max > 0.0 else 0.0, done_rounds,
                           iterations, max_strain)
    if m:
        report.springs_at_bound = np.flatnonzero(at_bound[:m]).tolist()
    for g in groups:
        stride = g.strands.stride
        hit = np.flatnonzero(at_bound[g.stretch_offset: g.bend_offset])
        report.strand_segments_at_bound += [(int(h // stride), int(h % stride) - 1) for h in hit]
        hit = np.flatnonzero(at_bound[g.bend_offset: g.end].reshape(-1, 3).any(axis=1))
        report.strand_vertices_at_bound += [(int(h // stride), int(h % stride) - 1) for h in hit]
    if ratios:
        allr = np.concatenate(ratios)
        if len(allr):
            report.rest_ratio_min, report.rest_ratio_max = float(allr.min()), float(allr.max())
    report.bend_change_max = bend_change
    if contacts is not None:
        c0, particles, _, scale = contacts
        report.support_particles = particles.tolist()
        report.support_forces = (scale * u[c0: c0 + len(particles)]).tolist()
    if load_max > 0.0 and residual_max > tol * load_max:
        where = f"particle {worst}"
        for g in groups:
            found = g.strands.strand_of(worst)
            if found is not None:
                where = f"strand {found[0]} (vertex {found[1] - 1} from the root, particle {worst})"
        bound_count = (len(report.springs_at_bound) + len(report.strand_segments_at_bound)
                       + len(report.strand_vertices_at_bound))
        left = (f"{where} keeps a residual force of {residual_max:.3g} N ({100 * report.residual_relative:.3g} % of "
                f"the largest load {load_max:.3g} N, tolerance {100 * tol:.3g} %)")
        if bound_count or limited:
            raise ValueError(
                f"sag_free: the bound max_strain={max_strain:g} cannot be met: {left}; rest states within the bound "
                f"cannot carry the load (the solve hit the bound; {bound_count} unknowns end at it); raise max_strain, "
                "stiffen the springs or lighten the model")
        # nothing at a bound: float32 rounding of very stiff springs (about k * 1e-8 m) or too few
        # iterations, not an impossible load
        warnings.warn(f"sag_free: {left} with no bound hit; raise max_iterations or tol", stacklevel=2)
    return report
