"""Soft body against soft body: vertices against triangles and edges against edges of other bodies.

:class:`SoftContact` is a collider (it runs after integration, so it works with every
integrator, semi-implicit and implicit Euler included). The search has two levels: a small BVH
over the bodies' bounds (grouped by world in a batch), then one grouped ``wp.Bvh`` over the
contact triangles of all bodies and one over their surface edges (group = body), whose subtrees
are queried only for the *other* bodies a vertex's or edge's box meets (its own body too with
``self_contact``). Every surface vertex keeps the nearest triangle closer than ``thickness`` [m],
every surface edge the nearest edge. Measured on the H100 (``bench_donuts.py --profile``): the
former single-level search visited 80 triangles per vertex query and 31 edges per edge query,
85-93 % of them the query's own body's; the two-level search visits 11-12 and 2.2-2.5.
Bodies can be copies of one topology (:meth:`SoftContact.copies`: the 1,000-torus heap).
Each pair is pushed apart and given an inelastic impulse with restitution and
Coulomb friction, equal and opposite (weighted by barycentrics or edge parameters): momentum is
conserved. The step is deterministic (fixed-point integer sums), allocates nothing and makes no
host read-back, so it records in a CUDA graph. Kernels: ``warpsim.kernels.soft_contact`` (the
method is described there).

Example::

    a = ws.add_soft_body(builder, *torus, position=(0, 0.3, 0))
    b = ws.add_soft_body(builder, *torus, position=(0, 0.45, 0))
    contact = ws.SoftContact([a, b], thickness=0.01, friction=0.5)
    sim = ws.Simulator(builder.finalize(), colliders=[ws.Plane(), contact])
"""

from __future__ import annotations

import copy
import math

import numpy as np
import warp as wp

from ..core import checks
from ..core.collider import Collider
from ..kernels import soft_contact as K
from ..kernels import soft_contact_list as L
from . import meshtools
from .soft_contact_force import SoftContactForce


def _body_faces(body, k: int) -> np.ndarray:
    faces = getattr(body, "faces", body)
    try:
        faces = np.asarray(faces)
        if faces.dtype.kind == "f":  # a float index is refused, never truncated
            faces = checks.index_array(faces, f"SoftContact bodies[{k}] triangles")
        faces = np.asarray(faces, dtype=np.int64)
    except (TypeError, ValueError) as exc:
        if "non-integer" in str(exc):
            raise
        raise ValueError(f"SoftContact bodies[{k}] is {type(body).__name__}; give a SoftBody (ws.add_soft_body) "
                         "or an (F, 3) array of triangles in particle indices") from None
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
        raise ValueError(f"SoftContact bodies[{k}]: triangles must have shape (F, 3) with F >= 1, got {faces.shape}")
    return faces


