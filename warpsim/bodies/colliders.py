"""Colliders: run after integration, they correct the new positions and velocities in place.

Every collider works on any Model with ``particle_radius`` and ``particle_inv_mass`` (pinned
particles, inverse mass 0, are never moved) and is called as ``apply(model, state, q_prev, dt)``
with the positions ``q_prev`` of the start of the step.

Common options (keyword arguments of every collider except ParticleCollisions):
  restitution e in [0, 1]; friction mu >= 0 (Coulomb, never reverses sliding);
  mode: "reflect" (resolved at the time of impact: the step ends on the surface and the particle
        leaves with e times its approach speed; no energy appears for e <= 1 at any dt, see
        ``kernels/collide.py``),
        "seed" (the lecture's update: penetration h becomes e h on the free side, v_n -> -e v_n;
        it gains energy at large steps, kept to reproduce the seed's frame table),
        "project" (position correction onto the surface, v_n -> -e v_n),
        "penalty" (a penalty spring k h plus a damper acting over the step as a velocity-level
        impulse; the position is not touched; the damping ratio zeta = -ln e / sqrt(pi^2 + ln^2 e)
        gives a linear spring-damper contact the restitution e; stable for dt < 2 sqrt(m / k));
  thickness [m]: extra offset added to every particle radius (cloth, fluids);
  stiffness [N/m]: the penalty spring constant (penalty mode only).

Finite shapes (Sphere, Capsule, Quad, TriangleMesh) detect collisions continuously along the
segment q_prev -> q, so fast particles do not tunnel through thin geometry, and can move as
kinematic bodies: ``motion=f(t) -> (position, rotation_xyzw)`` is evaluated every step at the
collider's own clock (``keyframe_motion`` builds one from keyframes), or
``set_transform(position, rotation)`` moves them between steps; the surface velocity at the
contact point then enters restitution and friction.
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from ..core import checks
from ..core.collider import Collider
from ..kernels import collide as K
from ..kernels import collide_lanes as KL
from ..kernels import worlds as KW
from .mesh_io import load_mesh

MODES = {"reflect": 0, "project": 1, "penalty": 2, "seed": 3}


def damping_ratio_for_restitution(restitution: float) -> float:
    """Damping ratio zeta of a linear spring-damper contact whose restitution is e:
    e = exp(-zeta pi / sqrt(1 - zeta^2)), i.e. zeta = -ln e / sqrt(pi^2 + ln^2 e) (1 at e = 0)."""
    if restitution <= 0.0:
        return 1.0
    log_e = math.log(restitution)
    return -log_e / math.sqrt(math.pi**2 + log_e**2)


def _coefficients(owner: str, restitution, friction, mode):
    r = checks.number(restitution, f"{owner} restitution", fix="give a number in [0, 1]")
    mu = checks.number(friction, f"{owner} friction", fix="give a number >= 0")
    if not (math.isfinite(r) and 0.0 <= r <= 1.0):
        raise ValueError(f"{owner} restitution {restitution} must be in [0, 1]")
    if not (math.isfinite(mu) and mu >= 0.0):
        raise ValueError(f"{owner} friction {friction} must be >= 0")
    if mode not in MODES:
        raise ValueError(f"{owner} mode {mode!r} is unknown; use one of {sorted(MODES)}")
    return r, mu, MODES[mode]


def _start_of_step(q, q_start, forces):
    """(q_start, forces) for the out-of-place kernels: missing ones become q and zeros."""
    return (q if q_start is None else q_start), (wp.zeros_like(q) if forces is None else forces)


def _per_particle(kernel, lanes_name: str, model):
    """(kernel, launch dim, leading inputs) of a per-particle collider: on the CPU its lanes
    variant (``kernels/collide_lanes.py``: eight particles a thread, a vector filter before the same
    per-particle code, so the same bits), elsewhere one thread per particle."""
    n = model.particle_count
    if wp.get_device(model.device).is_cpu:
        return getattr(KL, lanes_name), (n + KL.LANES - 1) // KL.LANES, [n]
    return kernel, n, []


class _Contact(Collider):
    """Restitution, friction, handling mode, thickness and penalty stiffness (see module doc)."""

    def _set_contact(self, owner, restitution, friction, mode, thickness, stiffness):
        self.restitution, self.friction, self.mode = _coefficients(owner, restitution, friction, mode)
        self.mode_name = mode
        thickness = checks.number(thickness, f"{owner} thickness", "m", "give a number >= 0")
        stiffness = checks.number(stiffness, f"{owner} stiffness", "N/m", "give a number > 0")
        if not (math.isfinite(thickness) and thickness >= 0.0):
            raise ValueError(f"{owner} thickness {thickness} must be finite and >= 0 [m]")
        if not (math.isfinite(stiffness) and stiffness > 0.0):
            raise ValueError(f"{owner} stiffness {stiffness} must be finite and > 0 [N/m] (the penalty spring)")
        self.thickness, self.stiffness = thickness, stiffness
        self.damping_ratio = damping_ratio_for_restitution(self.restitution)

    def _contact_args(self, dt):
        return [self.restitution, self.friction, self.mode, self.thickness, self.stiffness, self.damping_ratio,
                float(dt)]


class Planes(_Contact):
    """A set of half-spaces n . x >= offset + radius + thickness resolved together (one launch).

    normals: (P, 3), normalised here; offsets: (P,) [m]. Restitution e in [0, 1]: the normal
    velocity becomes -e v_n and, in ``mode="reflect"``, the penetration depth h becomes e h on
    the free side; ``mode="project"`` places the particle on the plane (position correction);
    ``mode="penalty"`` pushes with a spring of ``stiffness`` [N/m]. Coulomb friction
    ``friction`` removes at most mu (1 + e) |v_n| of tangential speed."""

    def __init__(self, normals, offsets, restitution=0.5, friction=0.0, mode="reflect", name="Planes", *,
                 thickness=0.0, stiffness=1.0e4):
        normals = checks.vectors(normals, f"{name} normals", item="normal")
        offsets = checks.numbers_array([checks.number(o, f"{name} offset", "m") for o in np.atleast_1d(
            np.asarray(offsets, dtype=object)).reshape(-1)], f"{name} offsets", item="offset", unit="m")
        if len(normals) != len(offsets):
            raise ValueError(f"{name}: {len(normals)} normals but {len(offsets)} offsets")
        lengths = np.linalg.norm(normals, axis=1)
        if np.any(~np.isfinite(lengths)) or np.any(lengths == 0.0) or np.any(~np.isfinite(offsets)):
            raise ValueError(f"{name}: every normal must be a finite non-zero vector and every offset finite")
        self.normals = normals / lengths[:, None]
        self.offsets = offsets
        self.name = name
        self._set_contact(name, restitution, friction, mode, thickness, stiffness)

    def bind(self, model) -> None:
        super().bind(model)
        self._normals = wp.array(self.normals.astype(np.float32), dtype=wp.vec3, device=model.device)
        self._offsets = wp.array(self.offsets.astype(np.float32), dtype=float, device=model.device)

    def apply(self, model, state, q_prev, dt) -> None:
        kernel, dim, head = _per_particle(K.collide_planes, "collide_planes_lanes", model)
        wp.launch(
            kernel, dim,
            inputs=[*head, model.particle_inv_mass, model.particle_radius, self._normals, self._offsets,
                    *self._contact_args(dt), q_prev, state.forces, state.positions, state.velocities],
            device=model.device,
        )

    def step_distances(self, model, positions) -> np.ndarray | None:
        """Per particle, the most it may move in one step [m] (``warpsim.core.stability``): in modes
        "seed" and "project" the larger of its collision thickness (radius + thickness) and its fall
        height above the nearest plane; None in "reflect" (resolved at the time of impact) and
        "penalty" (limited by its stiffness) modes."""
        if self.mode_name not in ("seed", "project"):
            return None
        r = model.particle_radius.numpy().astype(np.float64) + self.thickness
        q = np.asarray(positions, dtype=np.float64)
        heights = q @ self.normals.T - self.offsets[None, :] - r[:, None]  # (n, planes) [m]
        return np.maximum(r, np.maximum(heights.min(axis=1), 0.0))

    def apply_out(self, model, q, qd, q_out, qd_out, dt, plane: int, q_start=None, forces=None) -> None:
        """Differentiable runs (``warpsim.diff``): plane ``plane`` alone, out of place
        (q, qd) -> (q_out, qd_out); applying planes 0..P-1 in turn equals ``apply``. q_start and
        forces: the step's start positions [m] and force [N] (reflect mode; None: q and zero)."""
        from ..kernels import autodiff as KD

        q_start, forces = _start_of_step(q, q_start, forces)
        wp.launch(KD.collide_plane_out, model.particle_count,
                  inputs=[model.particle_inv_mass, model.particle_radius, self._normals, self._offsets, int(plane),
                          *self._contact_args(dt), q_start, forces, q, qd, q_out, qd_out],
                  device=model.device)


