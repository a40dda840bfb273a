"""Boundaries of a particle fluid: option checks and the world-space geometry (planes,
capsules/spheres, triangle meshes) of the warpsim colliders the fluid treats as static solids."""

from __future__ import annotations

import math

import numpy as np

from ..core import checks


def positive_value(name, value, allow_zero=False):
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(v) or v < 0.0 or (v == 0.0 and not allow_zero):
        raise ValueError(f"{name} must be {'>= 0' if allow_zero else '> 0'} and finite, got {value!r}")
    return v


def collider_geometry(k, c):
    """Boundary geometry of a warpsim collider, in world space at its current pose:
    ('planes', normals (P, 3), offsets (P,)), ('capsule', a, b, radius, sign) (a sphere has
    a == b; sign -1 for a hollow container) or ('mesh', points (V, 3), faces (F, 3), solid,
    thickness). Duck-typed so every warpsim collider shape works: Plane/Planes/Box, Sphere,
    Capsule, Quad and TriangleMesh."""
    name = f"colliders[{k}] ({type(c).__name__})"
    thickness = float(getattr(c, "thickness", 0.0) or 0.0)
    if hasattr(c, "normals") and hasattr(c, "offsets"):
        normals = np.asarray(c.normals, np.float64).reshape(-1, 3)
        offsets = np.asarray(c.offsets, np.float64).reshape(-1) + thickness
        return ("planes", normals, offsets)
    if hasattr(c, "radius") and (hasattr(c, "center") or (hasattr(c, "a") and hasattr(c, "b"))):
        r = float(c.radius) + thickness
        if not (math.isfinite(r) and r > 0.0):
            raise ValueError(f"{name}: radius {c.radius} must be > 0 [m]")
        if hasattr(c, "a") and hasattr(c, "b"):
            a, b = np.array(checks.vec3(c.a, f"{name} a")), np.array(checks.vec3(c.b, f"{name} b"))
        else:
            a = b = np.array(checks.vec3(c.center, f"{name} center"))
        return ("capsule", a, b, r, -1.0 if getattr(c, "inside", False) else 1.0)
    if hasattr(c, "corners") and callable(c.corners):
        pts = np.asarray(c.corners(), np.float64).reshape(-1, 3)
        return ("mesh", pts, np.array([[0, 1, 2], [0, 2, 3]]), 0, thickness)
    if hasattr(c, "faces") and (hasattr(c, "world_points") or hasattr(c, "points")):
        pts = c.world_points() if hasattr(c, "world_points") else c.points
        pts = np.asarray(pts, np.float64).reshape(-1, 3)
        faces = np.asarray(c.faces).reshape(-1, 3)
        if len(faces) == 0 or faces.min() < 0 or faces.max() >= len(pts):
            raise ValueError(f"{name}: faces must index its {len(pts)} points and hold at least one triangle")
        return ("mesh", pts, faces, int(bool(getattr(c, "solid", False))), thickness)
    raise ValueError(f"{name} is not a boundary the fluid understands: give planes (ws.Plane, ws.Planes, "
                     "ws.Box), spheres or capsules (center or a/b, radius), quads, or triangle meshes "
                     "(points/world_points() and faces)")
