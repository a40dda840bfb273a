"""Contact constraints inside :class:`~warpsim.cloth.solver.ClothImplicitEuler`'s solve
(``kernels/cloth_contact.py`` has the method and why).

:class:`ContactConstraints` reads the simulator's colliders: static planes (``ws.Plane``,
``ws.Planes``, ``ws.Box``) and static capsules and spheres (solid or ``inside=True``) become
constraints; any other collider (meshes, rectangles, moving shapes, penalty mode) keeps acting
after the step only, as before. The colliders still run after every step: they resolve the
contacts that begin within it (time of impact) and keep every particle outside.
"""

from __future__ import annotations

import numpy as np
import warp as wp
import warp.sparse as wps

from ..kernels import cloth_contact as KCC

TOLERANCE = 0.05
"""A particle touches a shape when its gap is at most this fraction of its collision distance
(particle radius + the collider's thickness), plus ``TOLERANCE_FLOOR`` [m]."""
TOLERANCE_FLOOR = 1.0e-5

__all__ = ["TOLERANCE", "TOLERANCE_FLOOR", "ContactConstraints", "constraint_shapes"]


def _tolerance(radius: float, thickness: float) -> float:
    return float(TOLERANCE * (radius + thickness) + TOLERANCE_FLOOR)


def constraint_shapes(colliders, radius: float) -> list:
    """The ``kernels.cloth_contact.ContactShape`` values of the colliders that become constraints
    (static planes and capsules/spheres outside penalty mode), in collider order; ``radius`` [m]:
    the largest particle radius (the touching tolerance's scale)."""
    out = []
    for c in colliders or ():
        mode = getattr(c, "mode_name", None)
        if mode is None or mode == "penalty" or getattr(c, "motion", None) is not None:
            continue
        normals, offsets = getattr(c, "normals", None), getattr(c, "offsets", None)
        if normals is not None and offsets is not None:
            for n, o in zip(np.asarray(normals, float).reshape(-1, 3), np.atleast_1d(np.asarray(offsets, float))):
                s = KCC.ContactShape()
                s.kind, s.normal, s.offset = int(KCC.SHAPE_PLANE), wp.vec3(*n), float(o)
                s.thickness, s.friction, s.restitution = float(c.thickness), float(c.friction), float(c.restitution)
                s.tolerance = _tolerance(radius, float(c.thickness))
                out.append(s)
            continue
        if hasattr(c, "a_local") and hasattr(c, "radius") and hasattr(c, "world_pose"):
            s = KCC.ContactShape()
            s.kind = int(KCC.SHAPE_CONTAINER if getattr(c, "inside", 0) else KCC.SHAPE_CAPSULE)
            s.a, s.b, s.radius = wp.vec3(*np.asarray(c.a, float)), wp.vec3(*np.asarray(c.b, float)), float(c.radius)
            s.thickness, s.friction, s.restitution = float(c.thickness), float(c.friction), float(c.restitution)
            s.tolerance = _tolerance(radius, float(c.thickness))
            out.append(s)
    return out


def _signature(shapes) -> tuple:
    return tuple((s.kind, tuple(s.normal), s.offset, tuple(s.a), tuple(s.b), s.radius, s.thickness, s.friction,
                  s.restitution, s.tolerance) for s in shapes)


class ContactConstraints:
    """Per-particle contact constraints for one implicit cloth system (allocated once; every call
    launches kernels only, so a step stays capturable).

    Args:
        colliders: the simulator's collider list (read again before each uncaptured step, so a
            collider added or moved between frames is seen).
        model: the model (particle radii, inverse masses).
        A: the system's BSR matrix (its topology is fixed).
        diagonal_slots: per particle, the slot of its diagonal block in ``A.values``.
    """

    def __init__(self, colliders, model, A, diagonal_slots):
        self.colliders = colliders
        self.model = model
        d = model.device
        n = model.particle_count
        self.device, self.n = d, n
        self.A = A
        self.A_plain = wps.bsr_copy(A)  # A before filtering: the constraint impulses read it
        self.diagonal_slots = diagonal_slots
        self.normal = wp.zeros(n, dtype=wp.vec3, device=d)
        self.friction = wp.zeros(n, dtype=float, device=d)
        self.z = wp.zeros(n, dtype=wp.vec3, device=d)
        self.product = wp.zeros(n, dtype=wp.vec3, device=d)
        self.rhs_plain = wp.zeros(n, dtype=wp.vec3, device=d)
        self.released = wp.zeros(n, dtype=int, device=d)
        self.impulse = wp.zeros(n, dtype=float, device=d)  # last step's normal impulse [N s] (its friction)
        self._signature = None
        self.shapes = wp.zeros(1, dtype=KCC.ContactShape, device=d)
        self._radius = float(model.particle_radius.numpy().max(initial=0.0))  # read once: no sync per step
        self.shape_count = 0
        self.refresh()

    def refresh(self) -> None:
        """Read the colliders again (outside a capture only; a captured step reads the shapes'
        array as it is at replay)."""
        if wp.get_device(self.device).is_capturing:
            return
        shapes = constraint_shapes(self.colliders, self._radius)
        sig = _signature(shapes)
        if sig == self._signature:
            return
        self._signature = sig
        self.shape_count = len(shapes)
        if shapes:
            self.shapes = wp.array(shapes, dtype=KCC.ContactShape, device=self.device)

    @property
    def active(self) -> bool:
        """True when some collider becomes a constraint."""
        return self.shape_count > 0

    def filter(self, q, qd, h, rhs, inverse) -> None:
        """Find the constraints at (q, qd) and filter the assembled system (``self.A``, ``rhs``,
        ``inverse``) of a step of ``h`` [s] in place; keeps the unfiltered A and b for :meth:`finish`."""
        d, n = self.device, self.n
        m = self.model
        wp.launch(KCC.find_contact_constraints, n,
                  inputs=[self.shapes, q, qd, m.particle_radius, m.particle_inv_mass, self.released, float(h)],
                  outputs=[self.normal, self.friction, self.z], device=d)
        wp.copy(self.A_plain.values, self.A.values)
        wp.copy(self.rhs_plain, rhs)
        wps.bsr_mv(self.A_plain, self.z, self.product, alpha=1.0, beta=0.0)
        wp.launch(KCC.filter_contact_system, n,
                  inputs=[self.A.offsets, self.A.columns, self.diagonal_slots, self.normal, self.friction, self.impulse,
                          qd, float(h), self.product],
                  outputs=[self.A.values, rhs, inverse], device=d)

    def finish(self, dv) -> None:
        """dv (the solved free part) += the prescribed part; release pulling contacts for the next
        step and keep the others' normal impulses (their friction in the next step)."""
        d, n = self.device, self.n
        wp.launch(KCC.add_prescribed, n, inputs=[self.z], outputs=[dv], device=d)
        wps.bsr_mv(self.A_plain, dv, self.product, alpha=1.0, beta=0.0)
        wp.launch(KCC.finish_contact_step, n,
                  inputs=[self.normal, self.product, self.rhs_plain], outputs=[self.released, self.impulse], device=d)

    def constrained(self) -> np.ndarray:
        """Indices of the particles constrained in the last step (a host read-back)."""
        return np.flatnonzero(np.linalg.norm(self.normal.numpy(), axis=1) > 0.0)
