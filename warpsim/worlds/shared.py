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
from ..kernels import occupancy as KO
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
    breakable = int(getattr(sim0.model, "breakable_spring_count", 0) or 0)
    if getattr(sim0, "fracture", None) is not None or breakable > 0:
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
    ``frame(frame_dt, steps)`` runs a frame in which world w takes ``steps[w]`` steps of
    ``frame_dt / steps[w]`` (``steps``: one count for all, or one per world: each world's own
    automatic count), one launch per sub-step up to the largest count (worlds past their count
    idle), or with ``block_per_world`` the whole frame in one launch, one thread block of
    ``lanes`` threads per world (the same bits); the state ends in ``batch.sim.state`` (no
    allocation: a frame captures as a CUDA graph).

    ``scales``: {spring array name: (base (S,) host, key (S,) device int, coefficient (S,) device
    float)} and ``world_values`` (device, world_count K) as the tiling computed them."""

    def __init__(self, batch, m0, scales, world_values, key_count, gravity, walls, block_per_world=False,
                 lanes=128):
        d = batch.device
        self.block_per_world = bool(block_per_world)
        self.lanes = 1 if d.is_cpu else int(lanes)  # CPU launches run blocks of one thread
        self.springs = shared_springs(m0, scales, world_values, key_count, d)
        self.world_gravity = wp.array(np.asarray(gravity, dtype=np.float32).reshape(-1, 3), dtype=wp.vec3, device=d)
        self.walls = walls
        self.batch = batch
        st = batch.sim.state
        self._home = (st.positions, st.velocities)
        self._spare = (wp.zeros_like(st.positions), wp.zeros_like(st.velocities))
        n = batch.world_count
        self.steps = K.WorldSteps()
        """Each world's steps per frame and step [s] (``kernels/world_step.py: WorldSteps``)."""
        self.steps.steps = wp.ones(n, dtype=int, device=d)
        self.steps.h = wp.zeros(n, dtype=float, device=d)
        self._steps_key: tuple | None = None
        self.max_steps = 1
        """The largest count of the last frame: launches per frame of the per-step path."""
        self._odd = False
        self.marks = None
        """A ``kernels/occupancy.py: CellMarks`` set by an occupancy recorder: each world's last
        sub-step of a frame marks the cells of its positions (None: no marks)."""
        self._no_marks = KO.CellMarks()
        self._no_marks.dims = wp.vec3i(1, 1, 1)
        self._no_marks.cell_hit = wp.zeros(0, dtype=wp.uint8, device=d)
        self._no_marks.bits = wp.zeros(0, dtype=wp.uint32, device=d)
        self._no_marks.frame = wp.zeros(1, dtype=int, device=d)

    def set_steps(self, frame_dt: float, steps) -> None:
        """World w takes ``steps[w]`` steps of ``frame_dt / steps[w]`` [s] a frame (``steps``: an int
        for all worlds or (world_count,) ints); the step is the float32 of the same float64
        division a world run alone makes. Copied to the device only when it changes (a captured
        frame replays with the same counts)."""
        n = self.batch.world_count
        counts = np.broadcast_to(np.asarray(steps, dtype=np.int64), (n,))
        if (counts < 1).any():
            w = int(np.flatnonzero(counts < 1)[0])
            raise ValueError(f"world {w} has {int(counts[w])} steps a frame; give >= 1")
        key = (float(frame_dt), counts.tobytes())
        if key == self._steps_key:
            return
        self.steps.steps.assign(counts.astype(np.int32))
        self.steps.h.assign((np.float64(frame_dt) / counts).astype(np.float32))
        self._steps_key = key
        self.max_steps = int(counts.max())
        self._odd = bool((counts % 2 == 1).any())

    def frame(self, frame_dt: float, steps) -> None:
        """One frame: world w takes ``steps[w]`` steps (or ``steps`` each) of ``frame_dt / steps[w]``
        [s]; worlds past their count idle (the mask is data: the launches depend on the largest
        count only)."""
        self.set_steps(frame_dt, steps)
        b, st = self.batch, self.batch.sim.state
        if st.positions is not self._home[0]:  # a state swapped in from outside: start from the home pair
            wp.copy(self._home[0], st.positions)
            wp.copy(self._home[1], st.velocities)
            st.positions, st.velocities = self._home
        m, marks = b.model, self._no_marks if self.marks is None else self.marks
        if self.block_per_world:
            wp.launch(K.frame_shared_worlds, b.world_count * self.lanes,
                      inputs=[st.positions, st.velocities, self._spare[0], self._spare[1], m.particle_mass,
                              m.particle_inv_mass, m.particle_radius, self.world_gravity, m.world_particle_count,
                              self.lanes, self.springs, self.walls, self.steps, marks],
                      block_dim=self.lanes, device=b.device)
        else:
            pairs = (self._home, self._spare)  # sub-step k reads pair k % 2 and writes the other
            for k in range(self.max_steps):
                (q, qd), (q_out, qd_out) = pairs[k % 2], pairs[(k + 1) % 2]
                wp.launch(K.step_shared_worlds, m.particle_count,
                          inputs=[q, qd, m.particle_mass, m.particle_inv_mass, m.particle_radius, self.world_gravity,
                                  m.world_particle_count, self.springs, self.walls, self.steps, k, q_out, qd_out,
                                  marks], device=b.device)
            if self._odd:  # worlds that took an odd count end in the spare pair
                wp.launch(K.settle_worlds, m.particle_count,
                          inputs=[*self._spare, m.world_particle_count, self.steps, *self._home], device=b.device)
        sim = b.sim
        sim.time += frame_dt
        sim.step_count += self.max_steps

    def device_bytes(self) -> int:
        """Bytes of the shared arrays (stored once for all worlds), the spare state pair and the
        per-world counts and steps."""
        s = self.springs
        arrays = [s.offsets, s.entries, s.keys, s.world_values, *self._spare, self.world_gravity, self.steps.steps,
                  self.steps.h]
        return sum(a.size * wp.types.type_size_in_bytes(a.dtype) for a in arrays)


