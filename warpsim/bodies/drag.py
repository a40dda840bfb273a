"""Dragging particles: grab one by index or by picking along a ray, move a target point over
time (interactively or along keyframes), release. Kernels in ``warpsim.kernels.interaction``.

``DragSpring`` is a Force: a zero-length spring of ``stiffness`` [N/m] with a damper
``damping`` [N s/m] pulls the grabbed particle p toward the target,
f_p = -k (x_p - target(t)) - c (v_p - target'(t)); it provides its Jacobian, so implicit Euler
treats it implicitly. The target path and grab window live on the device and are read at the
simulation time, so a scripted drag needs no host work per step::

    drag = ws_drag.DragSpring(stiffness=200.0, damping=2.0)
    sim = ws.Simulator(model, forces=[ws.Gravity(), drag])
    drag.grab(pick_particle(sim.state.positions, eye, ray_dir))      # mouse down
    drag.set_target(point_under_mouse)                               # mouse move
    drag.release()                                                   # mouse up

    # or scripted: grab particle 7 at t = 0.5 s, pull it up, let go at 1.5 s
    drag = DragSpring(200.0, 2.0, particle=7, path=[(0.5, (0, 0.5, 0)), (1.0, (0, 0.8, 0))], release=1.5)
"""

from __future__ import annotations

import math
from typing import Any, Optional

import numpy as np
import warp as wp

from ..core import checks
from ..core.forces import Force
from ..kernels import interaction as K

_FOREVER = 3.0e38


def pick_particle(positions, origin, direction, max_distance=None, device=None) -> int:
    """Index of the particle closest to the ray origin + t direction (t >= 0), or -1 when none
    is within ``max_distance`` [m] (None: no limit). ``positions``: wp.array of wp.vec3 or an
    (N, 3) array."""
    o = np.array(checks.vec3(origin, "ray origin"))
    d = np.array(checks.vec3(direction, "ray direction"))
    length = np.linalg.norm(d)
    if length == 0.0:
        raise ValueError("ray direction is the zero vector; give the direction the ray points to")
    if not isinstance(positions, wp.array):
        positions = wp.array(np.asarray(positions, dtype=np.float32).reshape(-1, 3), dtype=wp.vec3,
                             device=wp.get_device(device))
    n = positions.shape[0]
    if n == 0:
        return -1
    dist = wp.zeros(n, dtype=float, device=positions.device)
    wp.launch(K.distance_to_ray, n, inputs=[positions, wp.vec3(*o), wp.vec3(*(d / length)), dist],
              device=positions.device)
    dist = dist.numpy()
    best = int(np.argmin(dist))
    if max_distance is not None and dist[best] > float(max_distance):
        return -1
    return best


