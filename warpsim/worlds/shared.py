"""The shared-topology path of a :class:`warpsim.worlds.WorldBatch`: mass-spring worlds whose
springs, adjacency and base parameters are stored once, stepped by one fused kernel per sub-step
(``kernels/world_step.py``), bit-identical to the tiled path and to the generic Simulator.

Eligible scenes (``eligibility``): a ``ws.Simulator`` with semi-implicit Euler, uniform gravity
(per world or shared) and the model's springs as the only forces, plane walls (``ws.Plane``,
``ws.Box``, ``ws.Planes``) as the only colliders, no breakable springs, fixed sub-steps.

Per world the device holds only the state (positions and velocities, twice: the step reads one
pair and writes the other), masses, inverse masses, radii and the per-world values; a teapot world
(538 particles, 5,238 springs) needs 57 kB instead of the tiled path's 215 kB.
"""
from __future__ import annotations

import numpy as np
import warp as wp

from ..bodies.colliders import Planes, damping_ratio_for_restitution
from ..core.forces import Gravity, Springs
from ..core.integrators import SemiImplicitEuler
from ..core.model import ensure_spring_adjacency
from ..core.simulator import Simulator
from ..kernels import world_step as K

SPRING_PARAMS = ("spring_rest_length", "spring_stiffness", "spring_damping")


def eligibility(sim0) -> str | None:
    """None when the scene's simulator ``sim0`` (world 0) can take the shared path, else why not."""
    if type(sim0) is not Simulator:
        return f"the scene steps with {type(sim0).__name__}, not ws.Simulator"
    if not isinstance(sim0.integrator, SemiImplicitEuler):
        return f"the integrator is {sim0.integrator.name}, not semi_implicit_euler"
    if getattr(sim0, "adaptive", False):
        return "adaptive sub-stepping"
    breakable = int(getattr(sim0.model, "breakable_spring_count", 0))
    if getattr(sim0, "fracture", None) is not None or breakable:
        return "breakable springs"
    if getattr(sim0, "rollout", None) is not None:
        return "a differentiable run"
    forces = list(sim0.forces)
    if not forces or type(forces[0]) is not Gravity:
        return "its first force is not uniform gravity"
    for f in forces[1:]:
        if type(f) is not Springs:
            return f"force {type(f).__name__} (only gravity and the model's springs are fused)"
    for c in sim0.colliders:
        if not isinstance(c, Planes) or getattr(c, "motion", None) is not None:
            return f"collider {type(c).__name__} (only plane walls are fused)"
    return None