def shared_springs(m0, scales, world_values, key_count, device) -> K.SharedSprings:
    """The SharedSprings of world 0's model ``m0``: its CSR adjacency (ascending spring order) with
    each end's entry (value or coefficient of rest length, stiffness, damping; other end, which
    end) and packed keys; ``scales`` {name: (base (S,) host, key (S,) device, coefficient (S,)
    device)} as the tiling found them."""
    ensure_spring_adjacency(m0)
    P, S = m0.particle_count, m0.spring_count
    if P >= 1 << 23:
        raise ValueError(f"a world of {P} particles is too large for the shared path (< 2^23); use shared=False")
    if int(key_count) >= 1023:
        raise ValueError(f"{key_count} varied parameters: the shared path packs at most 1022; use shared=False")
    offsets = m0.particle_spring_offsets.numpy()
    springs = m0.particle_springs.numpy().astype(np.int64)
    ends = m0.spring_indices.numpy().reshape(-1, 2).astype(np.int64)
    row = np.repeat(np.arange(P), np.diff(offsets))  # the particle of each entry
    values, keys = [], np.zeros(len(springs), dtype=np.int64)
    for slot, name in enumerate(SPRING_PARAMS):
        base, key, coefficient = scales[name]
        key, coefficient = key.numpy(), coefficient.numpy()
        value = np.where(key >= 0, coefficient, np.asarray(base, dtype=np.float32)).astype(np.float32)
        values.append(value[springs])
        keys |= (key[springs].astype(np.int64) + 1) << (10 * slot)
    second = (ends[springs, 1] == row) & (ends[springs, 0] != row)
    other = np.where(second, ends[springs, 0], ends[springs, 1])
    code = (2 * other + second).astype(np.float32)  # exact below 2^24
    s = K.SharedSprings()
    s.offsets = wp.array(offsets, dtype=int, device=device)
    s.entries = wp.array(np.stack([*values, code], axis=1).reshape(-1, 4) if S else np.zeros((0, 4), np.float32),
                         dtype=wp.vec4, device=device)
    s.keys = wp.array(keys.astype(np.int32), dtype=int, device=device)
    s.world_values, s.key_count = world_values, int(key_count)
    return s


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