class DragSpring(Force):
    """Pulls one grabbed particle toward a target with a damped zero-length spring.

    Args:
        stiffness: spring constant k [N/m] (>= 0); damping: c [N s/m] (>= 0).
        particle: grab this particle from the start (None: nothing grabbed until ``grab``).
        target: fixed target [m] (default: the particle's initial position).
        path: keyframes [(time [s], (x, y, z) [m]), ...] with increasing times: the target moves
            piecewise linearly; the particle is grabbed at the first key's time.
        release: time [s] at which the particle is let go (None: never).
    """

    def __init__(self, stiffness: float = 200.0, damping: float = 2.0, particle=None, target=None, path=None,
                 release=None):
        for name, value in (("stiffness", stiffness), ("damping", damping)):
            if not (math.isfinite(float(value)) and float(value) >= 0.0):
                raise ValueError(f"DragSpring {name} {value} must be finite and >= 0")
        self.stiffness, self.damping = float(stiffness), float(damping)
        self.particle = -1
        self._keys: Any = None  # (times (K,) [s], points (K, 3) [m]) once bound
        self._window = (-_FOREVER, _FOREVER)
        self._arrays = None
        if path is not None and target is not None:
            raise ValueError("DragSpring: give either a fixed target or a keyframed path, not both")
        self._pending: Optional[tuple] = None
        if particle is not None:
            self._pending = (particle, target, path, release)
        else:
            self._pending = None

    # ------------------------------------------------------------------ setup
    def bind(self, model) -> None:
        super().bind(model)
        d = model.device
        self._grab = wp.array([-1], dtype=int, device=d)
        self._window_wp = wp.array(np.array(self._window, dtype=np.float32), dtype=float, device=d)
        self._key_times = wp.zeros(1, dtype=float, device=d)
        self._key_points = wp.zeros(1, dtype=wp.vec3, device=d)
        if self._pending is not None:
            particle, target, path, release = self._pending
            if path is not None:
                self.grab(particle)
                self.set_path(path, release=release)
            else:
                self.grab(particle, target)
                if release is not None:
                    self._set_window(-_FOREVER, float(release))
        elif self.particle >= 0:
            self._upload()

    def _check_bound(self):
        if getattr(self, "model", None) is None:
            raise ValueError("DragSpring is not bound to a model yet; pass it in Simulator(forces=[...]) first")

    def _upload(self):
        self._grab.fill_(int(self.particle))
        self._window_wp.assign(np.array(self._window, dtype=np.float32))
        times, points = self._keys
        d = self.model.device
        if self._key_times.shape[0] != len(times):
            self._key_times = wp.zeros(len(times), dtype=float, device=d)
            self._key_points = wp.zeros(len(times), dtype=wp.vec3, device=d)
        self._key_times.assign(times.astype(np.float32))
        self._key_points.assign(points.astype(np.float32))

    def _set_window(self, start, end):
        self._window = (float(start), float(end))
        self._window_wp.assign(np.array(self._window, dtype=np.float32))

    # ------------------------------------------------------------------ interaction
    def grab(self, particle: int, target=None, positions=None) -> None:
        """Grab ``particle`` now and hold it at ``target`` [m] (default: its position in
        ``positions``, a wp.array or (N, 3) array, else its initial position)."""
        self._check_bound()
        n = self.model.particle_count
        if not isinstance(particle, (int, np.integer)) or not 0 <= particle < n:
            raise ValueError(f"DragSpring: particle {particle!r} is out of range [0, {n})")
        if self.model.particle_inv_mass.numpy()[particle] == 0.0:
            raise ValueError(f"DragSpring: particle {particle} is pinned (mass 0); grab a dynamic particle")
        if target is None:
            src = self.model.particle_q if positions is None else positions
            src = src.numpy() if isinstance(src, wp.array) else np.asarray(src)
            target = src[particle]
        self.particle = int(particle)
        self._window = (-_FOREVER, _FOREVER)
        self._keys = (np.zeros(1), np.array([checks.vec3(target, "DragSpring target")]))
        self._upload()

    def grab_ray(self, positions, origin, direction, max_distance=None) -> int:
        """Grab the particle closest to the ray (see pick_particle), holding it where it is.
        Returns its index, or -1 (nothing grabbed) when none is within ``max_distance``."""
        self._check_bound()
        p = pick_particle(positions, origin, direction, max_distance)
        if p >= 0:
            self.grab(p, positions=positions)
        return p

    def set_target(self, target) -> None:
        """Move the target to ``target`` [m] now (e.g. under the mouse)."""
        self._check_bound()
        if self.particle < 0:
            raise ValueError("DragSpring.set_target: nothing is grabbed; call grab first")
        self._keys = (np.zeros(1), np.array([checks.vec3(target, "DragSpring target")]))
        self._upload()

    def set_path(self, path, release=None) -> None:
        """Keyframed target: ``path`` = [(time [s], (x, y, z) [m]), ...], times increasing. The
        grab starts at the first key's time and ends at ``release`` [s] (None: never)."""
        self._check_bound()
        if self.particle < 0:
            raise ValueError("DragSpring.set_path: nothing is grabbed; call grab first")
        try:
            times = np.array([float(t) for t, _ in path])
            points = np.array([checks.vec3(p, f"DragSpring path point {k}") for k, (_, p) in enumerate(path)])
        except (TypeError, ValueError) as exc:
            raise ValueError(f"DragSpring path must be [(time, (x, y, z)), ...]: {exc}") from None
        if len(times) == 0 or not np.all(np.isfinite(times)) or np.any(np.diff(times) <= 0.0):
            raise ValueError(f"DragSpring path times {times.tolist()} must be finite and strictly increasing")
        end = _FOREVER if release is None else float(release)
        if not end >= times[0]:
            raise ValueError(f"DragSpring release {release} comes before the first key at {times[0]} s")
        self._keys = (times, points)
        self._window = (float(times[0]), end)
        self._upload()

    def release(self) -> None:
        """Let go of the particle."""
        self._check_bound()
        self.particle = -1
        self._grab.fill_(-1)

    def active_at(self, t: float) -> bool:
        """Whether a particle is grabbed and the spring acts at time t [s]."""
        return self.particle >= 0 and self._window[0] <= t <= self._window[1]

    def target_at(self, t: float) -> np.ndarray:
        """The target position [m] at time t (host-side, same rule as the kernel)."""
        times, points = self._keys
        if t <= times[0]:
            return points[0].copy()
        if t >= times[-1]:
            return points[-1].copy()
        k = int(np.searchsorted(times, t) - 1)
        s = (t - times[k]) / (times[k + 1] - times[k])
        return points[k] + s * (points[k + 1] - points[k])

    # ------------------------------------------------------------------ Force interface
    def eval(self, q, qd, time, time_offset, f_out) -> None:
        wp.launch(K.eval_drag_spring, 1,
                  inputs=[q, qd, self._grab, self._window_wp, self._key_times, self._key_points, time,
                          float(time_offset), self.stiffness, self.damping, f_out],
                  device=self.model.device)

    def eval_jacobian(self, q, qd, time, time_offset, ck, cd, diag, rows, cols, values) -> None:
        wp.launch(K.eval_drag_spring_jacobian, 1,
                  inputs=[self._grab, self._window_wp, time, float(time_offset), self.stiffness, self.damping,
                          float(ck), float(cd), diag],
                  device=self.model.device)


