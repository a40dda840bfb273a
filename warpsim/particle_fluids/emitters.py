"""Where liquid enters and leaves: :class:`Nozzle` (a jet emitting lattice layers at rest
density) and :class:`Sink` (a box that removes particles)."""

from __future__ import annotations

import math

import numpy as np

from ..core import checks


class Nozzle:
    """Circular nozzle emitting a jet over time.

    Args:
        center: nozzle centre [m]; direction: jet direction (normalised here); radius [m];
        speed: jet speed [m/s] > 0; start, stop: emission window [s].

    A layer of particles (a disc lattice at the fluid's spacing, perpendicular to ``direction``)
    is emitted each time the jet has advanced one spacing, so the stream has rest density.
    """

    def __init__(self, center, direction=(0.0, -1.0, 0.0), radius=0.05, speed=1.0, start=0.0, stop=math.inf):
        self.center = np.array(checks.vec3(center, "Nozzle center"))
        d = np.array(checks.vec3(direction, "Nozzle direction"))
        if np.linalg.norm(d) == 0.0:
            raise ValueError("Nozzle direction must be a non-zero vector")
        self.direction = d / np.linalg.norm(d)
        self.radius = float(radius)
        if not (math.isfinite(self.radius) and self.radius > 0.0):
            raise ValueError(f"Nozzle radius must be > 0 [m], got {radius}")
        self.speed = float(speed)
        if not (math.isfinite(self.speed) and self.speed > 0.0):
            raise ValueError(f"Nozzle speed must be > 0 [m/s], got {speed}")
        self.start, self.stop = float(start), float(stop)
        if not self.stop > self.start:
            raise ValueError(f"Nozzle stop {stop} must be after start {start}")
        self.travel = 0.0
        """Distance [m] the fluid has moved out of the nozzle since its last layer (checkpointed)."""
        self.emitted = 0
        """Particles emitted so far."""

    def layer_offsets(self, spacing: float) -> np.ndarray:
        """Offsets (K, 3) [m] of one emitted layer from the nozzle centre."""
        helper = np.array([1.0, 0.0, 0.0]) if abs(self.direction[0]) < 0.9 else np.array([0.0, 0.0, 1.0])
        u = np.cross(self.direction, helper)
        u /= np.linalg.norm(u)
        w = np.cross(self.direction, u)
        m = int(math.ceil(self.radius / spacing))
        a = (np.arange(-m, m + 1)) * spacing
        aa, bb = np.meshgrid(a, a, indexing="ij")
        keep = aa**2 + bb**2 <= self.radius**2 + 1e-12
        if not keep.any():
            keep[m, m] = True
        return aa[keep][:, None] * u + bb[keep][:, None] * w

    def layers_due(self, time: float, dt: float, spacing: float) -> list:
        """Shifts [m] along ``direction`` of the layers to emit during (time, time + dt]."""
        t0, t1 = max(time, self.start), min(time + dt, self.stop)
        if t1 <= t0:
            return []
        self.travel += self.speed * (t1 - t0)
        shifts = []
        while self.travel >= spacing * (1.0 - 1e-9):
            self.travel = max(self.travel, spacing)
            self.travel -= spacing
            shifts.append(self.travel)
        return shifts


class Sink:
    """Outflow region: particles inside the box [lower, upper] [m] are removed (once per frame)."""

    def __init__(self, lower, upper):
        self.lower = np.array(checks.vec3(lower, "Sink lower"))
        self.upper = np.array(checks.vec3(upper, "Sink upper"))
        if np.any(self.upper <= self.lower):
            raise ValueError(f"Sink upper {tuple(self.upper)} must exceed lower {tuple(self.lower)} on every axis")
        self.removed = 0
        """Particles removed so far."""