class Plane(Planes):
    """The infinite plane n . x = offset; particles stay on the side ``normal`` points to."""

    def __init__(self, normal=(0.0, 1.0, 0.0), offset=0.0, restitution=0.5, friction=0.0, mode="reflect", *,
                 thickness=0.0, stiffness=1.0e4):
        super().__init__([checks.vec3(normal, "Plane normal")], [offset], restitution, friction, mode, name="Plane",
                         thickness=thickness, stiffness=stiffness)


class Box(Planes):
    """An axis-aligned box of six walls that keeps particles inside [lower, upper] [m]."""

    def __init__(self, lower=(-1.0, 0.0, -1.0), upper=(1.0, 2.0, 1.0), restitution=0.5, friction=0.0, mode="reflect",
                 *, thickness=0.0, stiffness=1.0e4):
        lo, hi = np.array(checks.vec3(lower, "Box lower")), np.array(checks.vec3(upper, "Box upper"))
        if np.any(hi <= lo):
            raise ValueError(f"Box upper {tuple(hi)} must exceed lower {tuple(lo)} on every axis")
        eye = np.eye(3)
        normals = np.concatenate([eye, -eye])
        offsets = np.concatenate([lo, -hi])
        super().__init__(normals, offsets, restitution, friction, mode, name="Box", thickness=thickness,
                         stiffness=stiffness)
        self.lower, self.upper = tuple(lo), tuple(hi)


