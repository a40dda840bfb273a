"""Per-world force and collider: gravity and plane walls whose coefficients differ by world.

Both read their world's values through ``model.particle_world`` (shape (particle_count,)) from
arrays of shape (world_count,), so one launch serves every world and the values can change
between frames (in place) without re-capturing a graph.
"""
from __future__ import annotations

import numpy as np
import warp as wp

from ..bodies.colliders import Planes, damping_ratio_for_restitution
from ..core.forces import Force
from ..kernels import collide as KC
from ..kernels import worlds as KW


class WorldGravity(Force):
    """f = m g_w: gravity [m/s^2] per world, ``g`` of shape (world_count, 3)."""

    def __init__(self, g):
        g = np.asarray(g, dtype=np.float64).reshape(-1, 3)
        if not np.isfinite(g).all():
            bad = int(np.flatnonzero(~np.isfinite(g).all(axis=1))[0])
            raise ValueError(f"WorldGravity: world {bad} has a non-finite gravity {g[bad]}; give finite values")
        self.g = g

    def bind(self, model):
        super().bind(model)
        if len(self.g) != model.world_count:
            raise ValueError(f"WorldGravity has {len(self.g)} gravity vectors for {model.world_count} worlds")
        self.world_gravity = wp.array(self.g.astype(np.float32), dtype=wp.vec3, device=model.device)

    def eval(self, q, qd, time, time_offset, f_out):
        m = self.model
        wp.launch(KW.eval_gravity_worlds, m.particle_count,
                  inputs=[m.particle_mass, m.particle_world, self.world_gravity, f_out], device=m.device)


class WorldPlanes(Planes):
    """A :class:`warpsim.Planes` (plane, box of walls) whose ``restitution`` and ``friction`` are
    per world: arrays of shape (world_count,). The penalty damping ratio follows each world's
    restitution; mode, thickness and stiffness are shared."""

    def __init__(self, planes: Planes, restitution, friction):
        r = np.asarray(restitution, dtype=np.float64).reshape(-1)
        mu = np.asarray(friction, dtype=np.float64).reshape(-1)
        super().__init__(planes.normals, planes.offsets, 0.5, 0.0, planes.mode_name, name=planes.name,
                         thickness=planes.thickness, stiffness=planes.stiffness)
        for w in range(len(r)):
            if not (np.isfinite(r[w]) and 0.0 <= r[w] <= 1.0):
                raise ValueError(f"{planes.name} restitution of world {w} is {r[w]}; it must be in [0, 1]")
            if not (np.isfinite(mu[w]) and mu[w] >= 0.0):
                raise ValueError(f"{planes.name} friction of world {w} is {mu[w]}; it must be >= 0")
        self.world_restitution_values = r
        self.world_friction_values = mu
        for attr in ("lower", "upper"):
            if hasattr(planes, attr):
                setattr(self, attr, getattr(planes, attr))

    def bind(self, model):
        super().bind(model)
        if len(self.world_restitution_values) != model.world_count:
            raise ValueError(f"{self.name}: {len(self.world_restitution_values)} restitutions for "
                             f"{model.world_count} worlds")
        d = model.device
        r = self.world_restitution_values
        self.world_restitution = wp.array(r.astype(np.float32), dtype=float, device=d)
        self.world_friction = wp.array(self.world_friction_values.astype(np.float32), dtype=float, device=d)
        zeta = np.array([damping_ratio_for_restitution(float(x)) for x in r], dtype=np.float32)
        self.world_damping_ratio = wp.array(zeta, dtype=float, device=d)

    def apply(self, model, state, q_prev, dt):
        wp.launch(
            KC.collide_planes_worlds, model.particle_count,
            inputs=[model.particle_inv_mass, model.particle_radius, model.particle_world, self._normals,
                    self._offsets, self.world_restitution, self.world_friction, self.world_damping_ratio,
                    self.mode, self.thickness, self.stiffness, float(dt), q_prev, state.forces, state.positions,
                    state.velocities],
            device=model.device,
        )
