"""Pinhole cameras for the preview renderer: explicit (eye, target) or framing given bounds.

A camera looks from ``eye`` [m] at ``target`` [m] with +Y up and a vertical field of view
``fov`` [degrees]. :func:`frame_bounds` places the eye in front of, above and to the right of a
box so that the box's bounding sphere fits the picture.
"""
from __future__ import annotations

import math

import numpy as np

DEFAULT_FOV = 40.0
DEFAULT_VIEW = (0.45, 0.5, 1.0)  # direction from the target towards the eye (front, above, right)


class Camera:
    """``eye``, ``target`` (3-vectors [m]), vertical field of view ``fov`` [degrees] in (0, 180)."""

    def __init__(self, eye, target, fov=DEFAULT_FOV):
        eye = np.asarray(eye, np.float64).reshape(-1)
        target = np.asarray(target, np.float64).reshape(-1)
        if eye.shape != (3,) or target.shape != (3,) or not (np.isfinite(eye).all() and np.isfinite(target).all()):
            raise ValueError(f"camera eye {eye.tolist()} and target {target.tolist()} must be finite 3-vectors, "
                             "e.g. --camera 2,1.5,3,0,0.3,0")
        if np.linalg.norm(target - eye) < 1e-9:
            raise ValueError(f"camera eye and target are the same point {eye.tolist()}; give a target apart from "
                             "the eye, e.g. --camera 2,1.5,3,0,0.3,0")
        if not 0.0 < fov < 180.0:
            raise ValueError(f"camera field of view {fov} degrees must lie in (0, 180)")
        self.eye, self.target, self.fov = eye, target, float(fov)

    def basis(self):
        """(forward, right, up) unit vectors; a camera looking straight up or down keeps +Z as 'up'."""
        f = self.target - self.eye
        f /= np.linalg.norm(f)
        world_up = np.array([0.0, 1.0, 0.0]) if abs(f[1]) < 0.999 else np.array([0.0, 0.0, -1.0])
        r = np.cross(f, world_up)
        r /= np.linalg.norm(r)
        return f, r, np.cross(r, f)

    def tangents(self, width, height):
        """(tan_x, tan_y): half-extent of the image plane at unit distance, across and up."""
        ty = math.tan(math.radians(0.5 * self.fov))
        return ty * width / height, ty

    def project(self, points, width, height):
        """Pixel coordinates (n, 2) (column, row; continuous, 0 at the image's top-left corner)
        and depths (n,) [m] of world points (n, 3)."""
        f, r, u = self.basis()
        tx, ty = self.tangents(width, height)
        q = np.asarray(points, np.float64).reshape(-1, 3) - self.eye
        z = q @ f
        col = (q @ r / (z * tx) + 1.0) * 0.5 * width
        row = (1.0 - q @ u / (z * ty)) * 0.5 * height
        return np.stack([col, row], 1), z

    def __repr__(self):
        return f"Camera(eye={self.eye.round(4).tolist()}, target={self.target.round(4).tolist()}, fov={self.fov:g})"


def parse_camera(text, fov=DEFAULT_FOV):
    """Camera from ``"ex,ey,ez,tx,ty,tz"``; ValueError naming the text and the expected form."""
    try:
        values = [float(v) for v in str(text).split(",")]
    except ValueError:
        values = []
    if len(values) != 6 or not np.isfinite(values).all():
        raise ValueError(f"--camera {text!r} must be six numbers eye_x,eye_y,eye_z,target_x,target_y,target_z, "
                         "e.g. --camera 2,1.5,3,0,0.3,0")
    return Camera(values[:3], values[3:], fov)


def frame_bounds(bounds, width, height, fov=DEFAULT_FOV, view=DEFAULT_VIEW, margin=1.05):
    """Camera looking at the centre of ``bounds`` [[lo], [hi]] along ``-view`` from far enough that
    the bounding sphere (radius times ``margin``) fits the narrower field of view."""
    lo, hi = np.asarray(bounds, np.float64)
    if not (np.isfinite(lo).all() and np.isfinite(hi).all()):
        raise ValueError(f"cannot frame non-finite bounds {lo.tolist()} .. {hi.tolist()}")
    centre = 0.5 * (lo + hi)
    radius = max(0.5 * float(np.linalg.norm(hi - lo)), 1e-3) * margin
    half = math.radians(0.5 * fov)
    half = min(half, math.atan(math.tan(half) * width / height))
    dist = radius / math.sin(half)
    v = np.asarray(view, np.float64)
    return Camera(centre + dist * v / np.linalg.norm(v), centre, fov)