# --------------------------------------------------------------------------------------
# Poses (host side, float64): position (3,) and unit quaternion (x, y, z, w)
# --------------------------------------------------------------------------------------
def quat_multiply(a, b) -> np.ndarray:
    """Hamilton product a * b of quaternions stored (x, y, z, w)."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return np.array([
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    ])


def quat_rotate(q, v) -> np.ndarray:
    """Rotate vector v by unit quaternion q (x, y, z, w)."""
    u, w = np.asarray(q[:3], dtype=np.float64), float(q[3])
    v = np.asarray(v, dtype=np.float64)
    return v + 2.0 * np.cross(u, np.cross(u, v) + w * v)


def quat_from_matrix(m) -> np.ndarray:
    """Unit quaternion (x, y, z, w) of a 3x3 rotation matrix (columns = rotated axes)."""
    m = np.asarray(m, dtype=np.float64)
    t = np.trace(m)
    if t > 0.0:
        s = 2.0 * math.sqrt(t + 1.0)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s]
    else:
        k = int(np.argmax(np.diag(m)))
        i, j = (k + 1) % 3, (k + 2) % 3
        s = 2.0 * math.sqrt(1.0 + m[k, k] - m[i, i] - m[j, j])
        q = [0.0, 0.0, 0.0, (m[j, i] - m[i, j]) / s]
        q[k] = 0.25 * s
        q[i] = (m[i, k] + m[k, i]) / s
        q[j] = (m[j, k] + m[k, j]) / s
    quat = np.array(q)
    return quat / np.linalg.norm(quat)


def quat_slerp(a, b, s: float) -> np.ndarray:
    """Spherical linear interpolation between unit quaternions a and b (shortest arc), s in [0, 1]."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    d = float(np.dot(a, b))
    if d < 0.0:
        b, d = -b, -d
    if d > 0.9995:
        q = a + s * (b - a)
        return q / np.linalg.norm(q)
    theta = math.acos(d)
    return (math.sin((1.0 - s) * theta) * a + math.sin(s * theta) * b) / math.sin(theta)


def keyframe_motion(keys):
    """A ``motion`` callable from keyframes [(time [s], position (3,), rotation (x, y, z, w) or
    None), ...] with increasing times: positions are interpolated linearly, rotations by slerp,
    and the pose is held before the first and after the last key."""
    times, poses = [], []
    for k, key in enumerate(keys):
        try:
            t, position, rotation = key
        except (TypeError, ValueError):
            raise ValueError(f"keyframe {k} must be (time, position, rotation_xyzw or None), got {key!r}") from None
        times.append(float(t))
        poses.append(parse_pose(position, rotation, f"keyframe {k}"))
    times = np.array(times)
    if len(times) == 0 or not np.all(np.isfinite(times)) or np.any(np.diff(times) <= 0.0):
        raise ValueError(f"keyframe times {times.tolist()} must be finite and strictly increasing")

    def motion(t):
        if t <= times[0]:
            return poses[0]
        if t >= times[-1]:
            return poses[-1]
        k = int(np.searchsorted(times, t) - 1)
        s = (t - times[k]) / (times[k + 1] - times[k])
        (p0, q0), (p1, q1) = poses[k], poses[k + 1]
        return p0 + s * (p1 - p0), quat_slerp(q0, q1, s)

    return motion