def parse_drag_spec(text: str) -> list:
    """Parse a scripted-drag string into [(who, points (K, 3), t0, t1), ...].

    Syntax: ``WHO:X,Y,Z[>X,Y,Z...]@T0-T1``, several separated by ``;``. WHO is a particle index
    or a name the caller resolves; the target moves through the points, spread evenly over
    [T0, T1] [s] (one point: held there), and the particle is released at T1. Example:
    ``spout:0.3,0.6,0@0.5-1.5;12:0,0.4,0>0.2,0.4,0@2-3``."""
    out = []
    for k, item in enumerate(s for s in str(text).split(";") if s.strip()):
        item = item.strip()
        try:
            who, rest = item.split(":", 1)
            path, window = rest.rsplit("@", 1)
            t0, t1 = (float(t) for t in window.split("-", 1)) if "-" in window[1:] else (float(window), None)
            if t1 is None:
                raise ValueError("missing release time")
            points = np.array([[float(c) for c in p.split(",")] for p in path.split(">")], dtype=np.float64)
            if points.ndim != 2 or points.shape[1] != 3:
                raise ValueError("points need 3 coordinates")
        except ValueError as exc:
            raise ValueError(f"drag item {k} {item!r} is not WHO:X,Y,Z[>X,Y,Z...]@T0-T1 (e.g. "
                             f"'spout:0.3,0.6,0@0.5-1.5'): {exc}") from None
        if not (np.all(np.isfinite(points)) and np.isfinite(t0) and np.isfinite(t1) and 0.0 <= t0 < t1):
            raise ValueError(f"drag item {k} {item!r}: need finite points and 0 <= T0 < T1")
        out.append((who.strip(), points, t0, t1))
    return out


def scripted_drag(particle: int, points, t0: float, t1: float, stiffness=200.0, damping=2.0) -> DragSpring:
    """A DragSpring that grabs ``particle`` at t0, moves its target through ``points`` (K, 3)
    spread evenly over [t0, t1] and releases it at t1."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(points) == 1:
        path = [(t0, points[0])]
    else:
        times = np.linspace(t0, t1, len(points))
        path = list(zip(times, points))
    return DragSpring(stiffness, damping, particle=particle, path=path, release=t1)
