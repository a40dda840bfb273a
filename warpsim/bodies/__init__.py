"""Bodies and what they touch: colliders (planes, boxes, spheres, capsules, quads, triangle meshes,
particle-particle contacts, keyframed motion), mass-spring soft bodies from triangle meshes, the
Utah teapot, dragging a particle with the mouse or a script, and host mesh helpers (``meshtools``).

Drives ``warpsim.kernels.collide``, ``warpsim.kernels.interaction`` and ``warpsim.kernels.soft_contact``
(soft body against soft body: ``SoftContact``, its implicit penalty ``SoftContactForce`` in
``soft_contact_force``; ``shapes``: ``torus_mesh`` makes the lecture's donuts, ``icosphere`` the hair's
head and the viewer's spheres), and
``warpsim.kernels.vbd`` / ``vbd_contact`` (``VBD``: backward Euler by vertex block descent with contact
inside the descent, ``VBDContact``).
Entry classes: Plane, Box, Sphere, TriangleMesh, ParticleCollisions, SoftContact, add_soft_body, teapot_mesh,
DragSpring, VBD, VBDContact.
"""

from typing import TYPE_CHECKING

from .._lazy import lazy_attributes
from .colliders import (
    Box, Capsule, Collider, ParticleCollisions, Plane, Planes, Quad, Rectangle, Sphere, TriangleMesh, keyframe_motion,
)
from .drag import DragSpring, pick_particle
from .softbody import SoftBody, add_soft_body, load_mesh
from .teapot import teapot_mesh

if TYPE_CHECKING:  # imported on first use at run time (_LAZY)
    from .shapes import torus_mesh
    from .soft_contact import SoftContact
    from .vbd import VBD
    from .vbd_contact import VBDContact

__all__ = [
    "Collider", "Planes", "Plane", "Box", "Sphere", "Capsule", "Quad", "Rectangle", "TriangleMesh",
    "ParticleCollisions", "keyframe_motion", "DragSpring", "pick_particle", "SoftBody", "add_soft_body", "load_mesh",
    "teapot_mesh", "SoftContact", "torus_mesh", "VBD", "VBDContact",
]

_LAZY = {"SoftContact": ".soft_contact", "VBD": ".vbd", "VBDContact": ".vbd_contact", "torus_mesh": ".shapes"}
"""Names imported on first use (soft-soft contact and vertex block descent define many kernels that
a scene of springs or a teapot never launches)."""


__getattr__ = lazy_attributes(__name__, _LAZY, globals())