def parse_pose(position, rotation, owner) -> tuple:
    m = np.asarray(position, dtype=np.float64) if not isinstance(position, wp.transform) else None
    if isinstance(position, wp.transform):
        return np.array(position.p, dtype=np.float64), np.array(position.q, dtype=np.float64)
    if m is not None and m.shape == (4, 4):
        if rotation is not None:
            raise ValueError(f"{owner}: give a 4x4 matrix or a position and a rotation, not both")
        if not np.all(np.isfinite(m)):
            raise ValueError(f"{owner}: the 4x4 matrix is not finite")
        return m[:3, 3].copy(), quat_from_matrix(m[:3, :3])
    p = np.array(checks.vec3(position, f"{owner} position"))
    if rotation is None:
        return p, np.array([0.0, 0.0, 0.0, 1.0])
    q = np.asarray(rotation, dtype=np.float64).reshape(-1)
    if q.shape == (9,):
        return p, quat_from_matrix(q.reshape(3, 3))
    if q.shape != (4,) or not np.all(np.isfinite(q)) or np.linalg.norm(q) == 0.0:
        raise ValueError(f"{owner} rotation {rotation!r} must be a non-zero quaternion (x, y, z, w) or a 3x3 matrix")
    return p, q / np.linalg.norm(q)


def _wp_transform(p, q) -> wp.transform:
    return wp.transform(wp.vec3(*[float(c) for c in p]), wp.quat(*[float(c) for c in q]))


class _Kinematic(_Contact):
    """A finite shape defined in a local frame placed by ``rest`` (position, rotation) and,
    on top of it, a motion pose (identity unless moved)."""

    def _set_pose(self, rest_position, rest_rotation, motion, owner):
        self._rest = parse_pose(rest_position, rest_rotation, owner)
        if motion is not None and not callable(motion):
            raise ValueError(f"{owner} motion must be a callable t -> (position, rotation_xyzw), got {motion!r}")
        self.motion = motion
        self._owner = owner
        self._motion_pose = (np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0]))
        self._clock = 0.0
        if motion is not None:
            self._motion_pose = self._eval_motion(0.0)
        self._world = self._compose(self._motion_pose)
        self._world_prev = self._world
        self._moved = False

    def _eval_motion(self, t):
        out = self.motion(t)
        if isinstance(out, wp.transform):
            return np.array(out.p, dtype=np.float64), np.array(out.q, dtype=np.float64)
        try:
            position, rotation = out
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{self._owner} motion({t}) must return (position, rotation_xyzw)") from exc
        return parse_pose(position, rotation, f"{self._owner} motion({t})")

    def _compose(self, motion_pose):
        (pm, qm), (pr, qr) = motion_pose, self._rest
        return pm + quat_rotate(qm, pr), quat_multiply(qm, qr)

    @property
    def time(self) -> float:
        """The collider's clock [s]: simulated time it has been applied for."""
        return self._clock

    @property
    def clock(self) -> float:
        """The collider's clock [s] (as ``time``); setting it calls ``set_clock``."""
        return self._clock

    @clock.setter
    def clock(self, t: float) -> None:
        self.set_clock(t)

    def set_clock(self, t: float) -> None:
        """Set the clock to ``t`` [s] (restoring a checkpoint, restarting a run). A shape that
        follows ``motion`` is placed at its pose at ``t`` with no sweep from the old pose: the next
        step starts there."""
        self._clock = checks.finite(t, f"{self._owner} clock", "s", "the simulated time, e.g. 0.0")
        if self.motion is not None:
            self._motion_pose = self._eval_motion(self._clock)
            self._world = self._world_prev = self._compose(self._motion_pose)

    def set_transform(self, position=(0.0, 0.0, 0.0), rotation=None) -> None:
        """Move the shape to the motion pose (position [m] and rotation quaternion (x, y, z, w) or
        3x3 matrix, None: no rotation; or one 4x4 rigid matrix / wp.transform), applied on top of
        its rest pose. Call it between frames; the next step sweeps the shape from the old pose to
        the new one (surface velocity = displacement / that step). For motion that must be
        followed within every sub-step, give ``motion=`` (e.g. ``keyframe_motion(...)``)."""
        self._motion_pose = parse_pose(position, rotation, f"{self._owner} set_transform")
        self._world = self._compose(self._motion_pose)
        self._moved = True

    def world_pose(self):
        """Current local-to-world pose: (position (3,), quaternion (x, y, z, w))."""
        return self._world[0].copy(), self._world[1].copy()

    def _extent(self) -> float:
        """Distance [m] from the shape's local origin to its farthest surface point (a bound; the
        geometry is fixed, so it is measured once)."""
        cached = getattr(self, "_extent_m", None)
        if cached is not None:
            return cached
        r = 0.0
        for attr in ("a_local", "b_local"):
            if hasattr(self, attr):
                r = max(r, float(np.linalg.norm(getattr(self, attr))))
        r += float(getattr(self, "radius", 0.0) or 0.0)
        if hasattr(self, "half_x"):
            r = max(r, math.hypot(getattr(self, "half_x"), getattr(self, "half_z")))
        if hasattr(self, "points"):
            r = max(r, float(np.linalg.norm(np.asarray(self.points, float), axis=1).max(initial=0.0)))
        self._extent_m: float | None = r
        return r

    def frame_surface_speed(self) -> float:
        """Largest speed [m/s] of the shape's surface over the steps since the last call (0 for a
        shape that did not move): the energy balance's allowance (``warpsim.core.energy``)."""
        speed, self._peak_speed = getattr(self, "_peak_speed", 0.0), 0.0
        return speed

    def advance_pose(self, dt: float):
        """Advance the clock by ``dt`` [s] as a step of ``apply`` does and return the step's poses
        (before, after) as wp.transforms: for code that steps the pose outside ``apply`` (a frame
        whose poses are copied to the device once, ``warpsim.strands.frame.HeadPoses``)."""
        return self._advance(dt)

    def _advance(self, dt):
        """Poses (prev, now) as wp.transforms for this step."""
        self._clock += dt
        if self.motion is not None:
            self._world_prev = self._world
            self._motion_pose = self._eval_motion(self._clock)
            self._world = self._compose(self._motion_pose)
        elif not self._moved:
            self._world_prev = self._world
        self._moved = False
        (p0, q0), (p1, q1) = self._world_prev, self._world
        if dt > 0 and (np.any(p0 != p1) or np.any(q0 != q1)):
            turn = 2.0 * math.acos(min(1.0, abs(float(np.dot(q0, q1)))))  # rotation angle over the step [rad]
            speed = (float(np.linalg.norm(p1 - p0)) + turn * self._extent()) / dt
            self._peak_speed = max(getattr(self, "_peak_speed", 0.0), speed)
        prev = _wp_transform(*self._world_prev)
        now = _wp_transform(*self._world)
        self._world_prev = self._world
        return prev, now


