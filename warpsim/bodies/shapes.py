"""Parametric closed meshes for soft bodies: the torus ("donut") of the mass-spring lecture."""

from __future__ import annotations

import numpy as np

from . import meshtools


def torus_mesh(major_radius: float = 0.1, minor_radius: float = 0.04, segments: int = 24,
               sides: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """A closed torus lying in the XZ plane (axis +Y), centred at the origin.

    ``major_radius`` [m]: centre of the tube to the axis; ``minor_radius`` [m]: tube radius;
    ``segments`` around the axis, ``sides`` around the tube (segments x sides vertices, twice as
    many triangles, wound outward). Returns (points (V, 3) float64, faces (F, 3) int64)."""
    major_radius, minor_radius = float(major_radius), float(minor_radius)
    if not (np.isfinite(major_radius) and np.isfinite(minor_radius) and 0.0 < minor_radius < major_radius):
        raise ValueError(f"torus radii major={major_radius}, minor={minor_radius}: need 0 < minor < major [m]")
    segments, sides = int(segments), int(sides)
    if segments < 3 or sides < 3:
        raise ValueError(f"torus segments={segments}, sides={sides}: each must be >= 3")
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
