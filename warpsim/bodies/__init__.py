"""Bodies and what they touch: colliders (planes, boxes, spheres, capsules, quads, triangle meshes,
particle-particle contacts, keyframed motion), mass-spring soft bodies from triangle meshes, the
Utah teapot, dragging a particle with the mouse or a script, and host mesh helpers (``meshtools``).

Drives ``warpsim.kernels.collide`` and ``warpsim.kernels.interaction``.
Entry classes: Plane, Box, Sphere, TriangleMesh, ParticleCollisions, add_soft_body, teapot_mesh, DragSpring.
"""

from .colliders import (
    Box, Capsule, Collider, ParticleCollisions, Plane, Planes, Quad, Rectangle, Sphere, TriangleMesh, keyframe_motion,
)
from .drag import DragSpring, pick_particle
from .softbody import SoftBody, add_soft_body, load_mesh
from .teapot import teapot_mesh

__all__ = [
    "Collider", "Planes", "Plane", "Box", "Sphere", "Capsule", "Quad", "Rectangle", "TriangleMesh",
    "ParticleCollisions", "keyframe_motion", "DragSpring", "pick_particle", "SoftBody", "add_soft_body", "load_mesh",
    "teapot_mesh",
]