class Capsule(_Kinematic):
    """A solid capsule: every point within ``radius`` [m] of the segment [a, b] [m].

    Particles are pushed out along the normal of the closest point; the path q_prev -> q is
    tested for entry (continuous detection; ``continuous=False``: the end point only, which
    differentiable runs need). See the module docstring for the common options."""

    def __init__(self, a=(0.0, 0.0, 0.0), b=(0.0, 1.0, 0.0), radius=0.25, *, restitution=0.5, friction=0.0,
                 mode="reflect", thickness=0.0, stiffness=1.0e4, motion=None, name="Capsule", continuous=True):
        self.continuous = checks.flag(continuous, f"{type(self).__name__} continuous")
        a, b = np.array(checks.vec3(a, f"{name} a")), np.array(checks.vec3(b, f"{name} b"))
        radius = checks.number(radius, f"{name} radius", "m", "give a number > 0")
        if not (math.isfinite(radius) and radius > 0.0):
            raise ValueError(f"{name} radius {radius} must be finite and > 0 [m]")
        self.radius = radius
        self.name = name
        self._set_contact(name, restitution, friction, mode, thickness, stiffness)
        center = 0.5 * (a + b)
        self.a_local, self.b_local = a - center, b - center
        self.inside = 0
        self._set_pose(center, None, motion, name)

    @property
    def a(self):
        p, q = self.world_pose()
        return p + quat_rotate(q, self.a_local)

    @property
    def b(self):
        p, q = self.world_pose()
        return p + quat_rotate(q, self.b_local)

    def apply(self, model, state, q_prev, dt) -> None:
        prev, now = self._advance(dt)
        kernel, dim, head = _per_particle(K.collide_capsule, "collide_capsule_lanes", model)
        wp.launch(
            kernel, dim,
            inputs=[*head, model.particle_inv_mass, model.particle_radius, q_prev, int(self.continuous),
                    wp.vec3(*self.a_local), wp.vec3(*self.b_local), self.radius, self.inside, prev, now,
                    *self._reach(prev, now), *self._contact_args(dt), state.forces, state.positions,
                    state.velocities],
            device=model.device,
        )

    def _reach(self, prev, now):
        """(world middle of the segment [m], half its length [m]) for the kernel's early-out when
        the shape is solid and did not move over the step (the poses' float32 values equal);
        (0, -1): no early-out."""
        if self.inside or tuple(prev) != tuple(now):
            return wp.vec3(0.0, 0.0, 0.0), -1.0
        p, q = self.world_pose()
        half = 0.5 * float(np.linalg.norm(self.b_local - self.a_local))
        return wp.vec3(*(p + quat_rotate(q, 0.5 * (self.a_local + self.b_local)))), half

    def apply_out(self, model, q, qd, q_out, qd_out, dt, q_start=None, forces=None) -> None:
        """Differentiable runs (``warpsim.diff``): discrete detection, out of place
        (q, qd) -> (q_out, qd_out); equals ``apply`` with ``continuous=False`` on a static shape."""
        from ..kernels import autodiff as KD

        prev, now = self._advance(dt)
        q_start, forces = _start_of_step(q, q_start, forces)
        wp.launch(KD.collide_capsule_out, model.particle_count,
                  inputs=[model.particle_inv_mass, model.particle_radius, wp.vec3(*self.a_local),
                          wp.vec3(*self.b_local), self.radius, self.inside, prev, now, *self._contact_args(dt),
                          q_start, forces, q, qd, q_out, qd_out],
                  device=model.device)


