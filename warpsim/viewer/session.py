"""The viewer's server-side state, independent of viser (so tests drive it directly).

A :class:`Session` owns one running scene: it steps it frame by frame, draws it into a
:class:`~warpsim.viewer.sink.ViewerSink`, paces it (real time when the machine keeps up, else as
fast as it can), applies parameter changes (live where the scene allows, else by rebuilding),
drags particles with a ``ws.DragSpring`` toward the pointer, records into a USD cache and turns
a ``SimulationError`` into a short explosion (drawn with positions clamped, then paused with the
message and the stability limit kept for the page; Reset restarts from the last parameters that
ran stable). Every public
method takes the session's lock, so GUI callbacks (viser runs them on a thread pool) and the
stepping loop can call it concurrently.
"""
from __future__ import annotations

import math
import threading
import time

import numpy as np

from ..bodies.drag import DragSpring
from ..core.errors import SimulationError
from ..scenes import parse_value
from ..scenes.timing import resolve_timing
from .params import format_param
from .picking import camera_plane_target, pick_mesh_vertex, pick_point
from .record import Recorder, default_recording_path
from .sink import ViewerSink

__all__ = ["EXPLOSION_FRAMES", "EXPLOSION_SECONDS", "STABLE_FRAMES", "Session"]

EXPLOSION_FRAMES = 45
"""Frames drawn past a blow-up, one simulation step each (slow motion; checks off, positions
clamped for drawing) before the session pauses with the explanation: the lecture's explosion, for
a bounded moment."""

EXPLOSION_SECONDS = 2.0
"""Wall seconds the blow-up is shown at most: the explosion pauses after EXPLOSION_FRAMES frames or
this long, whichever comes first, so "shown for a moment, then paused" holds where a step is slow
(the implicit cloth's step is a whole frame's Newton solve: 45 of them went on draping for many
seconds under the toast)."""

STABLE_FRAMES = 60
"""Frames a parameter set must run without a failure to count as the last stable one (Reset
after a blow-up returns to it)."""


