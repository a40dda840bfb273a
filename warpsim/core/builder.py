"""ModelBuilder: collects particles and springs on the host, validates them, and finalizes a Model."""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np
import warp as wp

from .model import Model


def _vec3(value, what: str) -> tuple:
    try:
        v = tuple(float(c) for c in value)
    except TypeError as exc:
        raise ValueError(f"{what} must be a sequence of 3 numbers, got {value!r}") from exc
    if len(v) != 3:
        raise ValueError(f"{what} must have 3 components, got {len(v)}")
    if not all(math.isfinite(c) for c in v):
        raise ValueError(f"{what} is not finite: {v}; give finite coordinates")
    return v


class ModelBuilder:
    """Builds particle systems with damped springs.

    Example::

        builder = ws.ModelBuilder()
        a = builder.add_particle((0, 1, 0), mass=0.0)      # pinned
        b = builder.add_particle((0, 0, 0), mass=1.0)
        builder.add_spring(a, b, stiffness=100.0, damping=1.0)
        model = builder.finalize(device="cpu")
    """

    def __init__(self):
        self.particle_q: list[tuple] = []
        self.particle_qd: list[tuple] = []
        self.particle_mass: list[float] = []
        self.particle_radius: list[float] = []
        self.spring_indices: list[tuple[int, int]] = []
        self.spring_rest_length: list[float] = []
        self.spring_stiffness: list[float] = []
        self.spring_damping: list[float] = []

    @property
    def particle_count(self) -> int:
        return len(self.particle_q)

    @property
    def spring_count(self) -> int:
        return len(self.spring_indices)

    def add_particle(self, pos, vel=(0.0, 0.0, 0.0), mass: float = 1.0, radius: float = 0.0) -> int:
        """Add a particle at ``pos`` [m] with velocity ``vel`` [m/s], ``mass`` [kg] (0 = pinned or
        kinematic: forces never move it) and collision ``radius`` [m]. Returns its index."""
        index = self.particle_count
        pos = _vec3(pos, f"particle {index} position")
        vel = _vec3(vel, f"particle {index} velocity")
        mass = float(mass)
        if not math.isfinite(mass) or mass < 0.0:
            raise ValueError(f"particle {index} has mass {mass}; mass must be finite and >= 0 (0 pins it)")
        radius = float(radius)
        if not math.isfinite(radius) or radius < 0.0:
            raise ValueError(f"particle {index} has radius {radius}; radius must be finite and >= 0")
        self.particle_q.append(pos)
        self.particle_qd.append(vel)
        self.particle_mass.append(mass)
        self.particle_radius.append(radius)
        return index

    def add_particles(self, positions, velocities=None, masses=1.0, radii=0.0) -> np.ndarray:
        """Add many particles at once; ``positions`` (N, 3). Returns their indices, shape (N,)."""
        positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        n = len(positions)
        velocities = np.zeros((n, 3)) if velocities is None else np.asarray(velocities, dtype=np.float64).reshape(n, 3)
        masses = np.broadcast_to(np.asarray(masses, dtype=np.float64), (n,))
        radii = np.broadcast_to(np.asarray(radii, dtype=np.float64), (n,))
        return np.array(
            [self.add_particle(positions[k], velocities[k], masses[k], radii[k]) for k in range(n)], dtype=np.int64
        )

    def add_spring(self, i: int, j: int, stiffness: float, damping: float = 0.0, rest_length: float | None = None) -> int:
        """Join particles ``i`` and ``j`` with a damped spring: stiffness [N/m], damping [N s/m],
        rest length [m] (default: their current distance). Returns the spring index."""
        index = self.spring_count
        n = self.particle_count
        for name, p in (("i", i), ("j", j)):
            if not isinstance(p, (int, np.integer)) or p < 0 or p >= n:
                raise ValueError(f"spring {index}: particle {name}={p!r} is out of range [0, {n}); add the particle first")
        if i == j:
            raise ValueError(f"spring {index} joins particle {i} to itself; join two different particles")
        for name, value in (("stiffness", stiffness), ("damping", damping)):
            if not math.isfinite(float(value)) or float(value) < 0.0:
                raise ValueError(f"spring {index} has {name} {value}; it must be finite and >= 0")
        if rest_length is None:
            rest_length = float(np.linalg.norm(np.subtract(self.particle_q[i], self.particle_q[j])))
        elif not math.isfinite(float(rest_length)) or float(rest_length) < 0.0:
            raise ValueError(f"spring {index} has rest length {rest_length}; it must be finite and >= 0")
        self.spring_indices.append((int(i), int(j)))
        self.spring_rest_length.append(float(rest_length))
        self.spring_stiffness.append(float(stiffness))
        self.spring_damping.append(float(damping))
        return index

    def finalize(self, device=None) -> Model:
        """Copy everything to ``device`` (None: Warp's preferred device) and return the Model."""
        model = Model(device)
        d = model.device
        n = self.particle_count
        mass = np.array(self.particle_mass, dtype=np.float32).reshape(n)
        inv_mass = np.zeros_like(mass)
        inv_mass[mass > 0.0] = 1.0 / mass[mass > 0.0]
        model.particle_count = n
        model.particle_q = wp.array(np.array(self.particle_q, dtype=np.float32).reshape(n, 3), dtype=wp.vec3, device=d)
        model.particle_qd = wp.array(np.array(self.particle_qd, dtype=np.float32).reshape(n, 3), dtype=wp.vec3, device=d)
        model.particle_mass = wp.array(mass, dtype=float, device=d)
        model.particle_inv_mass = wp.array(inv_mass, dtype=float, device=d)
        model.particle_radius = wp.array(np.array(self.particle_radius, dtype=np.float32).reshape(n), dtype=float, device=d)
        m = self.spring_count
        model.spring_count = m
        model.spring_indices = wp.array(np.array(self.spring_indices, dtype=np.int32).reshape(2 * m), dtype=int, device=d)
        model.spring_rest_length = wp.array(np.array(self.spring_rest_length, dtype=np.float32), dtype=float, device=d)
        model.spring_stiffness = wp.array(np.array(self.spring_stiffness, dtype=np.float32), dtype=float, device=d)
        model.spring_damping = wp.array(np.array(self.spring_damping, dtype=np.float32), dtype=float, device=d)
        return model


def check_indices(indices: Sequence[int], count: int, what: str) -> np.ndarray:
    """Validate particle indices for a force or collider; returns them as int32."""
    idx = np.asarray(indices, dtype=np.int64).reshape(-1)
    bad = idx[(idx < 0) | (idx >= count)]
    if len(bad):
        raise ValueError(f"{what}: particle index {int(bad[0])} is out of range [0, {count})")
    return idx.astype(np.int32)
