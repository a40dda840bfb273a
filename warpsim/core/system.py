"""Dynamic systems: what an integrator sees.

A system has ``count`` coordinates of type ``dtype`` (``wp.vec3`` for particles, ``float`` for
angle-form systems), per-coordinate ``mass`` / ``inv_mass`` arrays, and evaluates generalised
forces and, for implicit Euler, force Jacobians. The same five integrators drive every system.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import warp as wp

from .forces import Force, Springs
from ..kernels import forces as K


class DynamicSystem:
    """Interface shared by all systems (see module docstring)."""

    device: Any = None
    dtype: Any = wp.vec3
    block_type: Any = wp.mat33
    count = 0
    mass: wp.array
    inv_mass: wp.array

    def eval_forces(self, q, qd, time, time_offset: float, f_out) -> None:
        """Overwrite ``f_out`` with the total force at (q, qd, time[0] + time_offset)."""
        raise NotImplementedError

    def jacobian_triplet_count(self) -> int:
        return 0

    def eval_jacobians(self, q, qd, time, time_offset, ck, cd, diag, rows, cols, values) -> None:
        """Overwrite ``diag`` (count,) with the diagonal blocks of ck df/dx + cd df/dv and fill the
        coupling triplets (length jacobian_triplet_count())."""
        raise NotImplementedError


class ParticleSystem(DynamicSystem):
    """Particles of a Model under a list of forces (springs of the model included)."""

    def __init__(self, model, forces):
        self.model = model
        self.device = model.device
        self.count = model.particle_count
        self.mass = model.particle_mass
        self.inv_mass = model.particle_inv_mass
        forces = list(forces)
        for k, f in enumerate(forces):
            if not isinstance(f, Force):
                raise ValueError(f"forces[{k}] is {type(f).__name__}, not a warpsim Force (e.g. ws.Gravity())")
        if model.spring_count and not any(isinstance(f, Springs) for f in forces):
            forces.append(Springs())
        for f in forces:
            f.bind(model)
        self.forces = forces
        counts = [f.jacobian_triplet_count() for f in forces]
        self._offsets = np.concatenate([[0], np.cumsum(counts)]).astype(int)

    def eval_forces(self, q, qd, time, time_offset, f_out) -> None:
        f_out.zero_()
        for f in self.forces:
            f.eval(q, qd, time, time_offset, f_out)

    def add_force(self, force) -> None:
        """Bind ``force`` to the model and add it after the others (the caller re-prepares its
        integrator: see ``Simulator.add_force``)."""
        if not isinstance(force, Force):
            raise ValueError(f"add_force: {type(force).__name__} is not a warpsim Force (e.g. ws.DragSpring())")
        force.bind(self.model)
        self.forces.append(force)
        self._offsets = np.append(self._offsets, self._offsets[-1] + force.jacobian_triplet_count())

    def jacobian_triplet_count(self) -> int:
        return int(self._offsets[-1])

    def eval_jacobians(self, q, qd, time, time_offset, ck, cd, diag, rows, cols, values) -> None:
        diag.zero_()
        for k, f in enumerate(self.forces):
            a, b = self._offsets[k], self._offsets[k + 1]
            if b > a:
                f.eval_jacobian(q, qd, time, time_offset, ck, cd, diag, rows[a:b], cols[a:b], values[a:b])
            else:
                f.eval_jacobian(q, qd, time, time_offset, ck, cd, diag, None, None, None)


class PendulumSystem(DynamicSystem):
    """A batch of angle-form pendulums q'' = -(g / l) sin q; coordinates are angles [rad]."""

    dtype = float
    block_type = float

    def __init__(self, length, gravity: float, device):
        self.device = wp.get_device(device)
        length = np.asarray(length, dtype=np.float32).reshape(-1)
        self.count = len(length)
        self.g_over_l = wp.array(gravity / length, dtype=float, device=self.device)
        self.mass = wp.ones(self.count, dtype=float, device=self.device)
        self.inv_mass = wp.ones(self.count, dtype=float, device=self.device)

    def eval_forces(self, q, qd, time, time_offset, f_out) -> None:
        f_out.zero_()
        wp.launch(K.eval_pendulum, self.count, inputs=[q, self.g_over_l, f_out], device=self.device)

    def eval_jacobians(self, q, qd, time, time_offset, ck, cd, diag, rows, cols, values) -> None:
        diag.zero_()
        wp.launch(K.eval_pendulum_jacobian, self.count, inputs=[q, self.g_over_l, float(ck), diag], device=self.device)
