"""The contact topology and search of vertex block descent (``ws.VBD``): which pairs of primitives
may push on each particle, and how far each particle may move before the next search.

:class:`VBDContact` holds the surface (triangles, their edges and vertices) of copies of one body or
of a whole mesh, per-particle CSR rows of the triangles and edges touching each particle (built
once, fixed order), three BVHs (triangles, surface vertices, edges) and the per-query pair lists of
``warpsim.kernels.vbd_contact``. :meth:`VBDContact.search` refits the BVHs (a rebuild every
``rebuild_every`` searches), runs the three queries and turns their smallest distances into each
particle's displacement bound; it allocates nothing and reads nothing back (a CUDA graph can hold it).
"""

from __future__ import annotations

import copy
import math

import numpy as np
import warp as wp

from ..core import checks
from ..kernels import soft_contact as SK
from ..kernels import vbd_contact as K
from . import meshtools

QUERY_BLOCK_DIM = 64
"""Threads a CUDA block of ``query_pairs`` (``bench_donuts.py --query-block-dims``; H200, the heap of 12 /
100 tori after settling, one run: a search took 5.38 / 19.9 ms with Warp's default 256, 4.77 / 17.3 ms with
128, 4.91 / 16.7 ms with 64, 5.10 / 16.5 ms with 32; the same lists)."""


def guess_length(speed: float, g: float, h: float) -> float:
    """``ws.VBD``'s initial guess [m] for a particle falling at ``speed`` [m/s] under gravity ``g`` [m/s^2] in a step
    of ``h`` [s]: speed h + g h^2, rounded up to 0.1 mm. A guess longer than the particle's bound (at most
    ``max_displacement``) is cut, and the sweeps do not carry a body's translation on (its springs hold each vertex to
    its neighbours' cut positions): the fall is slowed, energy lost (a torus at 3 m/s, 1/240 s, bound 6 mm: 16 % slow
    after 20 steps; benchmarks/RESULTS.md)."""
    return math.ceil((speed * h + g * h * h) * 1.0e4) / 1.0e4


def steps_fitting_guess(speed: float, g: float, b_max: float, frame_dt: float, minimum: int = 1) -> int:
    """The fewest steps a frame of ``frame_dt`` [s] (at least ``minimum``) whose guesses (``guess_length``) fit
    ``b_max`` [m]: the root of speed h + g h^2 = b_max, then as many more as the rounding asks (at most 100; a
    ``b_max`` under 0.1 mm fits none)."""
    longest = 2.0 * b_max / (speed + math.sqrt(speed * speed + 4.0 * g * b_max))
    steps = max(int(minimum), math.ceil(frame_dt / longest))
    for _ in range(100):
        if guess_length(speed, g, frame_dt / steps) <= b_max:
            break
        steps += 1
    return steps


def cut_guess_line(subject: str, height: float, fall: float, g: float, frame_dt: float, steps: int, b_max: float,
                   bound: str, setting: str = "") -> str | None:
    """A scene's line before the first step when a fall from ``height`` [m] at ``fall`` [m/s] (gravity ``g``)
    takes a guess (``guess_length``) longer than ``b_max`` [m] at ``steps`` steps a frame of ``frame_dt`` [s]: the
    bound cuts it and slows the fall. ``subject``: what falls (e.g. "donuts: ... a torus"), ``bound``: where b_max
    comes from; the remedies are the steps a frame that fit the guess (``steps_fitting_guess``) and, with
    ``setting`` (an option's name), that option set to the guess. None when the guess fits."""
    h = frame_dt / steps
    guess = guess_length(fall, g, h)
    if guess <= b_max:
        return None
    more = steps_fitting_guess(fall, g, b_max, frame_dt, steps)
    remedy = f"take --substeps {more}" + (f" or set {setting}={guess:g}" if setting else "")
    return (f"{subject} falling from {height:.3g} m reaches {fall:.3g} m/s, an initial guess of {guess * 1e3:.3g} mm "
            f"a step of {h:.3g} s, longer than the {b_max * 1e3:.3g} mm a vertex may move before the next contact "
            f"search ({bound}): the bound cuts the guess and slows the fall (no energy is gained, it is lost); "
            f"{remedy}")