class SharedStepper:
    """Steps the worlds of ``batch`` (a WorldBatch on the shared path) in place of its simulator:
    ``frame(frame_dt, substeps)`` runs the sub-steps, one launch each, and leaves the state in
    ``batch.sim.state`` (no allocation: a frame captures as a CUDA graph).

    ``scales``: {spring array name: (base (S,) host, key (S,) device int, coefficient (S,) device
    float)} and ``world_values`` (device, world_count K) as the tiling computed them."""

    def __init__(self, batch, m0, scales, world_values, key_count, gravity, walls):
        d = batch.device
        ensure_spring_adjacency(m0)
        s = K.SharedSprings()
        s.offsets, s.springs, s.ends = m0.particle_spring_offsets, m0.particle_springs, m0.spring_indices
        for name, field in zip(SPRING_PARAMS, ("rest", "stiffness", "damping")):
            base, key, coefficient = scales[name]
            setattr(s, f"{field}_base", wp.array(np.asarray(base, dtype=np.float32), dtype=float, device=d))
            setattr(s, f"{field}_key", key)
            setattr(s, f"{field}_coefficient", coefficient)
        s.world_values, s.key_count = world_values, int(key_count)
        self.springs = s
        self.world_gravity = wp.array(np.asarray(gravity, dtype=np.float32).reshape(-1, 3), dtype=wp.vec3, device=d)
        self.walls = walls
        self.batch = batch
        st = batch.sim.state
        self._home = (st.positions, st.velocities)
        self._spare = (wp.zeros_like(st.positions), wp.zeros_like(st.velocities))

    def step(self, h: float) -> None:
        """One sub-step of ``h`` [s]: (q, qd) -> the other buffer pair, which becomes the state."""
        b, st = self.batch, self.batch.sim.state
        m = b.model
        q_out = self._spare[0] if st.positions is self._home[0] else self._home[0]
        qd_out = self._spare[1] if st.velocities is self._home[1] else self._home[1]
        wp.launch(K.step_shared_worlds, m.particle_count,
                  inputs=[st.positions, st.velocities, m.particle_mass, m.particle_inv_mass, m.particle_radius,
                          self.world_gravity, m.world_particle_count, self.springs, self.walls, float(h), q_out,
                          qd_out], device=b.device)
        st.positions, st.velocities = q_out, qd_out

    def frame(self, frame_dt: float, substeps: int) -> None:
        h = frame_dt / substeps
        for _ in range(int(substeps)):
            self.step(h)
        st = self.batch.sim.state
        if st.positions is not self._home[0]:  # the frame ends in the state's own arrays
            wp.copy(self._home[0], st.positions)
            wp.copy(self._home[1], st.velocities)
            st.positions, st.velocities = self._home
        sim = self.batch.sim
        sim.time += frame_dt
        sim.step_count += int(substeps)

    def device_bytes(self) -> int:
        """Bytes of the shared arrays (stored once for all worlds) and the spare state pair."""
        arrays = [getattr(self.springs, name) for name in ("offsets", "springs", "ends", "rest_base", "rest_key",
                                                            "rest_coefficient", "stiffness_base", "stiffness_key",
                                                            "stiffness_coefficient", "damping_base", "damping_key",
                                                            "damping_coefficient", "world_values")]
        arrays += [*self._spare, self.world_gravity]
        return sum(a.size * wp.types.type_size_in_bytes(a.dtype) for a in arrays)


def world_walls(colliders, world_count, device) -> K.WorldWalls:
    """The WorldWalls of plane colliders (``ws.Planes`` or per-world ``WorldPlanes``), in order."""
    from .forces import WorldPlanes

    normals, offsets, owner, mode, thickness, stiffness, r, mu, zeta = [], [], [], [], [], [], [], [], []
    for c_index, c in enumerate(colliders):
        normals.append(np.asarray(c.normals, dtype=np.float64))
        offsets.append(np.asarray(c.offsets, dtype=np.float64))
        owner += [c_index] * len(c.offsets)
        mode.append(c.mode)
        thickness.append(c.thickness)
        stiffness.append(c.stiffness)
        if isinstance(c, WorldPlanes):
            rw = np.asarray(c.world_restitution_values, dtype=np.float64)
            r.append(rw)
            mu.append(np.asarray(c.world_friction_values, dtype=np.float64))
            zeta.append(np.array([damping_ratio_for_restitution(float(x)) for x in rw]))
        else:
            r.append(np.full(world_count, c.restitution))
            mu.append(np.full(world_count, c.friction))
            zeta.append(np.full(world_count, c.damping_ratio))
    walls = K.WorldWalls()
    count = len(colliders)

    def per_world(columns):  # (world_count, C) -> flat, world-major
        return wp.array(np.stack(columns, axis=1).astype(np.float32).reshape(-1) if count else
                        np.zeros(1, np.float32), dtype=float, device=device)

    walls.normals = wp.array(np.concatenate(normals).astype(np.float32) if count else np.zeros((0, 3), np.float32),
                             dtype=wp.vec3, device=device)
    walls.offsets = wp.array(np.concatenate(offsets).astype(np.float32) if count else np.zeros(0, np.float32),
                             dtype=float, device=device)
    walls.collider = wp.array(np.asarray(owner, dtype=np.int32), dtype=int, device=device)
    walls.mode = wp.array(np.asarray(mode or [0], dtype=np.int32), dtype=int, device=device)
    walls.thickness = wp.array(np.asarray(thickness or [0.0], dtype=np.float32), dtype=float, device=device)
    walls.stiffness = wp.array(np.asarray(stiffness or [0.0], dtype=np.float32), dtype=float, device=device)
    walls.restitution, walls.friction, walls.damping_ratio = per_world(r), per_world(mu), per_world(zeta)
    walls.collider_count = max(count, 1)
    return walls