class Sphere(Capsule):
    """A solid sphere of ``radius`` [m] at ``center`` [m]; with ``inside=True`` a spherical
    container that keeps particles within it instead."""

    def __init__(self, center=(0.0, 0.0, 0.0), radius=0.5, *, inside=False, restitution=0.5, friction=0.0,
                 mode="reflect", thickness=0.0, stiffness=1.0e4, motion=None, continuous=True):
        c = checks.vec3(center, "Sphere center")
        super().__init__(c, c, radius, restitution=restitution, friction=friction, mode=mode, thickness=thickness,
                         stiffness=stiffness, motion=motion, name="Sphere", continuous=continuous)
        self.inside = int(checks.flag(inside, "Sphere inside"))

    @property
    def center(self):
        return self.world_pose()[0]


class Quad(_Kinematic):
    """A thin two-sided rectangle: ``center`` [m] plus half-edge vectors ``axis_u`` and
    ``axis_v`` [m] (orthogonal); it spans center + s axis_u + t axis_v, |s|, |t| <= 1.

    Continuous detection: a particle whose path crosses the rectangle during the step is
    stopped on the side it came from, whatever its speed; near the edges the closest point of
    the rectangle gives the normal (rounded edges)."""

    def __init__(self, center=(0.0, 0.0, 0.0), axis_u=(0.5, 0.0, 0.0), axis_v=(0.0, 0.0, 0.5), *, restitution=0.5,
                 friction=0.0, mode="reflect", thickness=0.0, stiffness=1.0e4, motion=None, name="Quad"):
        u = np.array(checks.vec3(axis_u, f"{name} axis_u"))
        v = np.array(checks.vec3(axis_v, f"{name} axis_v"))
        lu, lv = np.linalg.norm(u), np.linalg.norm(v)
        if lu == 0.0 or lv == 0.0:
            raise ValueError(f"{name} axis_u and axis_v must be non-zero half-edge vectors [m]")
        if abs(np.dot(u, v)) > 1.0e-6 * lu * lv:
            raise ValueError(f"{name} axis_u {tuple(u)} and axis_v {tuple(v)} must be orthogonal (a rectangle)")
        self.half_x, self.half_z = float(lu), float(lv)
        ex, ez = u / lu, v / lv
        ey = np.cross(ez, ex)
        self.name = name
        self._set_contact(name, restitution, friction, mode, thickness, stiffness)
        self._set_pose(center, quat_from_matrix(np.column_stack([ex, ey, ez])), motion, name)

    @property
    def normal(self):
        return quat_rotate(self.world_pose()[1], [0.0, 1.0, 0.0])

    def corners(self) -> np.ndarray:
        """World corner positions, shape (4, 3), counter-clockwise seen from +normal."""
        p, q = self.world_pose()
        local = [(-1, -1), (-1, 1), (1, 1), (1, -1)]
        return np.array([p + quat_rotate(q, [s * self.half_x, 0.0, t * self.half_z]) for s, t in local])

    def apply(self, model, state, q_prev, dt) -> None:
        prev, now = self._advance(dt)
        wp.launch(
            K.collide_quad, model.particle_count,
            inputs=[model.particle_inv_mass, model.particle_radius, q_prev, self.half_x, self.half_z, prev, now,
                    *self._contact_args(dt), state.forces, state.positions, state.velocities],
            device=model.device,
        )


