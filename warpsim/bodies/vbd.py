"""VBD: backward Euler for mass-spring bodies by vertex block descent, with contact inside the descent
(Chen et al., "Vertex Block Descent", SIGGRAPH 2024; the step bound after Chen et al., "Offset
Geometric Contact", SIGGRAPH 2025). Kernels: ``warpsim.kernels.vbd`` (the descent) and
``warpsim.kernels.vbd_contact`` (search, contact energies, bounds); contact topology and search:
:class:`warpsim.bodies.vbd_contact.VBDContact`.

A step of h [s] minimises backward Euler's incremental potential G (inertia ``m / (2 h^2) |x - y|^2``,
the springs, the contacts) by ``iterations`` sweeps over the particle colours, each particle a 3x3
Newton step with the others held (``kernels.vbd``), Chebyshev-accelerated, from VBD's adaptive
initial guess. Converged it is backward Euler (tested against ``ImplicitEuler``); stopped early it
is still unconditionally stable and dissipates: the number of iterations sets the accuracy, not the stability.
Each Newton step d is checked at its end (``kernels.vbd.accepts``): taken when the force there does not push back
along it harder than the force at its start pushed along it (f_end . d >= -f_start . d: along a step where the
particle's share of G is quadratic, exactly "d does not raise it"), else halved up to ``line_search`` times, else
not taken. Only a particle that can touch a contact before the next search is checked (``kernels.vbd.may_touch``: a
kept pair, a plane or sphere in reach); elsewhere the step is taken whole (its inertia and springs alone: on the
CPU's pressed 4-torus heap checking every particle or only these came to rest alike, 0.029 m/s and 0.12-0.15
searches a step; on the H200 checking every particle in the solve kernel made a 100-torus sweep 3.2x the plain one's
time, these alone in a launch of their own 2.3x). The blocks' models are positive semi-definite (a compressed
spring's and a contact's negative curvature dropped) and a contact not yet touched has none, so a whole step can
overshoot where G is not quadratic: into a contact, across a spring it compresses. Unchecked, the sweeps of a heap
pressed by contacts 50x stiffer than its springs cycled instead of converging (200 sweeps, vertices still moving 2-3
mm a sweep) and the resting heap jittered at 0.7 m/s (benchmarks/RESULTS.md); checked, it comes to rest. The check
uses forces only, so the springs' damping (no potential) is held to it too, and a converged step is still backward
Euler's. Most particles of a large heap have no contact within reach of their bound until the next search; with
``split`` the sweeps solve those a thread each over their springs alone (``kernels.vbd.solve_free``) and the colour
solve, with its contact lists, lanes and check, runs over the rest only.

No primitive passes through another (the step bound). At a search (the step's start, then every
``detect_every`` iterations) at positions x^d, let for each particle i::

    D_i = min( d(i, T) over triangles T not containing i,
               d(T', j) over triangles T' containing i and vertices j not in T',
               d(e, e') over edges e containing i and edges e' sharing no particle with e,
               d(i, plane or sphere) over the static shapes )

over the pairs listed at x^d: those closer than their radius r_c + C_a + C_b, where C_p in [b_min, b_max] is
particle p's cap, set at the search from its motion (``VBDContact``; b_max for all when the caps are fixed) and a
primitive's C is the largest of its particles'. Then b_i = min(gamma D_i, C_i) with gamma < 1/2. Until the next
search every position update is
clipped to ``|x_i - x_i^d| <= b_i`` (the initial guess, each Newton step, each Chebyshev extrapolation,
and after each search within the step the part of the initial guess the bound cut, ``restore_guess``).

Claim: no vertex-triangle or edge-edge pair that is apart at a search meets before the next one,
along the straight path of any update in between, so no edge passes through a triangle.
Proof. Vertex i and triangle T (i not in T), distance d = d(i, T) > 0 at x^d. Every point of T is
a convex combination sum w_k x_k of its corners, so it moves by at most ``max_k |dx_k| <= max_k b_k``;
the distance function is 1-Lipschitz in each argument, so at any later positions
``d' >= d - |dx_i| - max_k b_k``. If the pair is listed: D_i <= d (first term) and D_k <= d for each corner k
of T (second term, j = i), so ``|dx_i| <= gamma d`` and ``b_k <= gamma d``: d' >= (1 - 2 gamma) d > 0. If not,
d >= r_c + C_i + C_T, and b_i <= C_i, b_k <= C_k <= C_T: d' >= d - C_i - C_T >= r_c > 0. Edges e, e' sharing no
particle: each closest point is a convex combination of its edge's ends, each end k of e has D_k <= d(e, e')
(third term), likewise for e', so d' >= (1 - 2 gamma) d > 0 when listed, d' >= r_c when not. A plane or sphere
is static:
d' >= (1 - gamma) d. Every intermediate position of an update lies on the segment between two points
of the ball ``|x - x^d| <= b`` (the ball is convex), so the bounds hold along the path too. A pair of
closed surfaces that starts apart can interpenetrate only through a vertex crossing a triangle or an
edge crossing an edge, and neither pair's distance reaches 0; hence no edge passes through a
triangle. Since d' > 0 for every pair, no vertex is ever deeper than the thickness r_c either.
(Pairs within one body count only with ``self_contact``; pairs sharing a particle never.)

The same positions give the contact pairs: a pair not listed at a search closes by at most C_a + C_b before
the next, so it stays beyond r_c and exerts nothing; every pair that can push is listed. (The caps change only
at a search that runs, so they are those the lists were built with.) A search may be skipped, the one opening a
step as those within it (every particle still within
``renew_fraction`` of its bound from its reference, nothing of its guess cut): the bounds and lists of the last
search then hold until the next one that runs, as the claim above needs (it asks only that every update until the
next search be clipped to the last search's bounds, which the initial guess of the next step is too; a position
set from outside, a reset or a world's new state, farther than that from the reference makes the next search
run). The first step's search always runs. Of the listed pairs the sweeps gather only those that can
still come within r_c: a pair at distance D at the search whose sides' bounds are b_a and b_b stays at least
D - b_a - b_b apart (as above), so one with D - b_a - b_b >= r_c exerts nothing until the next search and is left out
(``kernels.vbd_contact.keep_near_pairs``; the sums, hence the bits, are those of the whole lists). Everything is
gathered per particle in fixed order (CSR rows, per-query lists written by their own thread; with ``lanes`` > 1 the
lanes' partial sums added by a fixed-order tile reduction): two runs give the same bits; a step allocates nothing
and reads nothing back.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from ..core import checks
from ..core.colouring import colour_groups, greedy_colouring, tile_colouring
from ..core.forces import Springs
from ..core.integrators import Integrator
from ..core.model import ensure_spring_adjacency
from ..core.stability import STABILITY_NOTES, StabilityWarning
from ..kernels import fast_mass_spring as FK
from ..kernels import vbd as K
from .vbd_contact import VBDContact

LISTED_BLOCKS_PER_SM = 32
"""Blocks a multiprocessor of a listed colour solve in lanes on CUDA (``kernels.vbd.solve_colour_lanes``): a launch of
at most this many blocks a multiprocessor, each taking every G-th listed particle, instead of a block a particle (32
blocks are what a multiprocessor of sm_90 holds at once)."""


def chebyshev_weights(rho: float, iterations: int) -> list:
    """Chebyshev weights omega_k of ``iterations`` iterations for spectral radius estimate ``rho``
    (Wang 2015, as VBD): 1, 2 / (2 - rho^2), then 4 / (4 - rho^2 omega_{k-1}); all 1 when rho = 0."""
    omegas = [1.0]
    for k in range(1, iterations):
        omegas.append(2.0 / (2.0 - rho * rho) if k == 1 else 4.0 / (4.0 - rho * rho * omegas[-1]))
    return omegas


class VBD(Integrator):
    """Backward Euler by vertex block descent (module docstring).

    Args:
        iterations: colour sweeps a step (accuracy, not stability; default 10).
        contact: a :class:`VBDContact` (contact energies inside the descent and the step bound), or None.
        body_size: particles of one copy when the model is copies of one body (P): the colouring of
            copy 0 is reused (a heap of 1,000 tori colours one torus); None: the whole model.
        chebyshev_rho: spectral radius estimate of the Chebyshev acceleration in [0, 1) (0: off;
            VBD uses 0.9-0.95; on the donut heap 0.9 with 12 iterations gained 13 % energy at the first
            impacts, so off by default).
        detect_every: iterations between contact searches within a step (a search opens the step, skipped
            at rest as those within it: ``renew_fraction``); 0: only that one. Each search lets a particle move
            another C_p (its cap, at most b_max) at most.
        adaptive_guess: VBD's adaptive initial guess (off: y, the inertial target).
        renew_fraction: a search (opening a step, or within it every ``detect_every`` iterations) runs only when
            some particle has moved more than this fraction of its bound since the last search or has some of its
            initial guess cut (decided on the device: a heap at rest skips them); None: always. The first step's
            opening search always runs.
        lanes: threads that share one particle's sums in a colour solve (B; the kernel
            ``kernels.vbd.solve_colour_lanes``: each lane sums every B-th spring and contact list entry, the B
            partial forces and Hessians added by a fixed-order tile reduction, so runs repeat bit for bit);
            1: a thread a particle (``solve_colour``); None: 32 on CUDA, 1 on the CPU. A colour holds a few
            thousand particles, a thread each fills ~1 % of a large GPU and runs as long as the particle with the
            longest lists (hundreds of entries, serial dependent gathers); 32 lanes are one warp (a shuffle-only
            reduction, no shared memory, no block barrier beyond the warp), keep ~10 entries a lane on the
            longest lists and put the colour's few thousand warps on every multiprocessor. On the CPU Warp runs a
            block's lanes one after another as fibers, and only with ``wp.config.enable_cpu_blocks`` (else a
            block is one lane: the sums of ``lanes`` = 1), so a thread a particle is faster there. The sums'
            order differs with B (other bits, the same physics; each B repeats its own bits).
        max_registers: with ``lanes`` > 1 on CUDA, the registers a thread of the colour solve at most: 64
            (``kernels.vbd.solve_colour_lanes_compact``: more warps resident, the rest spilled to local memory), None
            (the compiler's choice, 161 on sm_90) or "auto" (the default: 64 when the largest colour holds more
            particles than 32 warps x the device's multiprocessors, the warps resident at 64 registers; measured on
            an H200, 132 multiprocessors: 64 made a sweep of 100 tori, 19,000 particles a colour, 26 % faster and
            one of 12 tori, 2,300 a colour, 16-18 % slower). The same sums in the same order either way: the same bits.
        line_search: halvings of a particle's Newton step tried when the force at the step's end pushes back
            along it harder than the force at its start pushed (the module docstring); when none passes the particle
            stays. 0: every step taken whole (plain VBD, the colour solve without the check). A sweep evaluates the
            forces of each particle that can touch a contact once more, and once more a halving; each colour's solve
            is followed by a launch of ``kernels.vbd.check_colour``.
        split: whether each sweep solves apart the particles that no contact can reach before the next search: after
            each search (run or skipped) the others are listed by colour (``kernels.vbd.list_contact_particles``: a
            kept pair, or a plane or sphere within the thickness + 3 bounds of the search's positions) and solved
            and checked by the colour solve (in lanes on CUDA, every G-th of the colour's list a block), the rest by
            ``kernels.vbd.solve_free``, a thread each over its inertia and springs alone (for them the contacts add
            nothing: the same Newton step; on the CPU, a thread a particle either way, the same bits). True, False
            (every particle by the colour solve) or "auto" (the default: on the CPU, and on CUDA when the largest
            colour holds more particles than 32 x the device's multiprocessors, as ``max_registers``; on an H200 a
            split sweep of 1,000 falling tori, 2.6 % of the particles listed, took 4.07 ms against 9.95 ms for the
            tree before split sweeps (in another call), and in one call each one of 100 tori at rest 4.30 against
            4.63 ms unsplit, one of 12 tori 1.54 against 0.99 ms: benchmarks/RESULTS.md).

    Forces other than the model's springs (gravity, drags) are taken at the step's start into y.
    """

    name = "vbd"
    explicit_forces = True
    """Forces other than the springs enter at the step's start (``warpsim.core.stability.force_method_of``)."""
    springs_per_copy = True
    """Each copy's springs are read from the model (only the colouring is shared): worlds of a sweep may
    vary stiffness, damping and masses (``warpsim.worlds.batch``)."""

    def __init__(self, iterations: int = 10, *, contact: VBDContact | None = None, body_size: int | None = None,
                 chebyshev_rho: float = 0.0, detect_every: int = 5, adaptive_guess: bool = True,
                 renew_fraction: float | None = 0.5, lanes: int | None = None,
                 max_registers: int | str | None = "auto", line_search: int = 4, split: bool | str = "auto"):
        super().__init__()
        self.iterations = checks.integer(iterations, "VBD iterations", lo=1, hi=100_000, fix="e.g. 10")
        if contact is not None and not isinstance(contact, VBDContact):
            raise ValueError(f"VBD contact is {type(contact).__name__}; give a ws.VBDContact or None")
        self.contact = contact
        self.body_size = None if body_size is None else checks.integer(
            body_size, "VBD body_size", lo=1, hi=1 << 40, fix="the particles of one copy, or None")
        self.chebyshev_rho = checks.in_range(chebyshev_rho, "VBD chebyshev_rho", 0.0, 0.999,
                                             fix="e.g. 0.9, or 0 for no acceleration")
        self.detect_every = checks.integer(detect_every, "VBD detect_every", lo=0, hi=100_000,
                                           fix="iterations between contact searches, e.g. 5 (0: one a step)")
        self.adaptive_guess = checks.flag(adaptive_guess, "VBD adaptive_guess")
        self.renew_fraction = None if renew_fraction is None else checks.in_range(
            renew_fraction, "VBD renew_fraction", 0.0, 1.0, fix="e.g. 0.5, or None to search every time")
        self.lanes = None if lanes is None else checks.integer(
            lanes, "VBD lanes", lo=1, hi=1024, fix="threads a particle in a colour solve, e.g. 32 (1: a thread a "
            "particle), or None (32 on CUDA, 1 on the CPU)")
        if max_registers not in (None, K.COMPACT_REGISTERS, "auto"):
            raise ValueError(f"VBD max_registers is {max_registers!r}; give {K.COMPACT_REGISTERS} (the compact colour "
                             "solve), None (the compiler's choice) or 'auto'")
        self.max_registers = max_registers
        self.line_search = checks.integer(line_search, "VBD line_search", lo=0, hi=64,
                                          fix="halvings of a Newton step tried, e.g. 4 (0: every step taken whole)")
        if split not in (True, False, "auto"):
            raise ValueError(f"VBD split is {split!r}; give True (the particles that can touch a contact solved apart "
                             "from the rest), False (every particle by one colour solve) or 'auto'")
        self.split = split
        self._omegas = chebyshev_weights(self.chebyshev_rho, self.iterations)

    @property
    def searches_per_step(self) -> int:
        """Contact searches a step at most: the one opening it and one every ``detect_every`` iterations."""
        return 1 + ((self.iterations - 1) // self.detect_every if self.detect_every else 0)

    def compact_on(self, device) -> bool:
        """Whether the colour solve on ``device`` is the compact one (``max_registers``; "auto": on CUDA when the
        prepared model's largest colour holds more particles than 32 x the device's multiprocessors)."""
        if self.max_registers != "auto":
            return self.max_registers is not None
        d = wp.get_device(device)
        largest = max((b - a for a, b in zip(self.colour_offsets, self.colour_offsets[1:])), default=0)
        return bool(d.is_cuda and largest > 32 * d.sm_count)

    def split_on(self, device) -> bool:
        """Whether the sweeps on ``device`` solve the particles that can touch a contact apart from the rest (``split``;
        "auto": on the CPU, and on CUDA when the prepared model's largest colour holds more particles than 32 x the
        device's multiprocessors, as ``compact_on``)."""
        if self.split != "auto":
            return bool(self.split)
        d = wp.get_device(device)
        largest = max((b - a for a, b in zip(self.colour_offsets, self.colour_offsets[1:])), default=0)
        return bool(not d.is_cuda or largest > 32 * d.sm_count)

    def lanes_on(self, device) -> int:
        """Threads a particle in a colour solve on ``device`` (``lanes``; None: 32 on CUDA, 1 on the CPU)."""
        if self.lanes is not None:
            return self.lanes
        return 32 if wp.get_device(device).is_cuda else 1

    def tile_worlds(self, world_count: int, world_particle_count: int) -> None:
        """For a batch of worlds laid end to end (``warpsim.worlds.batch``, on the batch's copy of this
        integrator): the contact keeps each world's bodies to their own world."""
        if self.contact is not None:
            self.contact = self.contact.tile(world_count, world_particle_count)

    def colours(self, model) -> np.ndarray:
        """Colour of each particle (N,): a greedy colouring of copy 0's springs tiled over the copies
        (``body_size``) or of the whole model; ValueError if a spring joins two particles of one colour
        (copies that differ, or springs between copies)."""
        n = model.particle_count
        springs = model.spring_indices.numpy().reshape(-1, 2) if model.spring_count else np.zeros((0, 2), np.int64)
        if self.body_size is None:
            return greedy_colouring(n, springs)
        P = self.body_size
        if n % P:
            raise ValueError(f"VBD body_size = {P} does not divide the model's {n} particles; give the particles of "
                             "one copy, or None")
        first = springs[(springs < P).all(1)]
        colours = tile_colouring(greedy_colouring(P, first), n // P)
        clash = np.flatnonzero(colours[springs[:, 0]] == colours[springs[:, 1]]) if len(springs) else []
        if len(clash):
            i, j = springs[clash[0]]
            raise ValueError(f"VBD body_size = {P}: spring {int(clash[0])} joins particles {int(i)} and {int(j)}, "
                             "which copy 0's colouring gives one colour (the copies differ, or a spring joins two "
                             "copies); give body_size=None")
        return colours

    def _allocate(self, system) -> None:
        model = getattr(system, "model", None)
        if model is None or system.dtype is not wp.vec3:
            raise ValueError(f"VBD steps particle systems (springs of a Model); use implicit_euler for "
                             f"{type(system).__name__}")
        n, d = system.count, system.device
        self.model = model
        ensure_spring_adjacency(model)
        self._recorded_key: tuple | None = None
        colours = self.colours(model)
        offsets, particles = colour_groups(colours)
        self.particle_colour = wp.array(colours, dtype=int, device=d)
        """Colour of each particle (N,): the contact's Hessian blocks count the pair's particles of the same colour."""
        self.colour_offsets = [int(o) for o in offsets]
        """Start of each colour in ``colour_particles`` (host list, C + 1)."""
        self.colour_particles = wp.array(particles, dtype=int, device=d)
        self._colour_starts = wp.array(self.colour_offsets, dtype=int, device=d)
        self._listed = wp.zeros(n, dtype=int, device=d)
        """1 where a particle can touch a contact before the next search (``kernels.vbd.list_contact_particles``)."""
        self._colour_list = wp.zeros(n, dtype=int, device=d)
        """Those particles, colour c's from ``colour_offsets[c]`` (N,)."""
        self._listed_count = wp.zeros(len(self.colour_offsets) - 1, dtype=int, device=d)
        """How many of each colour are listed (C,)."""
        self._empty_ints = wp.zeros(0, dtype=int, device=d)
        self._other_forces = [f for f in system.forces if not isinstance(f, Springs)]
        self.f_ext = wp.zeros(n, dtype=wp.vec3, device=d)
        self.q0 = wp.zeros(n, dtype=wp.vec3, device=d)
        self.y = wp.zeros(n, dtype=wp.vec3, device=d)
        self.q_new = wp.zeros(n, dtype=wp.vec3, device=d)
        self.deficit = wp.zeros(n, dtype=wp.vec3, device=d)
        """What the bound cut from each particle's initial guess and no search has given back yet [m]."""
        self.qd_prev = wp.array(model.particle_qd.numpy(), dtype=wp.vec3, device=d)
        """Each particle's velocity at the start of the last step [m/s] (the adaptive guess's last acceleration)."""
        self._fresh = True  # no last step yet: the first takes the external acceleration as the last (forget_history)
        self._force = wp.zeros(0, dtype=wp.vec3, device=d)
        """Each particle's force [N] at the start of its last Newton step (``line_search``; else empty)."""
        self._step = wp.zeros(0, dtype=wp.vec3, device=d)
        """Each particle's last Newton step [m] before its clip (``line_search``; else empty)."""
        self._empty = wp.zeros(0, dtype=wp.vec3, device=d)
        row_lengths = np.diff(model.particle_spring_offsets.numpy())
        self._entry_particle = wp.array(np.repeat(np.arange(n, dtype=np.int32), row_lengths), dtype=int, device=d)
        """Particle of each entry of the CSR spring rows (E = 2 springs,)."""
        self._springs = wp.empty(len(self._entry_particle), dtype=K.SpringEntry, device=d)
        """The entries packed for the step's sweeps (``kernels.vbd.pack_springs``), (E,)."""
        chebyshev = self.chebyshev_rho > 0.0
        self._older = wp.zeros(n if chebyshev else 0, dtype=wp.vec3, device=d)
        self._old = wp.zeros(n if chebyshev else 0, dtype=wp.vec3, device=d)
        broken = getattr(model, "spring_broken", None)
        self._broken = broken if broken is not None else wp.zeros(model.spring_count, dtype=int, device=d)
        if self.contact is not None:
            self.contact.bind(model)
            self._reference, self._bound = self.contact.reference, self.contact.bound
            self._contact_inputs = self.contact.solve_inputs()
        else:
            empty = wp.zeros(0, dtype=int, device=d)
            self._reference = wp.zeros(n, dtype=wp.vec3, device=d)
            self._bound = wp.full(n, 1.0e30, dtype=float, device=d)
            self._contact_inputs = [wp.full(n, -1, dtype=int, device=d), empty, empty, 0, empty, empty, empty, empty,
                                    empty, empty, empty, empty, empty, empty, empty, empty, 0,
                                    *[wp.zeros(0, dtype=float, device=d)] * 3, wp.zeros(0, dtype=wp.vec4, device=d),
                                    wp.zeros(0, dtype=wp.vec4, device=d), 0.0, 0.0, 0.0, 1.0]

    @property
    def colour_count(self) -> int:
        """Colours of the prepared model (one launch each a sweep, and one commit)."""
        return len(self.colour_offsets) - 1

    def _record(self, q, qd, h: float) -> None:
        """Record the step's launches once per (positions, velocities, step size): a replayed launch
        skips ``wp.launch``'s argument packing, most of a launch's host time (CPU: 40 arguments a
        colour solve)."""
        m, d, n = self.model, self.model.device, self.model.particle_count
        if self.chebyshev_rho > 0.0 and not getattr(self, "_chebyshev_warned", False):
            import warnings

            self._chebyshev_warned = True
            warnings.warn(f"VBD: {self.stability_note}", StabilityWarning, stacklevel=4)

        def record(kernel, dim, inputs):
            return wp.launch(kernel, dim, inputs=inputs, device=d, record_cmd=True)

        springs = [m.particle_spring_offsets, self._springs]
        if self.contact is not None:  # its thickness, stiffness and friction as they are now
            self._contact_inputs = self.contact.solve_inputs()
            self.contact.set_motion(qd, self.qd_prev, self.f_ext, m.particle_inv_mass, self.deficit, h,
                                    self.adaptive_guess)
        self._predict = record(K.predict, n, [qd, self.qd_prev, self.f_ext, m.particle_inv_mass, h,
                                               int(self.adaptive_guess), self._reference, self._bound, q, self.q0,
                                               self.y, self.deficit, self.q_new])
        self._pack = record(K.pack_springs, len(self._entry_particle), [
            self._entry_particle, m.particle_springs, m.spring_indices, m.spring_rest_length, m.spring_stiffness,
            m.spring_damping, self._broken, self.q0, self._springs])
        self._restore = record(K.restore_guess, n, [self._reference, self._bound, self.deficit, q, self.q_new])
        # a sweep starts with q_new = q (predict, restore_guess and the Chebyshev step keep it so); colour c reads
        # one buffer and writes the other, copying colour c - 1 across (kernels.vbd's docstring), and the last
        # colour is committed to the buffer it did not write: one launch a colour and one a sweep
        buffers, offsets = (q, self.q_new), self.colour_offsets
        lanes = self.lanes_on(d)
        checked = self.line_search > 0
        # each particle's force at its step's start and its step, for the check: allocated when the launches are
        # recorded with line_search on (the first step, or the step after it is turned on), never within a step
        if checked and self._step.shape[0] != n:
            self._force = wp.zeros(n, dtype=wp.vec3, device=d)
            self._step = wp.zeros(n, dtype=wp.vec3, device=d)
        outputs = [self._force, self._step] if checked else [self._empty, self._empty]
        split = self.contact is not None and self.split_on(d)
        if lanes > 1:  # a block of lanes a particle (kernels.vbd.solve_colour_lanes)
            kernel = K.solve_colour_lanes_compact if self.compact_on(d) else K.solve_colour_lanes
            check_kernel = K.check_colour_lanes
            device = wp.get_device(d)
            blocks = LISTED_BLOCKS_PER_SM * device.sm_count if device.is_cuda and split else None

            def grid_of(count):  # blocks (split on CUDA: at most LISTED_BLOCKS_PER_SM a multiprocessor)
                return count if blocks is None else min(count, blocks)

            def solve(kernel, grid, inputs):
                return wp.launch_tiled(kernel, dim=[grid], inputs=inputs, device=d, block_dim=lanes, record_cmd=True)
        else:
            kernel, check_kernel = K.solve_colour, K.check_colour

            def grid_of(count):
                return count

            def solve(kernel, grid, inputs):
                return record(kernel, grid, inputs)
        self._sweep = []
        listed_count = self._listed_count if split else self._empty_ints
        particles = self._colour_list if split else self.colour_particles
        for c in range(self.colour_count):
            start, count = offsets[c], offsets[c + 1] - offsets[c]
            before, previous = (offsets[c - 1], offsets[c] - offsets[c - 1]) if c > 0 else (0, 0)
            read, write = buffers[c % 2], buffers[(c + 1) % 2]
            if split:  # the free particles a thread each (springs only; it copies the previous colour), then the list
                self._sweep.append(record(K.solve_free, max(count, previous), [
                    self.colour_particles, start, count, before, previous, read, self.q0, self.y, m.particle_mass,
                    m.particle_inv_mass, 1.0 / h, *springs, self._reference, self._bound, self._listed, write]))
                before, previous = 0, 0
            shared = [read, self.q0, self.y, m.particle_mass, m.particle_inv_mass, 1.0 / h, *springs,
                      *self._contact_inputs, self._reference, self._bound, self.particle_colour]
            grid = grid_of(max(count, previous))  # the stride too: block (thread) k takes particles k, k + grid, ...
            self._sweep.append(solve(kernel, grid, [
                particles, start, count, listed_count, c, grid, before, previous, *shared, *outputs, self.line_search,
                write]))
            if checked:  # the colour's steps checked at their ends (reading the buffer the solve read)
                grid = grid_of(count)
                self._sweep.append(solve(check_kernel, grid, [
                    particles, start, count, listed_count, c, grid, 0, 0, *shared, self._force, self._step,
                    self.line_search, write]))
        self._mark = None
        if split and self.contact is not None:
            cc = self.contact
            self._mark = record(K.list_contact_particles, n, [
                self.particle_colour, self._colour_starts, m.particle_inv_mass, self._reference, self._bound,
                cc._slot, cc._near_end, cc._planes, cc._spheres, cc.thickness, self._listed, self._colour_list,
                self._listed_count])
        last = self.colour_count - 1
        if last >= 0:
            self._sweep.append(record(K.commit_colour, offsets[last + 1] - offsets[last], [
                self.colour_particles, offsets[last], buffers[(last + 1) % 2], buffers[last % 2]]))
        self._accelerate = [(record(FK.chebyshev_step, n, [q, omega, self._older, self._old]),
                             record(K.clip_positions, n, [self._reference, self._bound, q]))
                            for omega in (self._omegas if self.chebyshev_rho > 0.0 else [])]
        self._finish = record(FK.finish_step, n, [q, self.q0, 1.0 / h, qd])
        self._recorded_key = self._key(q, qd, h)

    def _list_contact_particles(self) -> None:
        """After a search (run or skipped), when the sweeps are split (``split``): the particles that can touch a
        contact before the next one, by colour (``kernels.vbd.list_contact_particles``; the rest are solved by
        ``solve_free``)."""
        if self._mark is not None:
            self._listed_count.zero_()
            self._mark.launch()

    def _key(self, q, qd, h: float) -> tuple:
        """What the recorded launches depend on: the arrays, the step, ``lanes``, ``max_registers``, ``line_search``,
        ``split`` and the contact's coefficients (a changed ``lanes``, ``max_registers``, ``line_search``, ``split``,
        ``contact.friction``, ``stiffness`` or ``thickness`` is recorded again at the next step)."""
        c = self.contact
        coefficients = (c.thickness, c.stiffness, c.friction, c.friction_eps) if c is not None else ()
        return (q.ptr, qd.ptr, h, self.lanes, self.max_registers, self.line_search, self.split) + coefficients

    def forget_history(self) -> None:
        """The velocities before the current state say nothing of it (a state set from outside; ``Simulator``'s
        ``notify_changed("state")``): the next step's adaptive guess takes the external acceleration whole, as the
        first step does (``kernels.vbd.assume_external_acceleration``). Without it a body released at rest in the air
        started from a guess without gravity, and a 50 x 40 torus fell 32.6 mm instead of 35.8 mm in its first 20
        steps of 1/240 s, 10 % of its kinetic energy short: 12 sweeps do not carry a whole body's translation, and the
        shortfall fed the next steps' guesses."""
        self._fresh = True

    @property
    def stability_note(self) -> str:
        """What the stability report says of this VBD (``warpsim.core.stability.note_of``): unconditionally stable,
        unless Chebyshev acceleration is on."""
        if self.chebyshev_rho <= 0.0:
            return STABILITY_NOTES["vbd"]
        return (f"vertex block descent is unconditionally stable, accuracy set by iterations, but not with Chebyshev "
                f"acceleration (chebyshev_rho = {self.chebyshev_rho:g}): its extrapolation can add energy (a kicked "
                "torus of 1e5 N/m springs at 1/60 s, rho 0.99: 4,800x in its first step); chebyshev_rho=0, the default, "
                "turns it off")

    def energy_cause(self, h: float) -> str | None:
        """Chebyshev acceleration, when on: each extrapolation steps past the sweep's Newton steps, contact included,
        and no check holds it (``line_search`` checks the Newton steps only), so a step can gain energy; without it
        a step's sweeps lower G and dissipate (None)."""
        if self.chebyshev_rho <= 0.0:
            return None
        return (f"Cause: VBD's Chebyshev acceleration (chebyshev_rho = {self.chebyshev_rho:g}) extrapolates past each "
                "sweep's Newton steps, contacts included, unchecked, and can add energy (the donut heap gained 13 % "
                "at its first impacts at 0.9 with 12 iterations). Remedy: chebyshev_rho=0 (the donuts scene's "
                "vbd_chebyshev_rho), the default.")

    def step(self, system, q, qd, time, dt, f_out=None) -> None:
        self.prepare(system)
        h = float(dt)
        if getattr(self, "_recorded_key", None) != self._key(q, qd, h):
            self._record(q, qd, h)
        if f_out is not None:
            f_out.zero_()  # a straight path within the step (see ImplicitEuler.step)
        self.f_ext.zero_()
        for force in self._other_forces:
            force.eval(q, qd, time, 0.0, self.f_ext)
        if self._fresh:  # no step before this one to take the adaptive guess's acceleration from
            wp.launch(K.assume_external_acceleration, self.model.particle_count,
                      inputs=[qd, self.f_ext, self.model.particle_inv_mass, h, self.qd_prev], device=self.model.device)
            self._fresh = False
        if self.contact is not None:  # the first search (no bound holds before it) always runs, then as those within
            if self.renew_fraction is None or self.contact.searches == 0:  # the step (docstring); bind zeroes the count
                self.contact.search(q)
            else:
                self.contact.search(q, self.deficit, self.renew_fraction)
            self._list_contact_particles()
        self._predict.launch()
        self._pack.launch()  # the springs as the model holds them now, with q0, in the sweeps' order
        chebyshev = self.chebyshev_rho > 0.0
        if chebyshev:
            wp.copy(self._older, q)
            wp.copy(self._old, q)
        for k in range(self.iterations):
            if self.contact is not None and k > 0 and self.detect_every and k % self.detect_every == 0:
                if self.renew_fraction is None:
                    self.contact.search(q)
                else:  # skipped where every particle is well inside its bound with nothing of its guess cut
                    self.contact.search(q, self.deficit, self.renew_fraction)
                self._list_contact_particles()
                self._restore.launch()  # skipped or not: a deficit of zero and positions inside the bound stay
            for launch in self._sweep:  # one Gauss-Seidel sweep: colour by colour, q and q_new alternating
                launch.launch()
            if chebyshev:
                for launch in self._accelerate[k]:
                    launch.launch()
                wp.copy(self._old, q)  # the clipped iterate is the one the next extrapolation starts from
                wp.copy(self.q_new, q)  # the next sweep starts with both buffers equal
        wp.copy(self.qd_prev, qd)
        self._finish.launch()