class Session:
    """One scene running in the viewer.

    Args:
        scene_cls: a registered Scene class (see ``warpsim.scenes.get_scene``).
        params: {key: typed value or text} overriding the scene's defaults.
        device: Warp device.
        fps, substeps: as ``warpsim run`` (None: the scene's).
        max_points: points drawn per points prim (strided subset beyond it).
        record_dir: folder for recordings without an explicit path.
        scene: an already built scene instance of ``scene_cls`` to show (``ws.Viewer(scene)``).
    """

    def __init__(self, scene_cls, params=None, device=None, *, fps=None, substeps=None, max_points=200_000,
                 record_dir="usd_out", scene=None):
        self.cls = scene_cls
        self.params = scene_cls.resolve_params(params or {}) if scene is None else dict(scene.params)
        self.device = device if scene is None else scene.device
        self.fps_arg, self.substeps_arg = fps, substeps
        self.max_points = max_points
        self.record_dir = record_dir
        self.lock = threading.RLock()
        self.playing = True
        self.speed = 1.0  # simulated seconds per wall second asked for (math.inf: as fast as possible)
        self.error = None
        self.recorder = None
        self.last_recording = None
        self.messages = []  # (kind, text) for the page: parameter changes, recordings, errors
        self.wall_ms = 0.0  # wall milliseconds to simulate a frame, smoothed
        self.draw_ms = 0.0  # wall milliseconds to draw one (set by the front end), smoothed
        self.sim_rate = 0.0  # simulated seconds per wall second, measured
        self.drag_stiffness = None  # None: chosen per scene (see _default_drag)
        self.version = 0  # bumped on every rebuild: the front end redraws static prims
        default_dt = scene_cls.params["dt"].default if "dt" in scene_cls.params else None
        self.dt_by_hand = "dt" in self.params and self.params["dt"] != default_dt  # then no auto sub-steps
        self.stable_params = None  # the last parameters that ran STABLE_FRAMES frames without failing
        self.limit = None  # the scene's ws.StabilityLimit (None: no simulator with one)
        self.step_dt = None  # the step the scene takes [s]
        self.exploding = None  # {"error", "frame", "left"} while a blow-up is being shown
        self._frames_since_change = 0
        self._substeps_done = 0  # sub-steps taken of a frame a Pause interrupted
        self._build(scene)

    # ------------------------------------------------------------------ building
    def _timing(self):
        """The session's :class:`~warpsim.scenes.timing.FrameTiming`, resolved as ``warpsim run``
        does from the parameters, ``fps`` and ``substeps``. A dt set on the page is the step, and
        frames are dt x the steps a frame apart (--fps then follows: the page changes the step)."""
        fps = self.fps_arg
        if self.dt_by_hand and "dt" in self.cls.params:
            steps = self.substeps_arg if isinstance(self.substeps_arg, int) else self.cls.substeps
            fps = 1.0 / (float(self.params["dt"]) * steps)
        return resolve_timing(self.cls, self.params, fps=fps, substeps=self.substeps_arg,
                              given=("dt",) if self.dt_by_hand else ())

    def _build(self, scene=None):
        self._close_recording("the scene was rebuilt")
        if scene is None:
            scene = self.cls(self._timing().scene_params(self.params), device=self.device)
        self.scene = scene
        self.timing = self._timing()
        self.frame_dt, self.substeps, self.fps = self.timing.frame_dt, self.timing.steps, self.timing.fps
        scene.use_timing(self.timing)
        self.exploding = None
        self._clamping = False
        self._frames_since_change = 0
        if self.stable_params is None:
            self.stable_params = dict(self.params)
        self._update_limit()
        self.sink = ViewerSink(self.max_points)
        scene.declare(self.sink)
        self.static = self.sink.static_items()
        self.drag_map = scene.drag_map()
        self.drag = None  # the DragSpring, attached on the first grab
        self.grabbed = None  # {"prim", "vertex", "particle", "target", "start", "plane_point", "client"}
        self.frame = 0
        self.time = 0.0
        self.error = None
        self.failed_at = None
        """(frame, time [s]) where the run failed or blew up (the error names it; the frames of the
        explosion shown after it do not move it), None while it runs."""
        self._substeps_done = 0
        self.sim_rate = 0.0  # measured afresh: the rebuilt scene may run at another rate
        self._items = self.sink.draw(scene.frame_data(), 0)
        pts = [it.points.reshape(-1, 3) for it in self._items.values() if it.points is not None and it.points.size]
        pts = np.concatenate(pts) if pts else np.zeros((1, 3))
        self._bounds = (pts.min(0), pts.max(0))
        self._stale = False
        self.version += 1

    def _update_limit(self):
        """Recompute the stability limit and the step taken (after a build or a live change)."""
        try:
            self.limit = self.scene.stability() if hasattr(self.scene, "stability") else None
            steps = self.scene.frame_steps(self.frame_dt, self.substeps) if hasattr(self.scene, "frame_steps") \
                else self.substeps
        except (ValueError, AttributeError, TypeError):  # a scene whose model the estimate does not cover
            self.limit, steps = None, self.substeps
        self.step_dt = self.frame_dt / steps

    def stability(self):
        """The time step and its limit for the page: {"dt" (the scene's dt parameter or frame step)
        [s], "step" (the step taken) [s], "limit" [s] (None: unknown), "auto" (sub-steps chosen from
        the limit), "exceeded" (dt past the limit), "who" (the limiter), "reason"}."""
        with self.lock:
            dt = float(self.params["dt"]) if "dt" in self.params else self.frame_dt / self.substeps
            limit = self.limit
            auto = self.timing.auto
            known = limit is not None and math.isfinite(limit.dt)
            return {"dt": dt, "step": self.step_dt, "limit": limit.dt if limit is not None else None, "auto": auto,
                    "exceeded": bool(known and limit.exceeded_by(self.step_dt)),
                    "dt_exceeded": bool(known and limit.exceeded_by(dt)),
                    "who": limit.who() if limit is not None else "", "reason": limit.reason if limit else ""}

    def reset(self):
        """Rebuild the scene (frame 0): from its current parameters, or after a blow-up from the
        last parameters that ran stable."""
        with self.lock:
            if self.cls.__name__ == "SimulatorAdapter":
                raise ValueError("a simulator stepped by the caller cannot be reset from the viewer")
            failed = self.error is not None or self.exploding is not None
            restored = {k: v for k, v in (self.stable_params or {}).items() if self.params.get(k) != v} \
                if failed else {}
            if restored:
                self.params.update(restored)
                if "dt" in restored:
                    self.dt_by_hand = False
            self._build()
            if restored:
                self._say("info", "reset to the last stable parameters: " +
                          ", ".join(self.shown(k) for k in restored))
            else:
                self._say("info", "reset to frame 0")

    # ------------------------------------------------------------------ stepping
    @property
    def items(self):
        """{name: DrawItem} of the current frame, made when first asked for after a step (the
        display asks at its own rate, so frames it never shows cost no drawing); while a blow-up
        is shown the positions are clamped to a box around the scene (no NaN is drawn)."""
        with self.lock:
            if self._stale:
                try:
                    data = self.scene.frame_data()
                    if self._clamping:  # a blow-up shown, and its last picture while paused
                        data = self._clamped(data)
                    self._items = self.sink.draw(data, self.frame)
                except ValueError as exc:  # e.g. NaN positions the simulator's check has not caught
                    self._fail(exc, self.frame)
                self._stale = False
            return self._items

    def _clamped(self, data):
        """Frame data with every point array made finite and pulled radially into a sphere around
        the frame-0 drawing (radius 4 x its size: an exploding state is drawn flying outwards,
        never as NaN; a point gone NaN stays where it was last drawn)."""
        lo, hi = self._bounds
        center = 0.5 * (lo + hi)
        radius = 4.0 * max(float(np.linalg.norm(hi - lo)), 0.1)
        out = {}
        for name, prim in data.items():
            prim = dict(prim)
            for key in ("points", "velocities"):
                value = prim.get(key)
                if value is None:
                    continue
                arr = np.asarray(value.numpy() if hasattr(value, "numpy") else value, dtype=np.float64)
                if key == "points" and arr.ndim == 2 and arr.shape[-1] == 3:
                    d = arr - center
                    with np.errstate(invalid="ignore", over="ignore"):
                        r = np.linalg.norm(d, axis=1)
                        d = d * np.minimum(1.0, radius / np.maximum(r, 1e-30))[:, None]
                    arr = center + d
                    bad = ~np.isfinite(arr).all(axis=1)
                    last = self._last_drawn.get(name)
                    arr[bad] = last[bad] if last is not None and last.shape == arr.shape else center
                    self._last_drawn[name] = arr.copy()
                else:
                    arr = np.clip(np.nan_to_num(arr), -1.0e3, 1.0e3)
                prim[key] = arr.astype(np.float32)
            out[name] = prim
        return out

    def _fail(self, exc, frame):
        self.playing = False
        self.exploding = None
        if self.failed_at is None:
            self.failed_at = (frame, self.time)
        self.error = f"frame {frame}: {exc}" if not str(exc).startswith("frame") else str(exc)
        limit = self.limit
        if limit is not None and math.isfinite(limit.dt):
            self.error += (f"  \nStability limit: a step <= {1e3 * limit.dt:.4g} ms ({limit.who()}); this run stepped "
                           f"{1e3 * self.step_dt:.4g} ms. Reset restarts from the last stable parameters.")
        self._say("error", self.error)
        self._close_recording("the simulation failed")

    def _explode(self, exc, frame):
        """Start showing a blow-up: keep stepping with the checks off for EXPLOSION_FRAMES frames."""
        sim = getattr(self.scene, "sim", None)
        if EXPLOSION_FRAMES < 1 or not isinstance(exc, SimulationError) or not hasattr(sim, "check_every"):
            self._fail(exc, frame)
            return
        sim.check_every = 0  # the build after Reset makes a fresh simulator
        if self.grabbed is not None:  # let go: no drag line left pointing at a run that stopped
            self.drag.release()
            self.grabbed = None
        self.failed_at = (frame, self.time + self.frame_dt)
        self.exploding = {"error": exc, "frame": frame, "left": EXPLOSION_FRAMES,
                          "until": time.perf_counter() + EXPLOSION_SECONDS}
        self._last_drawn = {name: it.points.reshape(-1, 3).astype(np.float64) for name, it in self._items.items()
                            if it.kind in ("points", "mesh") and it.shown is None}  # the last good picture
        self._clamping = True
        self._say("error", f"frame {frame}: the simulation blew up; showing it for {EXPLOSION_FRAMES} frames")

    def _advance_exploding(self):
        ex = self.exploding
        try:  # in slow motion: one step per drawn frame, so the growth is seen before it overflows
            sim = getattr(self.scene, "sim", None)
            if hasattr(sim, "step"):
                sim.step(self.step_dt or self.frame_dt / self.substeps)
            else:
                self.scene.advance(self.frame_dt, self.substeps)
        except Exception:  # noqa: BLE001  (whatever a NaN state raises, the explosion ends here)
            ex["left"] = 0
        self.frame += 1
        self.time += self.frame_dt
        self._stale = True
        ex["left"] -= 1
        if ex["left"] <= 0 or time.perf_counter() >= ex["until"]:  # a moment: frames or wall time, the first
            self._fail(ex["error"], ex["frame"])
        return True

    def advance(self, interruptible=False):
        """Simulate one frame (recorded when recording); on a SimulationError show the explosion
        for EXPLOSION_FRAMES frames, then pause and keep the message (returns False when nothing
        was made). Returns True when a frame was made. ``interruptible`` (the viewer's stepping
        loop): a Pause stops it between sub-steps (False; the next call finishes the frame)."""
        with self.lock:
            if self.error is not None:
                return False
            if self.exploding is not None:
                return self._advance_exploding()
            t0 = time.perf_counter()
            try:
                if not self._advance_scene(interruptible):
                    return False  # paused between sub-steps: the frame goes on from there
                if self.recorder is not None:
                    self.recorder.write(self.scene.frame_data())
            except (SimulationError, ValueError, FloatingPointError) as exc:
                self._close_recording("the simulation failed")
                self._explode(exc, self.frame + 1)
                return self.exploding is not None
            self._frames_since_change += 1
            if self._frames_since_change == STABLE_FRAMES:
                self.stable_params = dict(self.params)
            self.frame += 1
            self.time += self.frame_dt
            self._stale = True
            ms = 1e3 * (time.perf_counter() - t0)
            self.wall_ms = ms if self.wall_ms == 0.0 else 0.8 * self.wall_ms + 0.2 * ms
            return True

    def _advance_scene(self, interruptible):
        """Simulate the frame: a scene stepped as ``SimulatorScene.advance`` steps it (its sub-steps,
        then the frame check) checks the Pause flag between sub-steps and keeps how many it took,
        so a slow frame (mass 0.001: seconds) pauses at once and resumes where it stopped, taking
        the same steps as one uninterrupted frame. False when paused (``interruptible``) before the
        frame's end."""
        from ..scenes import SimulatorScene

        scene = self.scene
        if type(scene).advance is not SimulatorScene.advance:  # a scene with a frame of its own
            scene.advance(self.frame_dt, self.substeps)
            return True
        n = scene.frame_steps(self.frame_dt, self.substeps)
        h = self.frame_dt / n
        while self._substeps_done < n:
            if interruptible and not self.playing:
                return False
            scene.sim.step(h)
            self._substeps_done += 1
        self._substeps_done = 0
        scene.sim.check_frame(self.frame_dt)
        return True

    def redraw(self):
        """Draw the scene's current state as the next frame without stepping it (a simulator
        that the caller steps: ``ws.Viewer(sim).update()``)."""
        with self.lock:
            self.frame += 1
            self._stale = True
            if self.recorder is not None:
                self.recorder.write(self.scene.frame_data())

    def frame_period(self):
        """Wall seconds one frame should take at the asked speed (0: as fast as possible)."""
        return 0.0 if not math.isfinite(self.speed) else self.frame_dt / self.speed

    def measure(self, frames, seconds):
        """Record the achieved rate: ``frames`` frames in ``seconds`` wall seconds, smoothed over
        about half a wall second (a frame that takes longer replaces the estimate outright: the
        readout follows a parameter change at once, not after many slow frames)."""
        if seconds > 0:
            rate = frames * self.frame_dt / seconds
            weight = 1.0 - math.exp(-seconds / 0.5)
            self.sim_rate = rate if self.sim_rate == 0.0 else (1.0 - weight) * self.sim_rate + weight * rate

    def set_playing(self, playing):
        """Play or pause without waiting for the frame being simulated (no lock: the stepping loop
        reads the flag between sub-steps, see ``_advance_scene``)."""
        self.playing = bool(playing) and self.error is None

    def step_once(self):
        """Pause and advance exactly one frame (the rest of one a Pause interrupted)."""
        with self.lock:
            self.playing = False
            return self.advance()

    # ------------------------------------------------------------------ parameters
    def shown(self, key):
        """``key = value unit`` of the value the session runs with, as the panel shows it (``dt``
        in ms, as its slider)."""
        return format_param(key, self.cls.params[key], self.params[key])

    def set_param(self, key, value):
        """Change a scene parameter: ``"live"`` when applied to the running simulation,
        ``"rebuilt"`` when the scene was rebuilt for it, ``"unchanged"``. ValueError naming the
        parameter for an unknown key or a bad value (the old value stays)."""
        with self.lock:
            if key not in self.cls.params:
                raise ValueError(f"scene {self.cls.name!r} has no parameter {key!r}; its parameters are "
                                 f"{', '.join(self.cls.params)}")
            param = self.cls.params[key]
            if isinstance(value, str) and not isinstance(param.default, str):
                value = parse_value(param, key, value)
            elif isinstance(param.default, bool):
                value = bool(value)
            elif isinstance(param.default, int):
                value = round(float(value))
            elif isinstance(param.default, float):
                value = float(value)
            elif isinstance(param.default, tuple):
                value = tuple(float(v) for v in value)
            if param.choices is not None and value not in param.choices:
                raise ValueError(f"{key}={value!r} is not one of {', '.join(map(str, param.choices))}")
            if self.params.get(key) == value:
                return "unchanged"
            if key == "dt":
                self.dt_by_hand = True  # the step fixed by hand: no automatic sub-steps
            if self.error is None and self.exploding is None and self.scene.set_param(key, value):
                self.params[key] = value
                self._frames_since_change = 0
                self._update_limit()
                self._say("info", f"{self.shown(key)}: applied live")
                return "live"
            old = self.params[key]
            self.params[key] = value
            try:
                self._build()
            except ValueError as exc:
                self.params[key] = old
                self._build()
                raise ValueError(f"{key}={value!r}: {exc}") from None
            self._say("info", f"{self.shown(key)}: the scene was rebuilt (not a live parameter)")
            return "rebuilt"

    # ------------------------------------------------------------------ dragging
    def _grabbable(self, prim):
        """(particle index per drawn vertex, bool grabbable per drawn vertex) of a drawn prim."""
        item = self.items.get(prim)
        mapping = self.drag_map.get(prim)
        n = 2 * len(item.points) if item.kind == "segments" else len(item.points)
        particles = np.arange(n) if mapping is None else np.asarray(mapping)
        if item.shown is not None:
            particles = particles[item.shown]
        inv_mass = self.scene.sim.model.particle_inv_mass.numpy()
        return particles, inv_mass[particles] > 0.0

    def _default_drag(self):
        """Drag spring (stiffness [N/m], damping [N s/m]): the model's median spring stiffness
        (a grabbed vertex follows about as firmly as its neighbours hold it) or, without springs,
        the scene's ``drag_stiffness_hint`` (hair) or m (0.5 / h)^2; explicit integrators are
        capped at m (0.5 / h)^2 so omega h <= 0.5."""
        model = self.scene.sim.model
        inv = model.particle_inv_mass.numpy()
        m = float(np.mean(1.0 / inv[inv > 0])) if (inv > 0).any() else 1.0
        h = self.frame_dt / self.substeps
        cap = m * (0.5 / h) ** 2
        k = float(np.median(model.spring_stiffness.numpy())) if model.spring_count else \
            float(getattr(self.scene, "drag_stiffness_hint", None) or cap)  # e.g. hair: its stretch springs
        implicit = "implicit" in type(self.scene.sim.integrator).__name__.lower() and \
            "semi" not in type(self.scene.sim.integrator).__name__.lower()
        if self.drag_stiffness is not None:
            k = float(self.drag_stiffness)
        elif not implicit:
            k = min(k, cap)
        return k, math.sqrt(k * m)  # half of critical damping 2 sqrt(k m)

    def pick(self, prim, ray_origin, ray_direction):
        """Drawn vertex of ``prim`` under the ray (-1: none): a triangle hit for meshes, the
        nearest point within 3 drawn radii for points, and for curves (``segments``: drawn
        vertex 2 s + e is end e of segment s) the nearest segment end."""
        with self.lock:
            item = self.items.get(prim)
            if item is None or prim not in self.drag_map:
                return -1
            _, ok = self._grabbable(prim)
            if item.kind == "mesh":
                return pick_mesh_vertex(ray_origin, ray_direction, item.points, item.triangles, ok)
            points = item.points.reshape(-1, 3) if item.kind == "segments" else item.points
            return pick_point(ray_origin, ray_direction, points, 3.0 * max(item.radius, 1e-3) + 0.02, ok)

    def grab(self, prim, vertex, client=None):
        """Grab drawn vertex ``vertex`` of ``prim``: a DragSpring holds its particle where it is
        until :meth:`drag_to` moves the target. Returns the particle index (-1: not grabbable)."""
        with self.lock:
            if self.error is not None or prim not in self.drag_map or vertex < 0:
                return -1
            particles, ok = self._grabbable(prim)
            if not (0 <= vertex < len(particles)) or not ok[vertex]:
                return -1
            particle = int(particles[vertex])
            k, c = self._default_drag()
            if self.drag is None:
                self.drag = DragSpring(k, c)
                self.scene.add_drag(self.drag)
            self.drag.stiffness, self.drag.damping = k, c
            x = self.scene.sim.state.positions.numpy()[particle].astype(np.float64)
            self.drag.grab(particle, x)
            if hasattr(self.scene.sim, "invalidate_stability"):
                self.scene.sim.invalidate_stability()  # the drag spring is an oscillator of its own
            self.grabbed = {"prim": prim, "vertex": int(vertex), "particle": particle, "start": x.copy(),
                            "target": x.copy(), "plane_point": x.copy(), "client": client}
            return particle

    def drag_to(self, target):
        """Move the grabbed particle's target to ``target`` [m]."""
        with self.lock:
            if self.grabbed is None:
                return
            target = np.asarray(target, np.float64).reshape(3)
            if not np.isfinite(target).all():
                return
            self.drag.set_target(target)
            self.grabbed["target"] = target

    def drag_ray(self, ray_origin, ray_direction, view_direction):
        """Move the target to where the pointer's ray meets the camera-facing plane through the
        point grabbed (its position at the grab)."""
        with self.lock:
            if self.grabbed is None:
                return None
            target = camera_plane_target(ray_origin, ray_direction, self.grabbed["plane_point"], view_direction)
            self.drag_to(target)
            return target

    def release(self, client=None):
        """Let go (only ``client``'s grab when given: a disconnecting browser releases its own)."""
        with self.lock:
            if self.grabbed is None or (client is not None and self.grabbed.get("client") != client):
                return False
            self.drag.release()
            self.grabbed = None
            return True

    def grabbed_position(self):
        """Current position [m] of the grabbed particle (None when nothing is grabbed)."""
        with self.lock:
            if self.grabbed is None:
                return None
            return self.scene.sim.state.positions.numpy()[self.grabbed["particle"]].astype(np.float64)

    # ------------------------------------------------------------------ recording
    def start_recording(self, path=None):
        """Record from the frame shown now into ``path`` (default ``usd_out/<scene>_view_<time>.usda``)."""
        with self.lock:
            if self.recorder is not None:
                return self.recorder.path
            path = path or default_recording_path(self.cls.name, self.record_dir)
            self.recorder = Recorder(self.scene, path, self.fps)
            self.recorder.write(self.scene.frame_data())
            self._say("info", f"recording into {path}")
            return self.recorder.path

    def stop_recording(self):
        """Complete the recording; returns the path of the cache (None if none was running)."""
        with self.lock:
            return self._close_recording(None)

    def _close_recording(self, why):
        rec, self.recorder = getattr(self, "recorder", None), None
        if rec is None:
            return None
        path = rec.close()
        self.last_recording = path
        self._say("info", f"recorded {rec.frames} frames into {path}" + (f" ({why})" if why else ""))
        return path

    def close(self):
        """Stop: complete any recording."""
        with self.lock:
            self._close_recording("the viewer stopped")

    # ------------------------------------------------------------------ reporting
    def _say(self, kind, text):
        self.messages.append((kind, text))
        del self.messages[:-20]

    def status(self):
        """Frame, simulated time [s], wall ms per frame, simulated s per wall s, and state flags. After
        a blow-up, the frame and time are where it blew up (those the error names), also while the
        explosion is shown past it."""
        with self.lock:
            frame, t = self.failed_at if self.failed_at is not None else (self.frame, self.time)
            return {"scene": self.cls.name, "frame": frame, "time": t, "wall_ms": self.wall_ms,
                    "draw_ms": self.draw_ms,
                    "sim_rate": self.sim_rate, "playing": self.playing, "speed": self.speed, "error": self.error,
                    "exploding": self.exploding is not None,
                    "recording": None if self.recorder is None else self.recorder.path,
                    "recorded_frames": 0 if self.recorder is None else self.recorder.frames,
                    "grabbed": None if self.grabbed is None else dict(self.grabbed)}