Rectangle = Quad


def check_triangles(points, faces, owner: str):
    """Validate a triangle mesh: points (V, 3) finite, faces (F, 3) in range, no repeated vertex
    in a face. Returns float64 points and int64 faces; ValueError naming the item otherwise."""
    points = np.asarray(points, dtype=np.float64)
    faces = np.asarray(faces)
    if points.size == 0 or faces.size == 0:
        raise ValueError(f"{owner}: the mesh is empty ({len(points)} points, {len(faces)} faces); give a mesh "
                         "with at least one triangle")
    points = points.reshape(-1, 3)
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"{owner}: faces must have shape (F, 3) (triangles), got {faces.shape}; triangulate first")
    if not np.issubdtype(faces.dtype, np.integer):
        raise ValueError(f"{owner}: faces must be integer vertex indices, got dtype {faces.dtype}")
    faces = faces.astype(np.int64)
    bad = np.flatnonzero(~np.all(np.isfinite(points), axis=1))
    if len(bad):
        raise ValueError(f"{owner}: point {int(bad[0])} is not finite: {points[bad[0]]}")
    out = np.flatnonzero(np.any((faces < 0) | (faces >= len(points)), axis=1))
    if len(out):
        raise ValueError(f"{owner}: face {int(out[0])} {faces[out[0]].tolist()} indexes a point outside "
                         f"[0, {len(points)})")
    rep = np.flatnonzero((faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2]) | (faces[:, 0] == faces[:, 2]))
    if len(rep):
        raise ValueError(f"{owner}: face {int(rep[0])} {faces[rep[0]].tolist()} repeats a vertex; remove "
                         "degenerate faces")
    return points, faces


class TriangleMesh(_Kinematic):
    """A triangle mesh collider through ``wp.Mesh`` (BVH queries), static or kinematic.

    points: (V, 3) [m] in the mesh's local frame; faces: (F, 3) vertex indices.
    ``solid=True`` declares a closed mesh (re-wound outward if needed): particles found inside
    are pushed out through the closest surface. Otherwise it is a thin two-sided surface. Either way the path
    q_prev -> q is ray-cast against the mesh (``wp.mesh_query_ray``), so particles cannot pass
    through it in one step. ``position``/``rotation`` place it (rest pose); ``motion`` or
    ``set_transform`` move it as a rigid kinematic body."""

    def __init__(self, points, faces, *, solid=False, position=(0.0, 0.0, 0.0), rotation=None, restitution=0.5,
                 friction=0.0, mode="reflect", thickness=0.0, stiffness=1.0e4, motion=None, name="TriangleMesh"):
        self.points, self.faces = check_triangles(points, faces, name)
        self.solid = int(checks.flag(solid, "TriangleMesh solid"))
        if self.solid:
            from . import meshtools

            meshtools.check_manifold(self.faces, name, consistent=True)
            if not meshtools.is_closed(self.faces):
                raise ValueError(f"{name}: solid=True needs a closed mesh (every edge in two faces); close it or "
                                 "use solid=False for a thin surface")
            if meshtools.signed_volume(self.points, self.faces) < 0.0:
                self.faces = self.faces[:, ::-1].copy()  # wound inward: turn it outward
        self.name = name
        self._set_contact(name, restitution, friction, mode, thickness, stiffness)
        self._set_pose(position, rotation, motion, name)
        self._mesh = None

    @classmethod
    def from_file(cls, path, **kwargs):
        """Load OBJ/STL/PLY/GLB/OFF (trimesh) or USD (.usd/.usda/.usdc, first Mesh prim)."""
        points, faces = load_mesh(path)
        return cls(points, faces, **kwargs)

    def world_points(self) -> np.ndarray:
        """Vertex positions in world space for the current pose, shape (V, 3)."""
        p, q = self.world_pose()
        u, w = q[:3], q[3]
        v = self.points
        return p + v + 2.0 * np.cross(u, np.cross(u, v) + w * v)

    def bind(self, model) -> None:
        super().bind(model)
        if self._mesh is None or self._mesh.device != model.device:
            d = model.device
            self._points_wp = wp.array(self.points.astype(np.float32), dtype=wp.vec3, device=d)
            self._indices_wp = wp.array(self.faces.astype(np.int32).reshape(-1), dtype=int, device=d)
            self._mesh = wp.Mesh(points=self._points_wp, indices=self._indices_wp)

    @property
    def mesh(self) -> wp.Mesh:
        """The wp.Mesh (local frame), available after bind."""
        return self._mesh

    def apply(self, model, state, q_prev, dt) -> None:
        prev, now = self._advance(dt)
        wp.launch(
            K.collide_mesh, model.particle_count,
            inputs=[model.particle_inv_mass, model.particle_radius, q_prev, self._mesh.id, self.solid, prev, now,
                    *self._contact_args(dt), state.forces, state.positions, state.velocities],
            device=model.device,
        )


