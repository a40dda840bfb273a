"""Soft body against soft body: vertices against triangles and edges against edges of other bodies.

:class:`SoftContact` is a collider (it runs after integration, so it works with every
integrator, semi-implicit and implicit Euler included). Each step it rebuilds one ``wp.Bvh`` over
the contact triangles of all bodies (one per world in a batch) and one over their surface edges;
every surface vertex queries the triangle BVH once and keeps the nearest triangle of another body
(optionally of its own body: ``self_contact``) closer than ``thickness`` [m], every surface edge
queries the edge BVH once and keeps the nearest edge of another body. Each pair is pushed apart and given an inelastic impulse with restitution and
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

from ..core.collider import Collider
from ..kernels import soft_contact as K
from . import meshtools


def _body_faces(body, k: int) -> np.ndarray:
    faces = getattr(body, "faces", body)
    try:
        faces = np.asarray(faces, dtype=np.int64)
    except (TypeError, ValueError):
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
        broad_phase: "bvh" (one BVH over all bodies' triangles, one over their edges) or
            "all_pairs" (every vertex against every triangle of its world: the O(n^2) reference).
        rebuild_every: rebuild the BVHs every this many steps and refit them in between (0: refit
            only; None: every step on CUDA, where the LBVH rebuild is cheap and a captured graph
            replays one step, every 20 steps on the CPU, where a SAH rebuild costs about 1.2 us per
            triangle or edge, measured). A refit keeps the tree of the first layout, whose boxes
            swell as bodies travel (a falling heap: 8.5x the step time at 48 tori against 12 with
            refits only, measured on the CPU). Results do not depend on it (nearest contacts).

    After a step, ``contact_count`` and ``edge_contact_count`` (one read-back each) are the
    numbers of vertex-triangle and edge-edge contacts found.
    """

    def __init__(self, bodies, *, thickness: float = 0.005, restitution: float = 0.0, friction: float = 0.5,
                 self_contact: bool = False, iterations: int = 4, search: float | None = None,
                 self_rest_distance: float | None = None, push: float = 0.5, edge_contact: bool = True,
                 broad_phase: str = "bvh", rebuild_every: int | None = None):
        bodies = list(bodies) if not isinstance(bodies, np.ndarray) else [bodies]
        if not bodies:
            raise ValueError("SoftContact needs at least one body (a SoftBody or an (F, 3) triangle array)")
        self.faces = [_body_faces(b, k) for k, b in enumerate(bodies)]
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
        self.friction = float(friction)
        self.restitution = restitution
        self.self_contact = bool(self_contact)
        self.iterations = int(iterations)
        self.search = 3.0 * self.thickness if search is None else float(search)
        self.self_rest_distance = 2.0 * self.thickness if self_rest_distance is None else float(self_rest_distance)
        for name in ("search", "self_rest_distance"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"SoftContact {name} is {value}; it must be finite and >= 0 [m]")
        if len(self.faces) < 2 and not self.self_contact:
            raise ValueError("SoftContact with one body does nothing unless self_contact=True; give two bodies or more")
        self.push = float(push)
        if not (math.isfinite(self.push) and 0.0 <= self.push <= 1.0):
            raise ValueError(f"SoftContact push is {push}; it must be in [0, 1] (fraction of the depth removed per step)")
        if broad_phase not in ("bvh", "all_pairs"):
            raise ValueError(f"SoftContact broad_phase is {broad_phase!r}; use 'bvh' or 'all_pairs'")
        self.broad_phase = broad_phase
        if rebuild_every is not None and (isinstance(rebuild_every, bool) or not isinstance(rebuild_every, int)
                                          or rebuild_every < 0):
            raise ValueError(f"SoftContact rebuild_every is {rebuild_every!r}; give an integer >= 0 (steps between BVH "
                             "rebuilds; 0: refit only)")
        self.rebuild_every = rebuild_every
        self._rebuild = rebuild_every
        self.edge_contact = bool(edge_contact)
        self.body_world: np.ndarray | None = None  # (faces,) world of each body's faces, batches only
        self._tri_bvhs, self._bvhs = [], []

    def tile(self, world_count: int, world_particle_count: int) -> SoftContact:
        """The same contact for ``world_count`` copies of the model laid end to end (world w owns
        particles ``w P .. (w + 1) P - 1``, P = ``world_particle_count``): every world gets its own
        bodies and its own BVHs, and contacts stay within a world (``warpsim.worlds.batch``)."""
        tiled = copy.copy(self)
        n, P = int(world_count), int(world_particle_count)
        tiled.faces = [faces + w * P for w in range(n) for faces in self.faces]
        tiled.body_world = np.repeat(np.arange(n), len(self.faces))
        tiled._tri_bvhs, tiled._bvhs = [], []
        return tiled

    def bind(self, model) -> None:
        super().bind(model)
        n = model.particle_count
        body_world = self.body_world
        if body_world is None:
            body_world = np.zeros(len(self.faces), dtype=np.int64)
        order = np.argsort(body_world, kind="stable")  # bodies world by world
        tri, tri_body, vert, vert_body, edges, edge_body = [], [], [], [], [], []
        seen = np.full(n, -1, dtype=np.int64)
        for k in order:
            faces = self.faces[k]
            if faces.min() < 0 or faces.max() >= n:
                raise ValueError(f"SoftContact bodies[{k}]: triangle index {int(faces.max())} is out of range "
                                 f"[0, {n}); build the bodies into this model")
            verts = np.unique(faces)
            shared = verts[seen[verts] >= 0]
            if len(shared):
                raise ValueError(f"SoftContact bodies[{k}]: particle {int(shared[0])} also belongs to bodies"
                                 f"[{int(seen[shared[0]])}]; every body needs its own particles")
            seen[verts] = k
            body_edges, _, _ = meshtools.edge_topology(faces)
            tri.append(faces)
            tri_body.append(np.full(len(faces), k))
            vert.append(verts)
            vert_body.append(np.full(len(verts), k))
            edges.append(body_edges)
            edge_body.append(np.full(len(body_edges), k))
        worlds = int(body_world.max()) + 1
        sorted_world = body_world[order]
        counts = {"tri": [len(f) for f in tri], "vert": [len(v) for v in vert], "edge": [len(e) for e in edges]}

        def starts(kind):
            per_world = np.zeros(worlds + 1, dtype=np.int64)
            np.add.at(per_world, sorted_world + 1, counts[kind])
            return np.cumsum(per_world)

        world_tri_start, world_edge_start = starts("tri"), starts("edge")
        d = model.device

        def ints(a):
            return wp.array(np.ascontiguousarray(np.concatenate(a) if isinstance(a, list) else a).reshape(-1)
                            .astype(np.int32), dtype=int, device=d)

        tri_all = np.concatenate(tri)
        self._tri = ints(tri)
        self._tri_body = ints(tri_body)
        self._vertex = ints(vert)
        self._vertex_body = ints(vert_body)
        self._vertex_world = ints(np.repeat(sorted_world, counts["vert"]))
        self._world_tri_start = ints(world_tri_start)
        self.vertex_count = int(self._vertex.shape[0])
        self.triangle_count = len(tri_all)
        self.world_count = worlds
        self._tri_lower = wp.empty(self.triangle_count, dtype=wp.vec3, device=d)
        self._tri_upper = wp.empty(self.triangle_count, dtype=wp.vec3, device=d)
        wp.launch(K.triangle_bounds, self.triangle_count, inputs=[self._tri, model.particle_q, self._tri_lower,
                                                                  self._tri_upper], device=d)
        # LBVH on CUDA: its in-place rebuild is capture safe (a CUDA graph replays the step)
        self._constructor = "lbvh" if d.is_cuda else "sah"
        self._tri_bvhs = [wp.Bvh(self._tri_lower[int(world_tri_start[w]):int(world_tri_start[w + 1])],
                                 self._tri_upper[int(world_tri_start[w]):int(world_tri_start[w + 1])],
                                 constructor=self._constructor)
                          for w in range(worlds)]
        self._tri_bvh_ids = wp.array([b.id for b in self._tri_bvhs], dtype=wp.uint64, device=d)
        self._steps = 0
        if self.rebuild_every is None:
            self._rebuild = 1 if d.is_cuda else 20
        self.edge_count = int(world_edge_start[-1]) if self.edge_contact else 0
        if self.edge_contact:
            self._edges = ints(edges)
            self._edge_body = ints(edge_body)
            self._edge_world = ints(np.repeat(sorted_world, counts["edge"]))
            self._world_edge_start = ints(world_edge_start)
            self._edge_lower = wp.empty(self.edge_count, dtype=wp.vec3, device=d)
            self._edge_upper = wp.empty(self.edge_count, dtype=wp.vec3, device=d)
            self._launch_edge_bounds(model.particle_q, model.particle_q)
            self._bvhs = [wp.Bvh(self._edge_lower[int(world_edge_start[w]):int(world_edge_start[w + 1])],
                                 self._edge_upper[int(world_edge_start[w]):int(world_edge_start[w + 1])],
                                 constructor=self._constructor)
                          for w in range(worlds)]
            self._bvh_ids = wp.array([b.id for b in self._bvhs], dtype=wp.uint64, device=d)
        slots = self.vertex_count + self.edge_count
        self._contact_particles = wp.full(slots, wp.vec4i(-1, -1, -1, -1), dtype=wp.vec4i, device=d)
        self._contact_weights = wp.zeros(slots, dtype=wp.vec4, device=d)
        self._contact_normal = wp.zeros(slots, dtype=wp.vec3, device=d)
        self._particle_contacts = wp.zeros(n, dtype=int, device=d)
        self._total = wp.zeros(2, dtype=int, device=d)
        self._dx = wp.zeros((n, 3), dtype=wp.int64, device=d)
        self._dv = wp.zeros((n, 3), dtype=wp.int64, device=d)
        self.record_candidates(False)

    def record_candidates(self, on: bool = True) -> None:
        """Diagnostics: with ``on``, every later step also writes, per vertex and per edge query,
        (candidates the broad phase returned, of them the query's own body's, contacts kept) for
        :meth:`candidate_stats` (allocates here, outside a step; off: zero-length buffers, no writes)."""
        d = self.model.device
        self._candidates_vertex = wp.zeros(self.vertex_count if on else 0, dtype=wp.vec3i, device=d)
        self._candidates_edge = wp.zeros(self.edge_count if on else 0, dtype=wp.vec3i, device=d)

    def candidate_stats(self) -> dict:
        """Per query kind ("vertex", "edge"): queries, candidates visited (total, mean and max
        per query), own-body candidates (total), contacts kept, visited per contact kept, from the
        last step (reads back; :meth:`record_candidates` must be on)."""
        out = {}
        for kind, arr in (("vertex", self._candidates_vertex), ("edge", self._candidates_edge)):
            c = arr.numpy().astype(np.int64).reshape(-1, 3)
            if not len(c):
                continue
            visited, own, kept = (int(x) for x in c.sum(0))
            out[kind] = {"queries": len(c), "visited": visited, "per_query": visited / len(c),
                         "max_per_query": int(c[:, 0].max()), "own_body": own, "kept": kept,
                         "visited_per_kept": visited / max(kept, 1)}
        return out

    def _launch_edge_bounds(self, q, q_prev) -> None:
        wp.launch(K.edge_bounds, self.edge_count, inputs=[self._edges, q, q_prev, self._edge_lower, self._edge_upper],
                  device=self.model.device)

    @property
    def bvhs(self) -> list:
        """The BVHs, per world: one over the triangle bounds, then (with edge contact) one over the
        edge bounds, at the last step."""
        return self._tri_bvhs + self._bvhs

    def _update(self, bvh) -> None:
        if self._rebuild and (self._steps - 1) % self._rebuild == 0:
            bvh.rebuild(self._constructor)
        else:
            bvh.refit()

    @property
    def contact_count(self) -> int:
        """Vertex-triangle contacts found in the last step (reads the counts back)."""
        return int(self._total.numpy()[0])

    @property
    def edge_contact_count(self) -> int:
        """Edge-edge contacts found in the last step (reads the counts back)."""
        return int(self._total.numpy()[1])

    def apply(self, model, state, q_prev, dt) -> None:
        d, n, v, e = model.device, model.particle_count, self.vertex_count, self.edge_count
        if d.is_cpu and d.is_capturing:
            raise ValueError("SoftContact does not run inside a graph captured on the CPU; use "
                             "ws.ClothSimulator(..., use_graph=False) or ws.Simulator")
        all_pairs = self.broad_phase == "all_pairs"
        self._steps += 1
        self._particle_contacts.zero_()
        self._total.zero_()
        contact = [self._contact_particles, self._contact_weights, self._contact_normal, self._particle_contacts,
                   self._total]
        common = [model.particle_q, model.particle_inv_mass, self.thickness, self.search, int(self.self_contact),
                  self.self_rest_distance]
        vertex = [self._vertex_world, self._vertex, self._vertex_body, self._tri, self._tri_body, state.positions]
        if all_pairs:
            wp.launch(K.find_vertex_contacts_all_pairs, v, inputs=[self._world_tri_start, *vertex, *common, *contact],
                      device=d)
        else:
            wp.launch(K.triangle_bounds, self.triangle_count, inputs=[self._tri, state.positions, self._tri_lower,
                                                                      self._tri_upper], device=d)
            for bvh in self._tri_bvhs:
                self._update(bvh)
            wp.launch(K.find_vertex_contacts, v, inputs=[self._tri_bvh_ids, self._world_tri_start, *vertex, *common,
                                                         *contact, self._candidates_vertex], device=d)
        if e:
            edge = [self._edge_world, self._edges, self._edge_body, state.positions, q_prev]
            if all_pairs:
                wp.launch(K.find_edge_contacts_all_pairs, e, inputs=[self._world_edge_start, *edge, *common, v,
                                                                     *contact], device=d)
            else:
                self._launch_edge_bounds(state.positions, q_prev)
                for bvh in self._bvhs:
                    self._update(bvh)
                wp.launch(K.find_edge_contacts, e, inputs=[self._bvh_ids, self._world_edge_start, *edge, *common, v,
                                                           *contact, self._candidates_edge], device=d)
        slots = [self._contact_particles, self._contact_weights, self._contact_normal, self._particle_contacts]
        for _ in range(self.iterations):
            wp.launch(K.resolve_contacts, v + e, inputs=[state.positions, state.velocities, model.particle_inv_mass,
                                                         *slots, self.thickness, self.push, self.restitution,
                                                         self.friction, self._dx, self._dv], device=d)
            wp.launch(K.apply_contact_deltas, n, inputs=[self._dx, self._dv, state.positions, state.velocities],
                      device=d)