def _csr(rows: np.ndarray, values: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(offsets (n + 1,), values sorted by row then value): the fixed-order rows of a CSR."""
    order = np.lexsort((values, rows))
    offsets = np.searchsorted(rows[order], np.arange(n + 1))
    return offsets.astype(np.int32), values[order].astype(np.int32)


def _tiled_csr(offsets: np.ndarray, values: np.ndarray, copies: int, value_stride: int):
    """A template CSR (P rows) repeated for ``copies`` copies, each copy's values shifted by ``value_stride``."""
    P = len(offsets) - 1
    counts = np.tile(np.diff(offsets), copies)
    full = np.zeros(P * copies + 1, dtype=np.int64)
    np.cumsum(counts, out=full[1:])
    shift = np.repeat(np.arange(copies, dtype=np.int64) * value_stride, len(values))
    return full.astype(np.int32), (np.tile(values.astype(np.int64), copies) + shift).astype(np.int32)


class VBDContact:
    """Vertex-triangle and edge-edge contact inside ``ws.VBD`` (and plane contact).

    Args:
        faces: (F, 3) triangles in particle indices: of one body when ``body_size`` is given (copy k
            is that body shifted by k body_size particles), else of the whole model.
        body_size: particles of one copy (P), or None.
        particle_body: (N,) body of each particle when ``body_size`` is None (default: one body).
        thickness: contact radius r_c [m]: a pair closer than this pushes (energy k_c/2 (r_c - d)^2).
        stiffness: k_c [N/m].
        friction: Coulomb coefficient mu >= 0.
        friction_eps: displacement [m] below which friction acts as a stiff spring (VBD's eps_v h).
        self_contact: also pairs within one body (pairs sharing a particle are always skipped).
        bound_fraction: gamma in (0, 1/2): each search lets a particle move gamma x its distance to the
            nearest non-incident primitive (``warpsim.bodies.vbd`` proves no pair then closes).
        max_displacement: b_max [m], the most a particle moves between searches (default: the thickness).
        min_displacement: b_min [m] (default: a quarter of the thickness): stepped by ``ws.VBD``, each
            particle's cap C_p, the most it may move before the next search, is set at each search from its own
            motion (``kernels.vbd_contact.displacement_caps``: ``cap_safety`` = 4 times the length of its initial
            guess's step, plus what the bound cut from it) within [b_min, b_max], and a pair is searched
            within r_c + C_a + C_b: a heap at rest searches a small radius, a falling body a large one. Equal to
            b_max (or a search without ``ws.VBD``'s motion): every cap is b_max, the radius r_c + 2 b_max.
        capacity: pairs kept per query list, the nearest (more are counted in :attr:`overflow`).
        near_capacity: list entries kept per surface vertex after a search for the colour sweeps, those that can
            still push on it (``kernels.vbd_contact.keep_near_pairs``); a vertex with more gathers over the whole
            lists (the same sums: only the time differs).
        planes: (normal (3,), offset) pairs: half-spaces n . x >= offset (floor and walls).
        spheres: (centre (3,), radius) pairs: static spheres the surface stays outside of.
        rebuild_every: searches between BVH rebuilds (refits in between).
    """

    CHUNK = 8
    """Surface vertices per thread of the body-bounds pass."""

    @staticmethod
    def list_bytes(vertices: int, triangles: int, edges: int, capacity: int = 32, near_capacity: int = 128) -> int:
        """Device bytes of one copy of a surface of ``vertices``, ``triangles`` and ``edges`` (int32 and
        float32): each query's ``capacity`` indices and distances with its count and smallest distance,
        the sweeps' ``near_capacity`` entries and 3 ends per vertex, the topology (corners, ends, the CSR
        of each vertex's triangles and edges) and the bounding boxes. The per-particle arrays (slot, body,
        reference, bound) are not counted here."""
        queries = vertices + triangles + edges
        lists = 8 * capacity * queries + 8 * queries
        near = 4 * near_capacity * vertices + 12 * vertices
        topology = 4 * (6 * triangles + 4 * edges) + 4 * vertices
        boxes = 24 * (triangles + edges) + 12 * vertices
        return lists + near + topology + boxes

    def __init__(self, faces, *, body_size: int | None = None, particle_body=None, thickness: float = 0.006,
                 stiffness: float = 2000.0, friction: float = 0.5, friction_eps: float | None = None,
                 self_contact: bool = False, bound_fraction: float = 0.4, max_displacement: float | None = None,
                 min_displacement: float | None = None, capacity: int = 32, near_capacity: int = 128, planes=(),
                 spheres=(), rebuild_every: int = 20):
        faces = checks.index_array(faces, "VBDContact faces")  # a float index is refused, never truncated
        if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
            raise ValueError(f"VBDContact faces must have shape (F, 3) with F >= 1, got {faces.shape}; give the "
                             "surface triangles in particle indices")
        self.faces = faces.astype(np.int64)
        self.body_size = None if body_size is None else checks.integer(
            body_size, "VBDContact body_size", lo=1, hi=1 << 40, fix="the particles of one copy, or None")
        self.particle_body = None if particle_body is None else np.asarray(particle_body, dtype=np.int64)
        self.thickness = checks.positive(thickness, "VBDContact thickness", unit="m", fix="e.g. 0.006")
        self.stiffness = checks.nonnegative(stiffness, "VBDContact stiffness", unit="N/m", fix="e.g. 2000")
        self.friction = checks.nonnegative(friction, "VBDContact friction", fix="e.g. 0.5")
        self.friction_eps = 0.1 * self.thickness if friction_eps is None else checks.positive(
            friction_eps, "VBDContact friction_eps", unit="m", fix="e.g. 1e-4")
        self.self_contact = checks.flag(self_contact, "VBDContact self_contact")
        self.bound_fraction = checks.in_range(bound_fraction, "VBDContact bound_fraction", 1.0e-3, 0.499,
                                              fix="a fraction below 1/2, e.g. 0.4")
        self.max_displacement = self.thickness if max_displacement is None else checks.positive(
            max_displacement, "VBDContact max_displacement", unit="m", fix="e.g. the thickness")
        if min_displacement is None:
            self.min_displacement = min(0.25 * self.thickness, self.max_displacement)
        else:
            self.min_displacement = checks.positive(min_displacement, "VBDContact min_displacement", unit="m",
                                                    fix="e.g. a quarter of the thickness")
            if self.min_displacement > self.max_displacement:
                raise ValueError(f"VBDContact min_displacement = {self.min_displacement:g} m exceeds max_displacement "
                                 f"= {self.max_displacement:g} m; give at most that")
        self.cap_safety = 4.0
        """A cap is this many times the length of the particle's guessed step (|v| h + s |f / m| h^2, s the share of
        the external acceleration it took in its last step with VBD's adaptive guess: 0 resting on a support, so a
        resting heap's caps do not grow with g h^2 at larger steps; ``kernels.vbd_contact.displacement_caps``): a search
        within the step (renewing at half the bound) is then skipped for a particle moving as predicted, and one
        that speeds up has room to double its speed before it is clipped."""
        self._motion: tuple | None = None
        self._recorded_key: tuple | None = None
        self.capacity = checks.integer(capacity, "VBDContact capacity", lo=1, hi=4096, fix="e.g. 32")
        self.near_capacity = checks.integer(near_capacity, "VBDContact near_capacity", lo=1, hi=1 << 16,
                                            fix="e.g. 128")
        self.rebuild_every = checks.integer(rebuild_every, "VBDContact rebuild_every", lo=1, hi=1 << 30,
                                            fix="e.g. 20")
        self.query_block_dim = QUERY_BLOCK_DIM
        """Threads a CUDA block of the pair queries (a launch setting: the same lists whatever it is)."""
        rows = []
        for k, plane in enumerate(planes):
            try:
                normal, offset = plane
                normal = np.asarray(checks.vec3(normal, f"VBDContact planes[{k}] normal"), dtype=np.float64)
            except (TypeError, ValueError) as exc:
                raise ValueError(f"VBDContact planes[{k}] is {plane!r}; give (normal (3,), offset [m]): {exc}") from None
            length = float(np.linalg.norm(normal))
            if not length > 0.0:
                raise ValueError(f"VBDContact planes[{k}] has a zero normal; give e.g. ((0, 1, 0), 0.0)")
            rows.append([*(normal / length), float(offset) / length])
        self.planes = np.asarray(rows, dtype=np.float64).reshape(-1, 4)
        balls = []
        for k, sphere in enumerate(spheres):
            try:
                centre, radius = sphere
                centre = checks.vec3(centre, f"VBDContact spheres[{k}] centre")
                radius = checks.positive(radius, f"VBDContact spheres[{k}] radius", unit="m", fix="e.g. 0.3")
            except (TypeError, ValueError) as exc:
                raise ValueError(f"VBDContact spheres[{k}] is {sphere!r}; give (centre (3,), radius [m] > 0): "
                                 f"{exc}") from None
            balls.append([*centre, radius])
        self.spheres = np.asarray(balls, dtype=np.float64).reshape(-1, 4)
        self.searches = 0
        self.world_particle_count: int | None = None
        """Particles of one world in a batch of worlds laid end to end (``tile``), or None: one world."""

    def tile(self, world_count: int, world_particle_count: int) -> VBDContact:
        """The same contact for ``world_count`` copies of the model laid end to end (world w owns
        particles w P .. (w + 1) P - 1, P = ``world_particle_count``): bodies meet only bodies of their
        own world (``warpsim.worlds.batch``). Unbound; ``body_size`` must be given."""
        if self.body_size is None or int(world_particle_count) % self.body_size:
            raise ValueError(f"VBDContact.tile: worlds of {world_particle_count} particles need body_size set to the "
                             "particles of one copy that divides them; build the contact with body_size")
        tiled = copy.copy(self)
        tiled.world_particle_count = int(world_particle_count)
        return tiled

    @property
    def query_radius(self) -> float:
        """r_c + 2 b_max [m], the largest radius a pair is searched within (that of two particles at the largest
        cap, and of every pair when the caps are not set from motion): a pair farther apart at a search can
        close by at most its two caps before the next, so it stays beyond r_c (no force missed) and apart (no
        crossing)."""
        return self.thickness + 2.0 * self.max_displacement

    def set_motion(self, qd, qd_prev, f_ext, inv_mass, deficit, h: float, adaptive: bool = True) -> None:
        """Let each search set the caps from the particles' motion (``ws.VBD``, at its recording): velocities
        ``qd`` (N,) [m/s] at the step's start and ``qd_prev`` (N,) at the one before, forces other than the
        springs ``f_ext`` (N,) [N], inverse masses (N,) [1/kg], what the bound cut from each initial guess
        ``deficit`` (N,) [m], step ``h`` [s], and whether the guess takes only the share of the external
        acceleration the particle took in its last step (``adaptive``, VBD's adaptive guess: a particle resting on
        a support then gets no g h^2 in its cap). Arrays are read at each search (no copy)."""
        self._motion = (qd, qd_prev, f_ext, inv_mass, deficit, float(h), int(bool(adaptive)))
        self._recorded_key = None

    def bind(self, model) -> None:
        """Build the surface, CSR rows, BVHs and lists for ``model`` (host work once; allocates)."""
        n, d = model.particle_count, model.device
        self.device = d
        self._motion = None  # until ws.VBD records its step for this model (set_motion)
        if self.body_size is not None:
            P = self.body_size
            if n % P:
                raise ValueError(f"VBDContact body_size = {P} does not divide the model's {n} particles; give the "
                                 "particles of one copy")
            copies = n // P
            body = np.repeat(np.arange(copies), P)
        else:
            P, copies = n, 1
            body = np.zeros(n, dtype=np.int64) if self.particle_body is None else self.particle_body
            if body.shape != (n,):
                raise ValueError(f"VBDContact particle_body has shape {body.shape}; give one body per particle ({n},)")
        if self.faces.min() < 0 or self.faces.max() >= P:
            raise ValueError(f"VBDContact faces index particle {int(self.faces.max())} outside 0..{P - 1}; give "
                             "triangles of " + ("one copy" if self.body_size else "the model"))
        F = len(self.faces)
        edges, _, _ = meshtools.edge_topology(self.faces)
        E = len(edges)
        surface = np.unique(self.faces)
        V = len(surface)
        tri_off, tri_val = _csr(self.faces.reshape(-1), np.repeat(np.arange(F), 3), P)
        edge_off, edge_val = _csr(edges.reshape(-1), np.repeat(np.arange(E), 2), P)
        slot = np.full(P, -1, dtype=np.int64)
        slot[surface] = np.arange(V)
        shift = np.arange(copies, dtype=np.int64)
        tiled = {
            "tri": (self.faces[None] + (shift * P)[:, None, None]).reshape(-1),
            "edges": (edges[None] + (shift * P)[:, None, None]).reshape(-1),
            "surface": (surface[None] + (shift * P)[:, None]).reshape(-1),
            "slot": np.where(np.tile(slot, copies) >= 0, np.tile(slot, copies) + np.repeat(shift * V, P), -1),
        }
        tri_off, tri_val = _tiled_csr(tri_off, tri_val, copies, F)
        edge_off, edge_val = _tiled_csr(edge_off, edge_val, copies, E)

        def ints(a):
            return wp.array(np.ascontiguousarray(a).astype(np.int32), dtype=int, device=d)

        self._tri, self._edges, self._surface, self._slot = (ints(tiled[k]) for k in ("tri", "edges", "surface", "slot"))
        self._body = ints(body)
        self._tri_offsets, self._tris = ints(tri_off), ints(tri_val)
        self._edge_offsets, self._edge_list = ints(edge_off), ints(edge_val)
        self.triangle_count, self.edge_count, self.vertex_count = F * copies, E * copies, V * copies
        C = self.capacity
        self._vt = wp.zeros(self.vertex_count * C, dtype=int, device=d)
        self._vt_count = wp.zeros(self.vertex_count, dtype=int, device=d)
        self._vt_min = wp.zeros(self.vertex_count, dtype=float, device=d)
        self._tv = wp.zeros(self.triangle_count * C, dtype=int, device=d)
        self._tv_count = wp.zeros(self.triangle_count, dtype=int, device=d)
        self._tv_min = wp.zeros(self.triangle_count, dtype=float, device=d)
        self._ee = wp.zeros(self.edge_count * C, dtype=int, device=d)
        self._ee_count = wp.zeros(self.edge_count, dtype=int, device=d)
        self._ee_min = wp.zeros(self.edge_count, dtype=float, device=d)
        self._distances = [wp.zeros(self.vertex_count * C, dtype=float, device=d),
                           wp.zeros(self.triangle_count * C, dtype=float, device=d),
                           wp.zeros(self.edge_count * C, dtype=float, device=d)]  # the lists' distances [m]
        self._overflow = wp.zeros(6, dtype=int, device=d)  # queries past capacity, most pairs of one query
        self._searched = wp.zeros(1, dtype=int, device=d)  # searches run (skipped ones not counted)
        self._near = wp.zeros(self.vertex_count * self.near_capacity, dtype=int, device=d)
        self._near_end = wp.zeros(3 * self.vertex_count, dtype=int, device=d)
        self._planes = wp.array(self.planes.astype(np.float32), dtype=wp.vec4, device=d)
        self._spheres = wp.array(self.spheres.astype(np.float32), dtype=wp.vec4, device=d)
        self.reference = wp.zeros(n, dtype=wp.vec3, device=d)
        """Positions [m] at the last search, shape (N,)."""
        self.bound = wp.zeros(n, dtype=float, device=d)
        """Each particle's displacement bound [m] from ``reference`` until the next search, shape (N,)."""
        self.cap = wp.full(n, self.max_displacement, dtype=float, device=d)
        """Each particle's cap [m] at the last search: its bound is at most this (``set_motion``), shape (N,)."""
        # two levels (``kernels.soft_contact``): a BVH over the bodies' bounds (from chunks of at most
        # CHUNK surface vertices of one body), then BVHs grouped by body
        B = int(body.max()) + 1
        per_world = B if self.world_particle_count is None else self.world_particle_count // P
        body_world = np.arange(B) // per_world
        W = int(body_world.max()) + 1
        surface_body = body[tiled["surface"]]
        starts = np.flatnonzero(np.diff(surface_body, prepend=-1) != 0)
        run = np.arange(len(surface_body)) - np.repeat(starts, np.diff(np.append(starts, len(surface_body))))
        chunk = np.flatnonzero(run % self.CHUNK == 0)
        self._chunk_start = ints(np.append(chunk, len(surface_body)))
        self._chunk_body = ints(surface_body[chunk])
        self.body_count = B
        self._groups = [ints(body[tiled["tri"][0::3]]), ints(surface_body), ints(body[tiled["edges"][0::2]]),
                        ints(body_world)]  # kept: a BVH holds its groups by pointer
        self._body_lower = wp.zeros(B, dtype=wp.vec3, device=d)
        self._body_upper = wp.zeros(B, dtype=wp.vec3, device=d)
        self._roots = [wp.zeros(B, dtype=int, device=d) for _ in range(3)] + [wp.zeros(W, dtype=int, device=d)]
        self._go = wp.ones(W, dtype=int, device=d)  # per world; 0: this search skipped there (search(deficit=))
        q = model.particle_q
        self._tri_lower = wp.zeros(self.triangle_count, dtype=wp.vec3, device=d)
        self._tri_upper = wp.zeros(self.triangle_count, dtype=wp.vec3, device=d)
        self._point_lower = wp.zeros(self.vertex_count, dtype=wp.vec3, device=d)
        self._point_upper = wp.zeros(self.vertex_count, dtype=wp.vec3, device=d)
        self._body_cap = wp.zeros(B, dtype=float, device=d)
        self._edge_lower = wp.zeros(self.edge_count, dtype=wp.vec3, device=d)
        self._edge_upper = wp.zeros(self.edge_count, dtype=wp.vec3, device=d)
        self._recorded_key = None
        self._record_bounds(q)
        for launch in self._bounds:
            launch.launch()
        self._constructor = "lbvh" if d.is_cuda else "sah"
        boxes = [(self._tri_lower, self._tri_upper), (self._point_lower, self._point_upper),
                 (self._edge_lower, self._edge_upper),
                 (self._body_lower, self._body_upper)]
        self._bvhs = [wp.Bvh(lo, hi, constructor=self._constructor, groups=g) for (lo, hi), g in zip(boxes, self._groups)]
        self._find_roots = [wp.launch(SK.group_roots, len(root), inputs=[bvh.id, root], device=d, record_cmd=True)
                            for bvh, root in zip(self._bvhs, self._roots)]
        for launch in self._find_roots:
            launch.launch()
        self.searches = 0

    def _record_bounds(self, q) -> None:
        """Record the launches that write the BVHs' boxes at positions ``q``."""
        def record(kernel, dim, inputs):
            return wp.launch(kernel, dim, inputs=inputs, device=self.device, record_cmd=True)

        self._bounds = [
            record(K.capped_boxes, max(self.triangle_count, self.vertex_count, self.edge_count), [
                self._surface, self._tri, self._edges, q, self.cap, self._tri_lower, self._tri_upper,
                self._point_lower, self._point_upper, self._edge_lower, self._edge_upper]),
            record(SK.reset_bounds, self.body_count, [self._body_lower, self._body_upper]),
            record(SK.body_bounds, self._chunk_body.shape[0], [self._chunk_start, self._chunk_body, self._surface, q, q,
                                                               self._body_lower, self._body_upper]),
            record(K.body_caps, self.vertex_count, [self._surface, self._body, self.cap, self._body_cap]),
            record(K.grow_bodies, self.body_count, [self._body_cap, self._body_lower, self._body_upper])]

    def _record(self, q) -> None:
        """Record the search's launches for positions ``q`` (replayed: no argument packing)."""
        d, C, sc = self.device, self.capacity, int(self.self_contact)

        def record(kernel, dim, inputs, block_dim=256):
            return wp.launch(kernel, dim, inputs=inputs, device=d, record_cmd=True, block_dim=block_dim)

        self._record_bounds(q)
        tri_bvh, point_bvh, edge_bvh, body_bvh = self._bvhs
        tri_roots, point_roots, edge_roots, world_roots = self._roots
        lists = [(self._vt, self._distances[0], self._vt_count, self._vt_min),
                 (self._tv, self._distances[1], self._tv_count, self._tv_min),
                 (self._ee, self._distances[2], self._ee_count, self._ee_min)]
        kinds = [(K.VERTEX_QUERY, K.WHOLE, self.vertex_count, tri_bvh, tri_roots, lists[0], lists[1]),
                 (K.TRIANGLE_QUERY, K.FINISH, self.triangle_count, point_bvh, point_roots, lists[1], None),
                 (K.EDGE_QUERY, K.HALF, self.edge_count, edge_bvh, edge_roots, lists[2], lists[2]),
                 (K.EDGE_QUERY, K.FINISH, self.edge_count, edge_bvh, edge_roots, lists[2], None)]
        self._queries = [
            record(K.begin_search, max(self.triangle_count, self.edge_count), [
                self._go, self._tri, self._edges, self._body, self._groups[3], self._tv_count, self._ee_count,
                self._overflow, self._searched])] + [
            record(K.query_pairs, count, [self._go, int(kind), int(mode), body_bvh.id, world_roots, self._groups[3],
                                          bvh.id, roots, self._surface, self._tri, self._edges, self._body, q,
                                          self.thickness, self.cap, sc, C,
                                          *out, self._overflow, int(mirror is not None), *(mirror or out)[:3]],
                   self.query_block_dim)
            for kind, mode, count, bvh, roots, out, mirror in kinds] + [
            record(K.displacement_bounds, q.shape[0], [
                self._go, self._body, self._groups[3], q, self._slot, self._vt_min, self._tri_offsets, self._tris,
                self._tv_min,
                self._edge_offsets, self._edge_list, self._ee_min, self._planes, self._spheres,
                self.bound_fraction, self.cap,
                self.reference, self.bound]),
            record(K.keep_near_pairs, self.vertex_count, [
                self._go, self._body, self._groups[3], self._surface, self._tri, self._edges, C, self._vt,
                self._distances[0], self._vt_count,
                self._tri_offsets, self._tris, self._tv, self._distances[1], self._tv_count, self._edge_offsets,
                self._edge_list, self._ee, self._distances[2], self._ee_count, self.reference, self.bound,
                self.thickness, self.near_capacity, self._near, self._near_end])]
        self._caps = None
        if self._motion is not None:
            qd, qd_prev, f_ext, inv_mass, deficit, h, adaptive = self._motion
            self._caps = record(K.displacement_caps, q.shape[0], [
                self._go, self._body, self._groups[3], qd, qd_prev, f_ext, inv_mass, deficit, h, adaptive,
                self.cap_safety,
                self.min_displacement, self.max_displacement, self.cap])
        else:
            self.cap.fill_(self.max_displacement)
        self._recorded_key = self._key(q)

    def _key(self, q) -> tuple:
        """What the recorded search depends on (a changed setting is recorded again at the next search)."""
        return (q.ptr, self.thickness, self.max_displacement, self.min_displacement, self.cap_safety,
                self.bound_fraction, self.self_contact, self.stiffness)

    def search(self, q, deficit=None, fraction: float = 0.5) -> None:
        """Pairs within their radius (the thickness and the two sides' caps, set first: ``set_motion``) at positions
        ``q`` (N,) [m], and each particle's bound and
        reference (no allocation, no read-back). With ``deficit`` (N,) [m] (what the bound cut from each
        particle's initial guess, ``ws.VBD``), only when some particle has moved more than ``fraction`` of its
        bound since the last search or has some of its guess cut (``kernels.vbd_contact.search_needed``,
        decided on the device, world by world in a batch of worlds); else the last search's lists and bounds
        stay (they hold until the next)."""
        if self._recorded_key != self._key(q):
            self._record(q)
        if deficit is None:
            self._go.fill_(1)
        else:
            self._go.zero_()
            wp.launch(K.search_needed, q.shape[0], inputs=[q, self.reference, self.bound, deficit, float(fraction),
                                                           self._body, self._groups[3], self._go], device=self.device)
        if self._caps is not None:  # the caps of the worlds that search, from their particles' motion
            self._caps.launch()
        for launch in self._bounds:
            launch.launch()
        rebuild = self.searches % self.rebuild_every == 0
        for bvh in self._bvhs:
            bvh.rebuild(self._constructor) if rebuild else bvh.refit()
        if rebuild:
            for launch in self._find_roots:
                launch.launch()
        self.searches += 1
        for launch in self._queries:  # begin_search zeroes the counts the vertex and edge queries stage into
            launch.launch()

    def solve_inputs(self) -> list:
        """The contact arguments of ``kernels.vbd.solve_colour`` (slot .. friction_eps)."""
        return [self._slot, self._tri, self._edges, self.capacity, self._vt, self._vt_count, self._tri_offsets,
                self._tris, self._tv, self._tv_count, self._edge_offsets, self._edge_list, self._ee, self._ee_count,
                self._near, self._near_end, self.near_capacity, *self._distances, self._planes, self._spheres,
                self.thickness, self.stiffness, self.friction, self.friction_eps]

    @property
    def searches_run(self) -> int:
        """Searches run so far (in a batch of worlds: the worlds' searches summed), those skipped
        (``search(..., deficit=)``) not counted (reads back)."""
        return int(self._searched.numpy()[0])

    @property
    def overflow(self) -> tuple:
        """(vertex, triangle, edge) queries with more pairs within the query radius than ``capacity`` at the
        last search (reads back; each kept its nearest ``capacity``). Per search, never accumulated: a figure
        at most the number of queries, which cannot wrap."""
        return tuple(int(x) for x in self._overflow.numpy()[:3])

    @property
    def most_pairs(self) -> tuple:
        """(vertex, triangle, edge): the most pairs within the query radius one query of that kind met at the
        last search, where it was more than ``capacity`` (else 0; reads back): the capacity that would have
        kept them all."""
        return tuple(int(x) for x in self._overflow.numpy()[3:])

    @property
    def surface_particles(self) -> np.ndarray:
        """The particles that are surface vertices (contact queries), in query order, shape (V,) (reads back)."""
        return self._surface.numpy()

    @property
    def nearest_triangles(self) -> np.ndarray:
        """Each surface vertex's distance [m] to its nearest listed triangle at the last search, 1e30 where it
        listed none, shape (V,) in ``surface_particles`` order (reads back)."""
        return self._vt_min.numpy()

    def active_pairs(self) -> np.ndarray:
        """Each particle's listed pairs that were within the thickness at the last search, by its part in them, shape
        (N, 3) int: [as the vertex of a vertex-triangle pair, as a corner of the triangle of one, as an end of an edge
        of an edge-edge pair] (each pair counted from each side it was listed from; reads back). What a particle that
        keeps moving is pressed by (``benchmarks/vbd_jitter.py --contacts``)."""
        C, r = self.capacity, self.thickness
        slot = self._slot.numpy()
        out = np.zeros((len(slot), 3), dtype=np.int64)

        def within(count, distance) -> np.ndarray:  # per list: its entries nearer than the thickness
            d = distance.numpy().reshape(-1, C)
            kept = np.arange(C)[None, :] < np.minimum(count.numpy(), C)[:, None]
            return ((d < r) & kept).sum(axis=1)

        surface = slot >= 0
        out[surface, 0] = within(self._vt_count, self._distances[0])[slot[surface]]
        sides = ((self._tri, self._tv_count, self._distances[1], 3),
                 (self._edges, self._ee_count, self._distances[2], 2))
        for column, (items, count, distance, corners) in enumerate(sides, start=1):
            per_item = within(count, distance)
            ends = items.numpy().reshape(-1, corners)
            for c in range(corners):
                np.add.at(out[:, column], ends[:, c], per_item)
        return out

    def near_stats(self) -> tuple:
        """(list entries the sweeps gather over, vertices past ``near_capacity`` that gather over the whole
        lists) at the last search (reads back)."""
        end = self._near_end.numpy().reshape(-1, 3)
        return int(end[:, 2].sum()), int((end[:, 0] < 0).sum())

    def pair_counts(self) -> tuple:
        """(vertex-triangle, edge-edge) pairs listed at the last search (reads back; each pair
        appears from both sides)."""
        return int(self._vt_count.numpy().sum()), int(self._ee_count.numpy().sum()) // 2