class SoftContact(Collider):
    """Vertex-triangle and edge-edge contact between soft bodies (see module docstring).

    Args:
        bodies: SoftBody objects (``ws.add_soft_body``) or (F, 3) triangle arrays in particle
            indices; each is one body. Their surface vertices are the contact vertices.
        thickness: contact distance [m]: a vertex is kept at least this far in front of every
            other body's triangles, an edge this far from every other body's edges.
        restitution: normal restitution e in [0, 1] (0: the approach stops).
        friction: Coulomb friction coefficient mu >= 0.
        self_contact: also test a body's vertices against its own triangles (except triangles
            within ``self_rest_distance`` [m] of the vertex in the rest pose; default 2 x thickness).
        iterations: passes per step, each a position push and an impulse per contact (Jacobi;
            more resolve a crowded contact better).
        search: how far behind a triangle [m] a vertex still counts as penetrating and is pushed
            back out (default 3 x thickness).
        push: fraction of a contact's depth removed by moving positions each pass (default 0.5;
            1 removes it at once but makes resting contacts jitter: measured on a 4-torus heap,
            kinetic energy at rest 0.02-0.05 J with 1, 0.002 J with 0.5, of a 13 J peak).
        edge_contact: also keep surface edges apart (edge-edge contact; without it long edges
            can cross where no vertex is near).
        broad_phase: "bvh" (two levels: the bodies' bounds, then the other bodies' subtrees of
            grouped BVHs over all triangles and edges, every step), "list" (that search only when
            needed, into a candidate list evaluated every step: ``pad``, ``search_every``,
            ``capacity``; ``warpsim.kernels.soft_contact_list``) or "all_pairs" (every vertex
            against every triangle of its world: the O(n^2) reference). All three find the same
            contacts.
        pad: "list" only: how far [m] a contact vertex may move before the device searches again
            (default: half the thickness); candidates are kept within max(thickness, search) + 2 pad
            of a vertex, thickness + 2 pad of an edge (kernel docstring).
        search_every: "list" only: steps between the host's BVH refits, each followed by a search
            (between them the device searches when a vertex moved more than ``pad``; default
            ``SEARCH_EVERY``).
        reach: speculative contact distance [m] beyond the thickness (default 0): pairs closer than
            thickness + reach are kept as contacts, so a penalty in an implicit solve
            (:meth:`implicit_force`) sees pairs that close during a large step before they touch;
            after the step such a pair may still approach by its gap beyond the thickness in one
            step, only faster approach is removed. Give at least the relative distance two bodies
            travel in one step (the donuts scene: 2 x thickness at 1/240 s).
        edge_reach: the same for edge-edge pairs [m] (None: ``reach``). Edges that pass through each
            other during a step are found after it anyway (the crossing test), so speculative edge
            pairs matter less, and each edge's query box grows by twice this. The donuts scene gives
            0: its heaps held as well or better, with fewer candidates (``benchmarks/RESULTS.md``).
        capacity: "list" only: candidates kept per vertex or edge query; a query with more counts
            an overflow (``candidate_overflow``) and may miss contacts.
        rebuild_every: rebuild the BVHs every this many steps and refit them in between (0: refit
            only; None: ``REBUILD_EVERY_CUDA`` / ``REBUILD_EVERY_CPU``; ``rebuild_period`` changes
            it later). A refit keeps the tree of the last rebuild, whose boxes swell as bodies
            travel: in a falling heap of 12 tori (CPU, 24 x 12 vertices) refits alone visited 3.2x
            the vertex candidates after 10 steps, 7.5x after 20, 16x after 80 (``candidate_stats``).
            Results do not depend on it (nearest contacts, ties to the lower index).

    After a step, ``contact_count`` and ``edge_contact_count`` (one read-back each) are the
    numbers of vertex-triangle and edge-edge contacts found.
    """

    CHUNK = 8
    """Contact vertices per thread of the body-bounds pass."""
    REBUILD_EVERY_CUDA = 10
    """Default BVH rebuild period on CUDA (steps; refits in between). Measured on the H100
    (``bench_donuts.py --rebuild-every``): a step of a settled heap of 12 tori x 2,000 vertices
    1.106 ms rebuilding every 10 steps against 1.596 ms every step, 100 tori 2.744 against 3.590 ms."""
    REBUILD_EVERY_CPU = 20
    """Default BVH rebuild period on the CPU, where a SAH rebuild costs about 1.2 us per item."""
    SEARCH_EVERY = 20
    """Default refit-and-search period of ``broad_phase="list"`` (steps)."""
    LIST_THREADS = 1 << 20
    """Most threads of the passes over listed contacts and particles (each takes every
    LIST_THREADS-th one; fewer when there are fewer slots or particles). Results do not depend on
    it (each item is taken by one thread; fixed-point sums). 65,536 left the landed heap of 1,000
    tori (2 M touched particles) at 0.78 ms a particle pass on the H100, 50 ms of a 162 ms step."""
    DEFAULT_CAPACITY = 256
    """Default candidates kept per query of ``broad_phase="list"`` (64 overflowed on a settled heap of
    tori of 2,000 vertices: 9.7 candidates a vertex query on average, many at 64)."""

    def __init__(self, bodies, *, thickness: float = 0.005, restitution: float = 0.0, friction: float = 0.5,
                 self_contact: bool = False, iterations: int = 4, search: float | None = None,
                 self_rest_distance: float | None = None, push: float = 0.5, edge_contact: bool = True,
                 broad_phase: str = "bvh", rebuild_every: int | None = None, pad: float | None = None,
                 search_every: int | None = None, capacity: int | None = None, reach: float = 0.0,
                 edge_reach: float | None = None):
        bodies = list(bodies) if not isinstance(bodies, np.ndarray) else [bodies]
        if not bodies:
            raise ValueError("SoftContact needs at least one body (a SoftBody or an (F, 3) triangle array)")
        # bodies as topologies and particle offsets: body b has triangles topologies[body_topology[b]]
        # + body_offset[b] (``copies`` shares one topology among many bodies: no per-body arrays)
        self._topologies = [_body_faces(b, k) for k, b in enumerate(bodies)]
        self._body_topology = np.arange(len(bodies), dtype=np.int64)
        self._body_offset = np.zeros(len(bodies), dtype=np.int64)
        from ..core import checks

        thickness = checks.positive(thickness, "SoftContact thickness", unit="m", fix="e.g. 0.005")
        friction = checks.nonnegative(friction, "SoftContact friction", fix="e.g. 0.5")
        restitution = checks.in_range(restitution, "SoftContact restitution", 0.0, 1.0, fix="e.g. 0.0")
        iterations = checks.integer(iterations, "SoftContact iterations", lo=1, hi=1000, fix="e.g. 4")
        for name, value in (("search", search), ("self_rest_distance", self_rest_distance)):
            if value is not None:
                checks.nonnegative(value, f"SoftContact {name}", unit="m", fix="or None for the default")
        push = checks.in_range(push, "SoftContact push", 0.0, 1.0, fix="a fraction of the depth removed per step")
        self.thickness = float(thickness)
        self.reach = float(checks.nonnegative(reach, "SoftContact reach", unit="m",
                                              fix="e.g. 2 x the thickness for steps of 1/240 s, or 0"))
        self.edge_reach = self.reach if edge_reach is None else float(checks.nonnegative(
            edge_reach, "SoftContact edge_reach", unit="m", fix="e.g. 0, or None for the reach"))
        self.friction = float(friction)
        self.restitution = restitution
        self.self_contact = checks.flag(self_contact, "SoftContact self_contact")
        self.iterations = int(iterations)
        self.search = 3.0 * self.thickness if search is None else float(search)
        self.self_rest_distance = 2.0 * self.thickness if self_rest_distance is None else float(self_rest_distance)
        for name in ("search", "self_rest_distance"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"SoftContact {name} is {value}; it must be finite and >= 0 [m]")
        if len(self._body_offset) < 2 and not self.self_contact:
            raise ValueError("SoftContact with one body does nothing unless self_contact=True; give two bodies or more")
        self.push = float(push)
        if not (math.isfinite(self.push) and 0.0 <= self.push <= 1.0):
            raise ValueError(f"SoftContact push is {push}; it must be in [0, 1] (fraction of the depth removed per step)")
        if broad_phase not in ("bvh", "list", "all_pairs"):
            raise ValueError(f"SoftContact broad_phase is {broad_phase!r}; use 'bvh', 'list' or 'all_pairs'")
        self.pad = 0.5 * self.thickness if pad is None else float(checks.positive(pad, "SoftContact pad", unit="m",
                                                                            fix="e.g. the thickness"))
        self.search_every = self.SEARCH_EVERY if search_every is None else checks.integer(
            search_every, "SoftContact search_every", lo=1, hi=1_000_000, fix="e.g. 20 (steps between refits)")
        self.capacity = checks.integer(self.DEFAULT_CAPACITY if capacity is None else capacity, "SoftContact capacity",
                                       lo=1, hi=4096, fix="e.g. 256")
        self.broad_phase = broad_phase
        if rebuild_every is not None and (isinstance(rebuild_every, bool) or not isinstance(rebuild_every, int)
                                          or rebuild_every < 0):
            raise ValueError(f"SoftContact rebuild_every is {rebuild_every!r}; give an integer >= 0 (steps between BVH "
                             "rebuilds; 0: refit only)")
        self.rebuild_every = rebuild_every
        self._rebuild = rebuild_every
        self.edge_contact = checks.flag(edge_contact, "SoftContact edge_contact")
        self.body_world: np.ndarray | None = None  # (faces,) world of each body's faces, batches only

    @classmethod
    def copies(cls, faces, offsets, **options) -> SoftContact:
        """Contact among copies of one body: body b has the triangles ``faces`` (F, 3) (particle
        indices of the first copy) + ``offsets[b]`` (B,); the topology is stored once, so a heap
        of 1,000 bodies builds in seconds. ``options`` as for the constructor."""
        offsets = np.asarray(offsets)
        if offsets.ndim != 1 or len(offsets) == 0 or offsets.dtype.kind not in "iu":
            raise ValueError(f"SoftContact.copies offsets must be a non-empty 1-D integer array, got shape "
                             f"{offsets.shape} of {offsets.dtype}")
        contact = cls([faces, faces], **options) if len(offsets) > 1 else cls([faces], **options)
        contact._topologies = contact._topologies[:1]
        contact._body_topology = np.zeros(len(offsets), dtype=np.int64)
        contact._body_offset = offsets.astype(np.int64)
        return contact

    @property
    def faces(self) -> list:
        """The triangles (F, 3) of each body in particle indices (made on demand)."""
        return [self._topologies[t] + o for t, o in zip(self._body_topology, self._body_offset)]

    def slot_count(self) -> int:
        """Contact slots: one per contact vertex and, with edge contact, one per surface edge (from
        the topologies; no binding needed)."""
        per_topology = np.array([len(np.unique(f)) + (len(meshtools.edge_topology(f)[0]) if self.edge_contact else 0)
                                 for f in self._topologies], dtype=np.int64)
        return int(per_topology[self._body_topology].sum())

    @property
    def body_count(self) -> int:
        return len(self._body_offset)

    def step_distances(self, model, positions) -> np.ndarray | None:
        """Per particle, the most it may move in one step [m] (``warpsim.core.stability``): the contact
        thickness plus the speculative ``reach``, so that no vertex crosses it, and the surfaces it
        keeps apart, within one step."""
        return np.full(model.particle_count, self.thickness + self.reach)

    def tile(self, world_count: int, world_particle_count: int) -> SoftContact:
        """The same contact for ``world_count`` copies of the model laid end to end (world w owns
        particles ``w P .. (w + 1) P - 1``, P = ``world_particle_count``): every world gets its own
        bodies and its own BVHs, and contacts stay within a world (``warpsim.worlds.batch``)."""
        tiled = copy.copy(self)
        n, P = int(world_count), int(world_particle_count)
        B = self.body_count
        tiled._body_topology = np.tile(self._body_topology, n)
        tiled._body_offset = (self._body_offset[None, :] + P * np.arange(n)[:, None]).reshape(-1)
        tiled.body_world = np.repeat(np.arange(n), B)
        return tiled

    def bind(self, model) -> None:
        super().bind(model)
        n = model.particle_count
        body_world = self.body_world
        if body_world is None:
            body_world = np.zeros(self.body_count, dtype=np.int64)
        order = np.argsort(body_world, kind="stable")  # bodies world by world
        tri, vert, edges = [], [], []
        topo_verts = [np.unique(f) for f in self._topologies]
        topo_edges = [meshtools.edge_topology(f)[0] if self.edge_contact else None for f in self._topologies]
        seen = np.full(n, -1, dtype=np.int64)
        for k in order:
            t, offset = self._body_topology[k], self._body_offset[k]
            faces = self._topologies[t] + offset
            verts = topo_verts[t] + offset
            if verts[0] < 0 or verts[-1] >= n:
                raise ValueError(f"SoftContact bodies[{k}]: triangle index {int(verts[-1])} is out of range "
                                 f"[0, {n}); build the bodies into this model")
            shared = verts[seen[verts] >= 0]
            if len(shared):
                raise ValueError(f"SoftContact bodies[{k}]: particle {int(shared[0])} also belongs to bodies"
                                 f"[{int(seen[shared[0]])}]; every body needs its own particles")
            seen[verts] = k
            tri.append(faces)
            vert.append(verts)
            if self.edge_contact:
                edges.append(topo_edges[t] + offset)
        # bodies are numbered in world order (s = position in ``order``): the groups of the BVHs
        bodies = len(order)
        worlds = int(body_world.max()) + 1
        sorted_world = body_world[order]
        counts = {"tri": np.array([len(f) for f in tri]), "vert": np.array([len(v) for v in vert]),
                  "edge": np.array([len(e) for e in edges], dtype=np.int64)}
        d = model.device

        def ints(a):
            return wp.array(np.ascontiguousarray(np.concatenate(a) if isinstance(a, list) else a).reshape(-1)
                            .astype(np.int32), dtype=int, device=d)

        def per_body(kind):
            return np.repeat(np.arange(bodies), counts[kind])

        self._tri = ints(tri)
        self._tri_body = ints(per_body("tri"))
        self._vertex = ints(vert)
        self._vertex_body = ints(per_body("vert"))
        self._vertex_world = ints(np.repeat(sorted_world, counts["vert"]))
        per_world = np.zeros(worlds + 1, dtype=np.int64)
        np.add.at(per_world, sorted_world + 1, counts["tri"])
        self._world_tri_start = ints(np.cumsum(per_world))  # the all-pairs reference's ranges
        self.vertex_count = int(self._vertex.shape[0])
        self.triangle_count = int(counts["tri"].sum())
        self.world_count = worlds
        # body bounds from chunks of at most CHUNK contact vertices, each inside one body
        chunks = -(-counts["vert"] // self.CHUNK)
        chunk_body = np.repeat(np.arange(bodies), chunks)
        within = np.arange(len(chunk_body)) - (np.cumsum(chunks) - chunks)[chunk_body]
        vert_start = np.concatenate([[0], np.cumsum(counts["vert"])])
        self._chunk_start = ints(np.append(vert_start[chunk_body] + within * self.CHUNK, vert_start[-1]))
        self._chunk_body = ints(chunk_body)
        self._body_lower = wp.empty(bodies, dtype=wp.vec3, device=d)
        self._body_upper = wp.empty(bodies, dtype=wp.vec3, device=d)
        self._tri_lower = wp.empty(self.triangle_count, dtype=wp.vec3, device=d)
        self._tri_upper = wp.empty(self.triangle_count, dtype=wp.vec3, device=d)
        self._launch_bounds(model.particle_q, model.particle_q)
        # LBVH on CUDA: its in-place rebuild is capture safe (a CUDA graph replays the step)
        self._constructor = "lbvh" if d.is_cuda else "sah"
        self._body_world = ints(sorted_world)  # kept: a BVH holds its groups array by pointer (rebuilds read it)
        self._body_bvh = wp.Bvh(self._body_lower, self._body_upper, constructor=self._constructor,
                                groups=self._body_world)
        self._tri_bvh = wp.Bvh(self._tri_lower, self._tri_upper, constructor=self._constructor,
                               groups=self._tri_body)
        self._world_root = wp.zeros(worlds, dtype=int, device=d)
        self._body_tri_root = wp.zeros(bodies, dtype=int, device=d)
        self._steps = 0
        if self.rebuild_every is None:
            self._rebuild = self.REBUILD_EVERY_CUDA if d.is_cuda else self.REBUILD_EVERY_CPU
        self.edge_count = int(counts["edge"].sum())
        if self.edge_contact:
            self._edges = ints(edges)
            self._edge_body = ints(per_body("edge"))
            self._edge_world = ints(np.repeat(sorted_world, counts["edge"]))
            per_world[:] = 0
            np.add.at(per_world, sorted_world + 1, counts["edge"])
            self._world_edge_start = ints(np.cumsum(per_world))
            self._edge_lower = wp.empty(self.edge_count, dtype=wp.vec3, device=d)
            self._edge_upper = wp.empty(self.edge_count, dtype=wp.vec3, device=d)
            self._launch_edge_bounds(model.particle_q, model.particle_q)
            self._edge_bvh = wp.Bvh(self._edge_lower, self._edge_upper, constructor=self._constructor,
                                    groups=self._edge_body)
            self._body_edge_root = wp.zeros(bodies, dtype=int, device=d)
        self._find_roots()
        slots = self.vertex_count + self.edge_count
        self._contact_particles = wp.full(slots, wp.vec4i(-1, -1, -1, -1), dtype=wp.vec4i, device=d)
        self._contact_weights = wp.zeros(slots, dtype=wp.vec4, device=d)
        self._contact_normal = wp.zeros(slots, dtype=wp.vec3, device=d)
        self._particle_contacts = wp.zeros(n, dtype=int, device=d)
        self._total = wp.zeros(2, dtype=int, device=d)
        self._dx = wp.zeros((n, 3), dtype=wp.int64, device=d)
        self._dv = wp.zeros((n, 3), dtype=wp.int64, device=d)
        # the last search's contact slots and their particles, listed once (``kernels.soft_contact.list_touched``):
        # the passes run over these only (at 1,000 tori 2.7 M of 8 M slots held a contact)
        self._touch_mark = wp.zeros(n, dtype=int, device=d)
        self._touch_list = wp.zeros(n, dtype=int, device=d)
        self._touch_count = wp.zeros(1, dtype=int, device=d)
        self._slot_list = wp.zeros(slots, dtype=int, device=d)
        self._slot_count = wp.zeros(1, dtype=int, device=d)
        self._touch_listed = False
        self._impulse_counts = wp.zeros(n, dtype=int, device=d)  # per pass: contacts giving a particle an impulse
        if self.broad_phase == "list":
            self._bind_list(n, slots)
        self.record_candidates(False)

    def _bind_list(self, n: int, slots: int) -> None:
        """Buffers of the candidate list (``broad_phase="list"``): ``capacity`` candidates a query,
        the contact vertices' positions at the last refit and search, the device flags
        (``warpsim.kernels.soft_contact_list``), the found contacts and their particles."""
        d = self.model.device
        self._cand = wp.zeros(slots * self.capacity, dtype=int, device=d)
        self._cand_count = wp.zeros(slots, dtype=int, device=d)
        self._x_tree = wp.zeros(self.vertex_count, dtype=wp.vec3, device=d)
        self._x_search = wp.zeros(self.vertex_count, dtype=wp.vec3, device=d)
        self._flags = wp.zeros(3, dtype=int, device=d)
        self._motion = wp.zeros(2, dtype=float, device=d)  # moved since the refit, in this step (max)
        self._active = wp.zeros(slots, dtype=int, device=d)
        self._touched = wp.zeros(n, dtype=int, device=d)
        self._seen = wp.zeros(n, dtype=int, device=d)  # a particle's contacts this step (the touched list's marks)
        self._listed = wp.zeros(2, dtype=int, device=d)

    def record_candidates(self, on: bool = True) -> None:
        """Diagnostics: with ``on``, every later step also writes, per vertex and per edge query,
        (candidates the broad phase returned, of them the query's own body's, bodies visited, contacts kept) for
        :meth:`candidate_stats` (allocates here, outside a step; off: zero-length buffers, no writes)."""
        d = self.model.device
        self._candidates_vertex = wp.zeros(self.vertex_count if on else 0, dtype=wp.vec4i, device=d)
        self._candidates_edge = wp.zeros(self.edge_count if on else 0, dtype=wp.vec4i, device=d)

    def candidate_stats(self) -> dict:
        """Per query kind ("vertex", "edge"): queries, candidates visited (total, mean and max
        per query), own-body candidates (total), other bodies visited per query, contacts kept, visited per contact kept, from the
        last step (reads back; :meth:`record_candidates` must be on)."""
        out = {}
        for kind, arr in (("vertex", self._candidates_vertex), ("edge", self._candidates_edge)):
            c = arr.numpy().astype(np.int64).reshape(-1, 4)
            if not len(c):
                continue
            visited, own, bodies, kept = (int(x) for x in c.sum(0))
            out[kind] = {"queries": len(c), "visited": visited, "per_query": visited / len(c),
                         "max_per_query": int(c[:, 0].max()), "own_body": own, "bodies_per_query": bodies / len(c),
                         "kept": kept, "visited_per_kept": visited / max(kept, 1)}
        return out

    def _launch_edge_bounds(self, q, q_prev) -> None:
        wp.launch(K.edge_bounds, self.edge_count, inputs=[self._edges, q, q_prev, self._edge_lower, self._edge_upper],
                  device=self.model.device)

    def _launch_bounds(self, q, q_prev) -> None:
        """Triangle bounds now, body bounds over the step (start and end)."""
        d = self.model.device
        wp.launch(K.triangle_bounds, self.triangle_count, inputs=[self._tri, q, self._tri_lower, self._tri_upper],
                  device=d)
        wp.launch(K.reset_bounds, self.body_count, inputs=[self._body_lower, self._body_upper], device=d)
        wp.launch(K.body_bounds, self._chunk_body.shape[0], inputs=[self._chunk_start, self._chunk_body,
                                                                    self._vertex, q, q_prev, self._body_lower,
                                                                    self._body_upper], device=d)

    def _find_roots(self) -> None:
        """Subtree roots of each world (body BVH) and each body (triangle and edge BVHs)."""
        d = self.model.device
        wp.launch(K.group_roots, self.world_count, inputs=[self._body_bvh.id, self._world_root], device=d)
        wp.launch(K.group_roots, self.body_count, inputs=[self._tri_bvh.id, self._body_tri_root], device=d)
        if self.edge_contact:
            wp.launch(K.group_roots, self.body_count, inputs=[self._edge_bvh.id, self._body_edge_root], device=d)

    @property
    def bvhs(self) -> list:
        """The BVHs at the last step: over the bodies' bounds (grouped by world), over the contact
        triangles (grouped by body) and, with edge contact, over the surface edges (grouped by body)."""
        return [self._body_bvh, self._tri_bvh] + ([self._edge_bvh] if self.edge_contact else [])

    def set_broad_phase(self, name: str) -> None:
        """Switch the search after binding ("bvh", "list" or "all_pairs"; the list's buffers are
        allocated here, outside a step); the next step searches afresh."""
        if name not in ("bvh", "list", "all_pairs"):
            raise ValueError(f"SoftContact broad_phase is {name!r}; use 'bvh', 'list' or 'all_pairs'")
        self.broad_phase = name
        if name == "list" and not hasattr(self, "_cand"):
            self._bind_list(self.model.particle_count, self.vertex_count + self.edge_count)
        self._particle_contacts.zero_()  # the list's steps start from zero counts (the BVH search leaves them)
        if hasattr(self, "_seen"):
            self._seen.zero_()
        self._recorded_key: tuple | None = None
        self._steps = 0

    @property
    def schedule_period(self) -> int:
        """Steps after which the host's launches repeat (a CUDA graph of this many steps replays
        the schedule): ``search_every`` for "list", else the rebuild period (at least 1)."""
        return self.search_every if self.broad_phase == "list" else max(1, self.rebuild_period)

    def list_stats(self) -> dict:
        """``broad_phase="list"``: searches done, queries that overflowed the capacity, and the last
        search's candidates per query (mean and max, vertex and edge queries) (reads back)."""
        flags = self._flags.numpy()
        counts = self._cand_count.numpy()
        v = self.vertex_count
        out: dict = {"searches": int(flags[1]), "overflow": int(flags[2])}
        for kind, c in (("vertex", counts[:v]), ("edge", counts[v:])):
            if len(c):
                out[kind] = {"per_query": float(c.mean()), "max": int(c.max())}
        return out

    @property
    def candidate_overflow(self) -> int:
        """``broad_phase="list"``: queries whose candidates exceeded ``capacity`` so far (reads back;
        read it at a frame's end: nonzero means contacts may have been missed, raise the capacity)."""
        return int(self._flags.numpy()[2]) if self.broad_phase == "list" else 0

    @property
    def rebuild_period(self) -> int:
        """Steps between BVH rebuilds in use (refits in between; 0: refit only); settable."""
        return int(self._rebuild or 0)

    @rebuild_period.setter
    def rebuild_period(self, steps: int) -> None:
        if isinstance(steps, bool) or not isinstance(steps, int) or steps < 0:
            raise ValueError(f"SoftContact rebuild_period is {steps!r}; give an integer >= 0 (0: refit only)")
        self._rebuild = steps

    def _update_bvhs(self) -> None:
        """Rebuild every ``rebuild_every`` steps (then find the subtree roots again), refit otherwise."""
        if self._rebuild and (self._steps - 1) % self._rebuild == 0:
            for bvh in self.bvhs:
                bvh.rebuild(self._constructor)
            self._find_roots()
        else:
            for bvh in self.bvhs:
                bvh.refit()

    def implicit_force(self, stiffness: float, damping: float = 0.0, coupling: bool = False) -> SoftContactForce:
        """This contact as a penalty force for an implicit solve (:class:`SoftContactForce`): pass it
        among the Simulator's forces, this SoftContact among its colliders."""
        return SoftContactForce(self, stiffness, damping, coupling)

    @property
    def contact_count(self) -> int:
        """Vertex-triangle contacts found in the last step (reads the counts back)."""
        return int(self._total.numpy()[0])

    @property
    def edge_contact_count(self) -> int:
        """Edge-edge contacts found in the last step (reads the counts back)."""
        return int(self._total.numpy()[1])

    def apply(self, model, state, q_prev, dt) -> None:
        d, v, e = model.device, self.vertex_count, self.edge_count
        if d.is_cpu and d.is_capturing:
            raise ValueError("SoftContact does not run inside a graph captured on the CPU; use "
                             "ws.ClothSimulator(..., use_graph=False) or ws.Simulator")
        all_pairs = self.broad_phase == "all_pairs"
        self._steps += 1
        self._clear_touched()
        if self.broad_phase == "list":
            self._apply_listed(model, state, q_prev, dt)
            return
        self._particle_contacts.zero_()
        self._total.zero_()
        contact = [self._contact_particles, self._contact_weights, self._contact_normal, self._particle_contacts,
                   self._total]
        common = [model.particle_q, model.particle_inv_mass, self.detect_distance, self.search, self.thickness,
                  int(self.self_contact), self.self_rest_distance]
        edge_common = [*common[:2], self.edge_detect_distance, *common[3:]]
        vertex = [self._vertex_world, self._vertex, self._vertex_body, self._tri, self._tri_body, state.positions]
        if all_pairs:
            wp.launch(K.find_vertex_contacts_all_pairs, v, inputs=[self._world_tri_start, *vertex, *common, *contact],
                      device=d)
            if e:
                wp.launch(K.find_edge_contacts_all_pairs, e, inputs=[self._world_edge_start, self._edge_world,
                                                                     self._edges, self._edge_body, state.positions,
                                                                     q_prev, *edge_common, v, *contact], device=d)
        else:
            self._launch_bounds(state.positions, q_prev)
            if e:
                self._launch_edge_bounds(state.positions, q_prev)
            self._update_bvhs()
            body = [self._body_bvh.id, self._world_root]
            wp.launch(K.find_vertex_contacts, v, inputs=[*body, self._tri_bvh.id, self._body_tri_root, *vertex,
                                                         *common, *contact, self._candidates_vertex], device=d)
            if e:
                wp.launch(K.find_edge_contacts, e, inputs=[*body, self._edge_bvh.id, self._body_edge_root,
                                                           self._edge_world, self._edges, self._edge_body,
                                                           state.positions, q_prev, *edge_common, v, *contact,
                                                           self._candidates_edge], device=d)
        slots = [self._contact_particles, self._contact_weights, self._contact_normal, self._particle_contacts]
        self._list_touched()
        q, qd, inv_dt = state.positions, state.velocities, self._inv_dt(dt)
        stride = min(v + e, self.LIST_THREADS)
        listed = [stride, self._slot_count, self._slot_list, q, qd, model.particle_inv_mass]
        for _ in range(self.iterations):
            wp.launch(L.count_listed_impulses, stride, inputs=[*listed, *slots[:3], self.thickness, inv_dt,
                                                               self._impulse_counts], device=d)
            wp.launch(L.resolve_listed, stride, inputs=[*listed, *slots, self._impulse_counts, self.thickness,
                                                        self.push, self.restitution, self.friction, inv_dt, self._dx,
                                                        self._dv], device=d)
            self._apply_touched(q, qd, positions_only=False)

    def _list_touched(self) -> None:
        """List the particles of the stored contacts (once per search)."""
        wp.launch(K.list_touched, self.vertex_count + self.edge_count,
                  inputs=[self._contact_particles, self._touch_mark, self._touch_list, self._touch_count,
                          self._slot_list, self._slot_count], device=self.model.device)
        self._touch_listed = True

    def _apply_touched(self, q, qd, positions_only: bool, count=None, touched=None) -> None:
        """Apply the deltas of the listed particles (``count[0]`` of ``touched``; default the list of
        ``_list_touched``)."""
        stride = min(self.model.particle_count, self.LIST_THREADS)
        count = self._touch_count if count is None else count
        touched = self._touch_list if touched is None else touched
        wp.launch(K.apply_touched, stride, inputs=[stride, count, touched, self._dx, self._dv, q, qd,
                                                   int(positions_only), self._impulse_counts],
                  device=self.model.device)

    def _clear_touched(self) -> None:
        """Lower the marks of the listed particles and empty the list (before the next search)."""
        if self._touch_listed:
            stride = min(self.model.particle_count, self.LIST_THREADS)
            wp.launch(K.clear_touched, stride, inputs=[stride, self._touch_count, self._touch_list, self._touch_mark],
                      device=self.model.device)
            self._touch_count.zero_()
            self._slot_count.zero_()
            self._touch_listed = False

    def project_positions(self, q, passes: int = 1) -> None:
        """Push the pairs found by the last step's search apart at the positions ``q`` (``passes``
        Jacobi passes of the position push alone, ``kernels.soft_contact.push_listed``: no velocity
        changes, no search), for a solver that iterates on positions within a step
        (``ws.FastMassSpring(contacts=...)``: between its iterations the springs then adapt to the
        pushed vertices). The pairs are those within thickness + reach at the end of the last step;
        the push uses their stored normals and weights, and skips pairs deeper than ``search``."""
        slots = [self._contact_particles, self._contact_weights, self._contact_normal, self._particle_contacts]
        if self.broad_phase == "list":  # its narrow phase listed the contacts and their particles already
            listed, particles = (self._listed, self._active), (self._listed[1:], self._touched)
        else:
            if not self._touch_listed:
                self._list_touched()
            listed, particles = (self._slot_count, self._slot_list), (self._touch_count, self._touch_list)
        stride = min(self.vertex_count + self.edge_count, self.LIST_THREADS)
        for _ in range(passes):
            wp.launch(K.push_listed, stride, inputs=[stride, *listed, q, self.model.particle_inv_mass, *slots,
                                                     self.thickness, self.push, self.search, self._dx],
                      device=self.model.device)
            self._apply_touched(q, q, True, *particles)

    @property
    def vertex_particles(self) -> np.ndarray:
        """Particle index of each contact vertex (surface vertices of the bodies), shape (V,) (reads back)."""
        return self._vertex.numpy()

    @property
    def detect_distance(self) -> float:
        """Distance [m] within which vertex-triangle pairs are kept as contacts: thickness + reach."""
        return self.thickness + self.reach

    @property
    def edge_detect_distance(self) -> float:
        """Distance [m] within which edge-edge pairs are kept as contacts: thickness + edge_reach."""
        return self.thickness + self.edge_reach

    def _inv_dt(self, dt) -> float:
        """1 / dt [1/s] for speculative contacts (``reach`` > 0), else 0 (``resolve_one``)."""
        return 1.0 / float(dt) if self.reach > 0.0 else 0.0

    def _refit_listed(self, q) -> None:
        """Host cadence (every ``search_every`` steps): rebuild the BVHs at the current positions and
        raise the search flag."""
        d = self.model.device
        self._launch_bounds(q, q)
        if self.edge_count:
            self._launch_edge_bounds(q, q)
        for bvh in self.bvhs:
            bvh.rebuild(self._constructor)
        self._find_roots()
        wp.launch(L.begin_search, self.vertex_count, inputs=[self._vertex, q, self._x_tree, self._flags, self._motion],
                  device=d)

    def _record_listed(self, model, state, q_prev, dt) -> list:
        """The launches of every step of ``broad_phase="list"``, recorded once (``record_cmd``: a
        replayed launch skips most of ``wp.launch``'s host work): zero the last step's particles' contact
        counts (``forget_listed``), check the motion, search if the flag is up (both pair kinds, one
        launch), lower it and clear the list lengths (``end_search``), the nearest contact per query among
        its candidates, then ``iterations`` passes over the found contacts and their particles only."""
        d, n, v, e = model.device, model.particle_count, self.vertex_count, self.edge_count
        q, qd = state.positions, state.velocities
        edge_tree = [self._edge_bvh.id, self._body_edge_root, self._edge_world, self._edges, self._edge_body] if e \
            else [self._tri_bvh.id, self._body_tri_root, self._vertex_world, self._tri, self._tri_body]
        contact = [self._contact_particles, self._contact_weights, self._contact_normal]

        def record(kernel, dim, inputs):
            return wp.launch(kernel, dim, inputs=inputs, device=d, record_cmd=True)

        threads = [min(v + e, self.LIST_THREADS), min(n, self.LIST_THREADS)]
        launches = [
            record(L.forget_listed, threads[1], [threads[1], self._listed, self._touched, self._particle_contacts,
                                                 self._seen]),
            record(L.check_motion, v, [self._vertex, q, q_prev, self._x_search, self._x_tree, self.pad,
                                       0.5 * self.thickness, self._flags, self._motion]),
            record(L.search_candidates, v + e, [
                self._flags, self._motion, self.detect_distance, self.edge_detect_distance, self.search, self.pad,
                self._body_bvh.id,
                self._world_root, self._tri_bvh.id, self._body_tri_root, edge_tree[0], edge_tree[1],
                self._vertex_world, self._vertex, self._vertex_body, self._tri, self._tri_body, *edge_tree[2:], q,
                model.particle_q, model.particle_inv_mass, int(self.self_contact), self.self_rest_distance,
                self.capacity, self._x_search, self._cand, self._cand_count]),
            record(L.end_search, 1, [self._flags, self._motion, self._total, self._listed]),
            record(L.narrow_candidates, v + e, [
                self._cand, self._cand_count, self.capacity, self._vertex, self._tri, edge_tree[3], q, q_prev,
                self.detect_distance, self.edge_detect_distance, self.search, self.thickness, *contact,
                self._particle_contacts, self._seen,
                self._total, self._active, self._touched, self._listed]),
        ]
        for _ in range(self.iterations):
            launches.append(record(L.count_listed_impulses, threads[0], [
                threads[0], self._listed, self._active, q, qd, model.particle_inv_mass, *contact, self.thickness,
                self._inv_dt(dt), self._impulse_counts]))
            launches.append(record(L.resolve_listed, threads[0], [
                threads[0], self._listed, self._active, q, qd, model.particle_inv_mass, *contact, self._particle_contacts,
                self._impulse_counts, self.thickness, self.push, self.restitution, self.friction, self._inv_dt(dt),
                self._dx, self._dv]))
            launches.append(record(L.apply_listed, threads[1], [threads[1], self._listed, self._touched, self._dx,
                                                                self._dv, q, qd, self._impulse_counts]))
        return launches

    def _apply_listed(self, model, state, q_prev, dt) -> None:
        """``broad_phase="list"``: the host's refit cadence, then the recorded launches of a step
        (recorded again when an array or a setting they take changed)."""
        if (self._steps - 1) % self.search_every == 0:
            self._refit_listed(state.positions)
        key = (state.positions.ptr, state.velocities.ptr, q_prev.ptr, self.pad, self.thickness, self.search,
               self.iterations, self.push, self.restitution, self.friction, self.reach, self.edge_reach,
               self._inv_dt(dt),
               self._bvh_ids())
        if getattr(self, "_recorded_key", None) != key:
            self._recorded = self._record_listed(model, state, q_prev, dt)
            self._recorded_key = key
        for launch in self._recorded:
            launch.launch()

    def _bvh_ids(self) -> tuple:
        return tuple(int(b.id) for b in self.bvhs)

    def contact_slots(self) -> tuple:
        """(particles, weights, normals) of the contact slots the last search stored (device arrays,
        not copies: ``SoftContactForce`` reads them inside an implicit solve)."""
        return self._contact_particles, self._contact_weights, self._contact_normal