class ParticleCollisions(Collider):
    """Sphere-sphere collisions between the model's particles (radius = particle_radius).

    Overlapping pairs found through a ``wp.HashGrid`` get the 1D two-body rule along the line
    of centres: momentum is conserved and the relative normal velocity u = (v_b - v_a) . n
    becomes -c_R u (c_R = ``restitution``); the tangential velocity is unchanged unless
    ``friction`` mu > 0 (Coulomb, at most mu times the normal impulse, never reversing the
    slip). ``separate=True`` also removes the overlap, split by inverse mass. A particle touching
    several others at once gets each pair's impulse scaled by 1 / max(contacts of the pair), a
    convex combination, so kinetic energy never increases for c_R <= 1 and momentum stays exact.
    Pinned particles (inverse mass 0) act as infinitely heavy."""

    def __init__(self, restitution=1.0, friction=0.0, separate=True, grid_dim=128):
        self.restitution, self.friction, _ = _coefficients("ParticleCollisions", restitution, friction, "reflect")
        self.separate = int(checks.flag(separate, "ParticleCollisions separate"))
        self.grid_dim = checks.count(grid_dim, "ParticleCollisions grid_dim", fix="hash grid cells per axis, e.g. 128")

    def bind(self, model) -> None:
        super().bind(model)
        radius = model.particle_radius.numpy()
        bad = np.flatnonzero(radius <= 0.0)
        if len(bad):
            raise ValueError(f"ParticleCollisions: particle {int(bad[0])} has radius {radius[bad[0]]}; give every "
                             "particle a radius > 0 (add_particle(..., radius=r))")
        self.max_radius = float(radius.max()) if len(radius) else 0.0
        d, n = model.device, model.particle_count
        self.grid = wp.HashGrid(self.grid_dim, self.grid_dim, self.grid_dim, device=d)
        self._count = wp.zeros(n, dtype=int, device=d)
        self._q = wp.zeros(n, dtype=wp.vec3, device=d)
        self._qd = wp.zeros(n, dtype=wp.vec3, device=d)
        # batched worlds (warpsim.worlds): pairs only within a world, each world's copy of space
        # offset in the grid by a stride a few times its extent (one world: no offset)
        worlds = getattr(model, "world_count", 1)
        self._world = getattr(model, "particle_world", None) if worlds > 1 else None
        if self._world is None:
            self._world = wp.zeros(n, dtype=int, device=d)
        q = model.particle_q.numpy()
        extent = float(np.ptp(q, axis=0).max()) if n else 0.0
        self._stride = 4.0 * (extent + 1.0 + 8.0 * self.max_radius) if worlds > 1 else 0.0
        self._side = max(1, int(np.ceil(worlds ** (1.0 / 3.0) - 1e-9)))
        self._keyed = wp.zeros(n, dtype=wp.vec3, device=d) if worlds > 1 else None

    def apply(self, model, state, q_prev, dt) -> None:
        n = model.particle_count
        if n == 0:
            return
        d = model.device
        points = state.positions
        if self._keyed is not None:
            wp.launch(KW.key_world_points, n, inputs=[state.positions, self._world, self._stride, self._side,
                                                      self._keyed], device=d)
            points = self._keyed
        self.grid.build(points, 2.0 * self.max_radius)
        world = (self._world, self._stride, self._side)
        wp.launch(K.count_particle_contacts, n,
                  inputs=[self.grid.id, state.positions, model.particle_radius, model.particle_inv_mass,
                          self.max_radius, *world, self._count], device=d)
        wp.launch(K.collide_particle_pairs, n,
                  inputs=[self.grid.id, state.positions, state.velocities, model.particle_radius,
                          model.particle_inv_mass, self._count, self.max_radius, self.restitution, self.friction,
                          self.separate, *world, self._q, self._qd], device=d)
        wp.copy(state.positions, self._q)
        wp.copy(state.velocities, self._qd)
