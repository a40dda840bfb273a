"""Colliders: run after integration, they correct the new positions and velocities in place."""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from .builder import _vec3
from .kernels import collide as K

MODES = {"reflect": 0, "project": 1}


class Collider:
    """Base class: ``bind(model)`` once, then ``apply(model, state, q_prev, dt)`` after every
    integration step (``q_prev``: positions at the start of the step, for continuous detection)."""

    def bind(self, model) -> None:
        self.model = model

    def apply(self, model, state, q_prev, dt: float) -> None:
        raise NotImplementedError


def _coefficients(owner: str, restitution, friction, mode):
    r, mu = float(restitution), float(friction)
    if not (math.isfinite(r) and 0.0 <= r <= 1.0):
        raise ValueError(f"{owner} restitution {restitution} must be in [0, 1]")
    if not (math.isfinite(mu) and mu >= 0.0):
        raise ValueError(f"{owner} friction {friction} must be >= 0")
    if mode not in MODES:
        raise ValueError(f"{owner} mode {mode!r} is unknown; use one of {sorted(MODES)}")
    return r, mu, MODES[mode]


class Planes(Collider):
    """A set of half-spaces n . x >= offset + radius resolved together (one kernel launch).

    normals: (P, 3), normalised here; offsets: (P,) [m]. Restitution e in [0, 1]: the normal
    velocity becomes -e v_n and, in ``mode="reflect"``, the penetration depth h becomes e h on
    the free side; ``mode="project"`` places the particle on the plane (position correction).
    Coulomb friction ``friction`` removes at most mu (1 + e) |v_n| of tangential speed."""

    def __init__(self, normals, offsets, restitution=0.5, friction=0.0, mode="reflect", name="Planes"):
        normals = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
        offsets = np.asarray(offsets, dtype=np.float64).reshape(-1)
        if len(normals) != len(offsets):
            raise ValueError(f"{name}: {len(normals)} normals but {len(offsets)} offsets")
        lengths = np.linalg.norm(normals, axis=1)
        if np.any(~np.isfinite(lengths)) or np.any(lengths == 0.0) or np.any(~np.isfinite(offsets)):
            raise ValueError(f"{name}: every normal must be a finite non-zero vector and every offset finite")
        self.normals = normals / lengths[:, None]
        self.offsets = offsets
        self.restitution, self.friction, self.mode = _coefficients(name, restitution, friction, mode)

    def bind(self, model):
        super().bind(model)
        self._normals = wp.array(self.normals.astype(np.float32), dtype=wp.vec3, device=model.device)
        self._offsets = wp.array(self.offsets.astype(np.float32), dtype=float, device=model.device)

    def apply(self, model, state, q_prev, dt):
        wp.launch(
            K.collide_planes, model.particle_count,
            inputs=[model.particle_inv_mass, model.particle_radius, self._normals, self._offsets, self.restitution,
                    self.friction, self.mode, state.positions, state.velocities],
            device=model.device,
        )


class Plane(Planes):
    """The infinite plane n . x = offset; particles stay on the side ``normal`` points to."""

    def __init__(self, normal=(0.0, 1.0, 0.0), offset=0.0, restitution=0.5, friction=0.0, mode="reflect"):
        super().__init__([_vec3(normal, "Plane normal")], [offset], restitution, friction, mode, name="Plane")


class Box(Planes):
    """An axis-aligned box of six walls that keeps particles inside [lower, upper] [m]."""

    def __init__(self, lower=(-1.0, 0.0, -1.0), upper=(1.0, 2.0, 1.0), restitution=0.5, friction=0.0, mode="reflect"):
        lo, hi = np.array(_vec3(lower, "Box lower")), np.array(_vec3(upper, "Box upper"))
        if np.any(hi <= lo):
            raise ValueError(f"Box upper {tuple(hi)} must exceed lower {tuple(lo)} on every axis")
        eye = np.eye(3)
        normals = np.concatenate([eye, -eye])
        offsets = np.concatenate([lo, -hi])
        super().__init__(normals, offsets, restitution, friction, mode, name="Box")
        self.lower, self.upper = tuple(lo), tuple(hi)
