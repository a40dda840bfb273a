"""Parametric closed meshes: the torus ("donut") of the mass-spring lecture, for soft bodies, and
the icosphere (the hair scene's head, the viewer's spheres; ``warpsim.viewer.geometry`` re-exports it)."""

from __future__ import annotations

import math

import numpy as np

from . import meshtools

MAX_TORUS_RING = 4096
"""Most segments (or sides) a torus takes: 4096 x 4096 is 16.7 million vertices."""


def torus_mesh(major_radius: float = 0.1, minor_radius: float = 0.04, segments: int = 24,
               sides: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """A closed torus lying in the XZ plane (axis +Y), centred at the origin.

    ``major_radius`` [m]: centre of the tube to the axis; ``minor_radius`` [m]: tube radius;
    ``segments`` around the axis, ``sides`` around the tube (segments x sides vertices, twice as
    many triangles, wound outward). Returns (points (V, 3) float64, faces (F, 3) int64)."""
    from ..core import checks

    major_radius = checks.positive(major_radius, "torus_mesh major_radius", unit="m", fix="e.g. 0.1")
    minor_radius = checks.positive(minor_radius, "torus_mesh minor_radius", unit="m", fix="e.g. 0.04")
    if not minor_radius < major_radius:
        raise ValueError(f"torus radii major={major_radius}, minor={minor_radius}: need 0 < minor < major [m]")
    segments = checks.integer(segments, "torus_mesh segments", lo=3, hi=MAX_TORUS_RING, fix="e.g. 24")
    sides = checks.integer(sides, "torus_mesh sides", lo=3, hi=MAX_TORUS_RING, fix="e.g. 12")
    u = 2.0 * np.pi * np.arange(segments) / segments
    v = 2.0 * np.pi * np.arange(sides) / sides
    uu, vv = np.meshgrid(u, v, indexing="ij")
    ring = major_radius + minor_radius * np.cos(vv)
    points = np.stack([ring * np.cos(uu), minor_radius * np.sin(vv), ring * np.sin(uu)], -1).reshape(-1, 3)
    a = np.arange(segments)[:, None] * sides + np.arange(sides)[None, :]
    b = ((np.arange(segments)[:, None] + 1) % segments) * sides + np.arange(sides)[None, :]
    c = ((np.arange(segments)[:, None] + 1) % segments) * sides + (np.arange(sides)[None, :] + 1) % sides
    e = np.arange(segments)[:, None] * sides + (np.arange(sides)[None, :] + 1) % sides
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, e], -1).reshape(-1, 3)])
    if meshtools.signed_volume(points, faces) < 0.0:
        faces = faces[:, ::-1].copy()
    return points, faces.astype(np.int64)


def icosphere(subdivisions=1):
    """Unit sphere: (vertices (V, 3) float32, triangles (T, 3) uint32), outward winding."""
    t = (1.0 + math.sqrt(5.0)) / 2.0
    v = [(-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0), (0, -1, t), (0, 1, t), (0, -1, -t), (0, 1, -t),
         (t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1)]
    f = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4), (11, 10, 2),
         (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8), (3, 8, 9), (4, 9, 5), (2, 4, 11),
         (6, 2, 10), (8, 6, 7), (9, 8, 1)]
    verts = [np.array(p, float) / np.linalg.norm(p) for p in v]
    for _ in range(int(subdivisions)):
        cache, out = {}, []

        def mid(a, b, cache=cache):
            key = (min(a, b), max(a, b))
            if key not in cache:
                m = verts[a] + verts[b]
                verts.append(m / np.linalg.norm(m))
                cache[key] = len(verts) - 1
            return cache[key]

        for a, b, c in f:
            ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
            out += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        f = out
    return np.array(verts, np.float32), np.array(f, np.uint32)
