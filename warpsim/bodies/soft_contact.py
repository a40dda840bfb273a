"""Soft body against soft body: vertices of one body against the triangles of another.

:class:`SoftContact` is a collider (it runs after integration, so it works with every
integrator, semi-implicit and implicit Euler included). Each step it refits one ``wp.Mesh``
BVH per body over its surface triangles (``mesh.refit()`` on a copy of the current positions),
finds for every surface vertex the nearest triangle of another body (optionally of its own
body: ``self_contact``) closer than ``thickness`` [m], pushes the pair apart and applies
an inelastic impulse with restitution and Coulomb friction. Impulses act on the vertex and,
weighted by barycentrics, on the triangle's three vertices, equal and opposite: momentum is
conserved exactly. Kernels: ``warpsim.kernels.soft_contact`` (the method is described there).

Example::

    a = ws.add_soft_body(builder, *torus, position=(0, 0.3, 0))
    b = ws.add_soft_body(builder, *torus, position=(0, 0.45, 0))
    contact = ws.SoftContact([a, b], thickness=0.01, friction=0.5)
    sim = ws.Simulator(builder.finalize(), colliders=[ws.Plane(), contact])
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from ..core.collider import Collider
from ..kernels import soft_contact as K


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
    """Vertex-triangle contact between soft bodies (see module docstring).

    Args:
        bodies: SoftBody objects (``ws.add_soft_body``) or (F, 3) triangle arrays in particle
            indices; each is one body. Their surface vertices are the contact vertices.
        thickness: contact distance [m]: a vertex is kept at least this far in front of every
            other body's triangles.
        restitution: normal restitution e in [0, 1] (0: the approach stops).
        friction: Coulomb friction coefficient mu >= 0.
        self_contact: also test a body's vertices against its own triangles (except triangles
            within ``self_rest_distance`` [m] of the vertex in the rest pose; default 2 x thickness).
        iterations: impulse passes per step (Jacobi; more resolve a crowded contact better).
        search: how far behind a triangle [m] a vertex still counts as penetrating and is pushed
            back out (default 3 x thickness).
        push: fraction of a contact's depth removed by moving positions each step (default 0.5;
            1 removes it at once but makes resting contacts jitter: measured on a 4-torus heap,
            kinetic energy at rest 0.02-0.05 J with 1, 0.002 J with 0.5, of a 13 J peak).

    After a step, ``contact_count`` (one read-back) is the number of vertex contacts found.
    """

    def __init__(self, bodies, *, thickness: float = 0.005, restitution: float = 0.0, friction: float = 0.5,
                 self_contact: bool = False, iterations: int = 4, search: float | None = None,
                 self_rest_distance: float | None = None, push: float = 0.5):
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
        self._meshes = []

    def bind(self, model) -> None:
        super().bind(model)
        n = model.particle_count
        tri, vert, vert_body = [], [], []
        seen = np.full(n, -1, dtype=np.int64)
        for k, faces in enumerate(self.faces):
            if faces.min() < 0 or faces.max() >= n:
                raise ValueError(f"SoftContact bodies[{k}]: triangle index {int(faces.max())} is out of range "
                                 f"[0, {n}); build the bodies into this model")
            verts = np.unique(faces)
            shared = verts[seen[verts] >= 0]
            if len(shared):
                raise ValueError(f"SoftContact bodies[{k}]: particle {int(shared[0])} also belongs to bodies"
                                 f"[{int(seen[shared[0]])}]; every body needs its own particles")
            seen[verts] = k
            tri.append(faces)
            vert.append(verts)
            vert_body.append(np.full(len(verts), k))
        d = model.device
        i32 = np.int32
        self._tri = wp.array(np.concatenate(tri).reshape(-1).astype(i32), dtype=int, device=d)
        self._tri_start = wp.array(np.concatenate([[0], np.cumsum([len(f) for f in tri])]).astype(i32), dtype=int,
                                   device=d)
        self._vertex = wp.array(np.concatenate(vert).astype(i32), dtype=int, device=d)
        self._vertex_body = wp.array(np.concatenate(vert_body).astype(i32), dtype=int, device=d)
        self.vertex_count = int(self._vertex.shape[0])
        self.triangle_count = sum(len(f) for f in tri)
        v = self.vertex_count
        self._points = wp.clone(model.particle_q)
        self._meshes = [wp.Mesh(points=self._points, indices=wp.array(f.reshape(-1).astype(i32), dtype=int, device=d))
                        for f in tri]
        self._mesh_ids = wp.array([m.id for m in self._meshes], dtype=wp.uint64, device=d)
        self._contact_tri = wp.zeros(v, dtype=int, device=d)
        self._contact_bary = wp.zeros(v, dtype=wp.vec3, device=d)
        self._contact_normal = wp.zeros(v, dtype=wp.vec3, device=d)
        self._contact_depth = wp.zeros(v, dtype=float, device=d)
        self._particle_contacts = wp.zeros(n, dtype=int, device=d)
        self._total = wp.zeros(1, dtype=int, device=d)
        self._dx = wp.zeros(n, dtype=wp.vec3, device=d)
        self._dv = wp.zeros(n, dtype=wp.vec3, device=d)

    @property
    def meshes(self) -> list:
        """One BVH ``wp.Mesh`` per body (points: positions at the last step)."""
        return self._meshes

    @property
    def contact_count(self) -> int:
        """Vertex-triangle contacts found in the last step (reads one int back)."""
        return int(self._total.numpy()[0])

    def apply(self, model, state, q_prev, dt) -> None:
        d, n, v = model.device, model.particle_count, self.vertex_count
        if d.is_cpu and d.is_capturing:
            # wp.Mesh.refit on the CPU is a host call that a captured graph would not replay
            raise ValueError("SoftContact cannot run inside a graph captured on the CPU (the BVH refit would not "
                             "be replayed); use ws.ClothSimulator(..., use_graph=False) or ws.Simulator")
        wp.copy(self._points, state.positions)
        for mesh in self._meshes:
            mesh.refit()
        self._particle_contacts.zero_()
        self._total.zero_()
        wp.launch(K.find_soft_contacts, v,
                  inputs=[self._mesh_ids, self._tri_start, state.positions, model.particle_q, model.particle_inv_mass,
                          self._tri, self._vertex, self._vertex_body, self.thickness, self.search,
                          int(self.self_contact), self.self_rest_distance, self._contact_tri, self._contact_bary,
                          self._contact_normal, self._contact_depth, self._particle_contacts, self._total], device=d)
        contact = [self._contact_tri, self._contact_bary, self._contact_normal]
        wp.launch(K.push_soft_contacts, v,
                  inputs=[model.particle_inv_mass, self._tri, self._vertex, *contact, self._contact_depth,
                          self._particle_contacts, self.push, self._dx], device=d)
        for _ in range(self.iterations):
            wp.launch(K.impulse_soft_contacts, v,
                      inputs=[state.velocities, model.particle_inv_mass, self._tri, self._vertex, *contact,
                              self._particle_contacts, self.restitution, self.friction, self._dv], device=d)
            wp.launch(K.apply_soft_contact_deltas, n, inputs=[self._dx, self._dv, state.positions, state.velocities],
                      device=d)
