"""The viser front end: :class:`Viewer` (``ws.Viewer``) serves a running scene to the browser.

:class:`Drawer` turns :class:`~warpsim.viewer.sink.DrawItem`\\ s into viser scene nodes
(meshes, point clouds or, for grabbable particles, instanced spheres that take clicks, line
segments (grabbable curves, e.g. hair, also as invisible ribbons that take clicks: the pick is the
curve point nearest the pointer's ray), instanced prototypes) and updates them in place each
frame. :class:`Viewer` owns a
:class:`~warpsim.viewer.session.Session`, a stepping thread paced to the asked speed, the
panels (``controls``, ``params``) and the mouse: a left drag on a grabbable mesh or particle
grabs the vertex under the pointer (a ray cast from the camera) and moves the drag spring's
target to where the pointer's ray meets the camera-facing plane through the grabbed point.
"""
from __future__ import annotations

import socket
import threading
import time

import numpy as np

from .geometry import icosphere
from .pace import THIN_SEGMENTS, ClientPace, thin_strands
from .picking import pointer_ray, segment_ribbon_triangles, segment_ribbons
from .serving import Serving
from .session import Session
from .sink import DrawItem

__all__ = ["Drawer", "PortInUseError", "Viewer", "check_port"]

PICKABLE_POINTS = 4096  # grabbable points prims up to this size are drawn as clickable spheres
RIBBON_PERIOD = 1.0  # [s] between updates of the invisible ribbons that take clicks on grabbable curves
# (8 vertices a segment: 3 MB a frame for 2,000 strands x 16 segments; the pick itself reads the
# current curve points, the ribbons only have to be under the pointer)


class PortInUseError(OSError):
    """The asked port is taken; the message names a free one."""


def check_port(host, port):
    """Raise PortInUseError naming a free port when ``port`` on ``host`` cannot be bound."""
    def free(p):
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as the server binds: TIME_WAIT is free
            try:
                s.bind((host, p))
                return True
            except OSError:
                return False

    if not free(port):
        alt = next((p for p in range(port + 1, min(port + 200, 65536)) if free(p)), None)
        if alt is None:
            with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
                s.bind((host, 0))
                alt = s.getsockname()[1]
        raise PortInUseError(f"port {port} on {host} is in use; try --port {alt}")


def quiet_stdout(quiet=True):
    """Context: standard output dropped while ``quiet`` (viser prints a box with the address on every
    start, ``verbose`` or not; ``warpsim view`` says the URL itself)."""
    import contextlib
    import io

    return contextlib.redirect_stdout(io.StringIO()) if quiet else contextlib.nullcontext()


def _rgb(color):
    return tuple(round(255 * min(max(float(c), 0.0), 1.0)) for c in color)


class Drawer:
    """Keeps viser scene nodes in step with a dict of DrawItems. ``on_drag(prim, event)`` is
    called for drags on the prims named in ``draggable``. One draw at a time: the stepping loop and
    a button's handler (Reset, Step) may draw at once, and a node one removes the other must not
    hook."""

    def __init__(self, server, on_drag=None):
        self.server = server
        self.on_drag = on_drag
        self.nodes = {}  # name -> (handle or list of handles, signature)
        self._ribbons_sent = {}  # name -> time [s] the click ribbons of grabbable curves were last sent
        self.static_nodes = []
        self.version = None
        self.thin = 1
        """Draw one curve in ``thin`` of curve sets longer than THIN_SEGMENTS segments (and take clicks
        on those drawn: their ribbons are most of what a frame sends)."""
        self._sphere = icosphere(1)
        self._drawing = threading.Lock()

    def clear(self):
        for node, _ in self.nodes.values():
            for h in node if isinstance(node, list) else [node]:
                h.remove()
        for h in self.static_nodes:
            h.remove()
        self.nodes, self.static_nodes = {}, []

    def draw(self, items, static, version, draggable=()):
        """Show ``items`` (dynamic) and, after a rebuild (new ``version``), ``static``."""
        with self._drawing, self.server.atomic():
            if version != self.version:
                self.clear()
                self.version = version
                for name, item in static.items():
                    if len(item.points) and len(item.triangles):
                        self.static_nodes.append(self.server.scene.add_mesh_simple(
                            f"/static/{name}", item.points, item.triangles, color=_rgb(item.color), side="double",
                            cast_shadow=False, receive_shadow=False,
                            opacity=None if item.opacity is None else max(item.opacity, 0.1)))
            for name, item in items.items():
                self._update(name, item, name in draggable)

    def _drag_hook(self, handle, name):
        if self.on_drag is None:
            return

        async def cb(event):
            self.on_drag(name, event)

        handle.on_drag("left")(cb)

    @staticmethod
    def _ribbon_width(item):
        """Half width [m] of the invisible ribbons a click on grabbable curves hits: 3 drawn radii
        and at least 3 mm (thin hair is a few pixels wide)."""
        return max(3.0 * item.radius, 3.0e-3)

    def _update(self, name, item, draggable):
        path = f"/scene/{name}"
        n = len(item.points)
        if item.kind == "mesh":
            sig = ("mesh", item.topology, n)
        elif item.kind == "points":
            sig = ("spheres" if draggable and n <= PICKABLE_POINTS else "cloud", n)
        elif item.kind == "segments":  # a thinned long set is a new node (its click ribbons are fewer)
            sig = ("pick_segments" if draggable else "segments", n, self.thin if n > THIN_SEGMENTS else 1)
        else:
            sig = ("instances", n, tuple(np.bincount(item.proto, minlength=len(item.prototypes))) if n else ())
        known = self.nodes.get(name)
        if known is not None and known[1] != sig:
            for h in known[0] if isinstance(known[0], list) else [known[0]]:
                h.remove()
            known = None
        empty = n == 0 or (item.kind == "mesh" and len(item.triangles) == 0)
        if known is None:
            if empty:
                self.nodes[name] = ([], sig)
                return
            self.nodes[name] = (self._add(path, item, sig, draggable, name), sig)
            return
        handle = known[0]
        if empty:
            return
        if sig[0] == "mesh":
            handle.vertices = np.asarray(item.points, np.float32)
        elif sig[0] == "spheres":
            handle.batched_positions = np.asarray(item.points, np.float32)
        elif sig[0] == "cloud":
            handle.points = np.asarray(item.points, np.float32)
        elif sig[0] == "segments":
            handle.points = self._lines(item)
        elif sig[0] == "pick_segments":
            handle[0].points = self._lines(item)
            now = time.perf_counter()
            if now - self._ribbons_sent.get(name, 0.0) >= RIBBON_PERIOD:  # the click target lags a little
                self._ribbons_sent[name] = now
                handle[1].vertices = segment_ribbons(self._lines(item), self._ribbon_width(item))
        else:
            for k, h in enumerate(handle):
                sel = item.proto == k
                if sel.any():
                    h.batched_positions = np.asarray(item.points[sel], np.float32)
                    h.batched_wxyzs = np.asarray(item.orientations[sel], np.float32)

    def _lines(self, item):
        """The segments of a curves item to draw: one curve in :attr:`thin` of a long set."""
        points = np.asarray(item.points, np.float32)
        return thin_strands(points, self.thin) if len(points) > THIN_SEGMENTS else points

    def _add(self, path, item, sig, draggable, name):
        scene = self.server.scene
        color = _rgb(item.color)
        if sig[0] == "mesh":
            h = scene.add_mesh_simple(path, np.asarray(item.points, np.float32), item.triangles, color=color,
                                      side="double", cast_shadow=False, receive_shadow=False)
            if draggable:
                self._drag_hook(h, name)
            return h
        if sig[0] == "spheres":
            v, f = self._sphere
            r = max(item.radius, 1e-3)
            h = scene.add_batched_meshes_simple(
                path, v * r, f, np.tile([[1.0, 0.0, 0.0, 0.0]], (len(item.points), 1)),
                np.asarray(item.points, np.float32), batched_colors=color, lod="off",
                cast_shadow=False, receive_shadow=False)
            self._drag_hook(h, name)
            return h
        if sig[0] == "cloud":
            return scene.add_point_cloud(path, np.asarray(item.points, np.float32), color,
                                         point_size=2.0 * max(item.radius, 1e-3), point_shape="circle",
                                         precision="float32")
        if sig[0] == "segments":
            return scene.add_line_segments(path, self._lines(item), color, thickness=max(2.0 * item.radius, 1.5e-3))
        if sig[0] == "pick_segments":  # grabbable curves (hair): drawn as lines, clicked on a ribbon mesh
            shown = self._lines(item)
            lines = scene.add_line_segments(path, shown, color, thickness=max(2.0 * item.radius, 1.5e-3))
            ribbons = scene.add_mesh_simple(f"{path}_pick", segment_ribbons(shown, self._ribbon_width(item)),
                                            segment_ribbon_triangles(len(shown)), color=color, opacity=0.0,
                                            side="double", cast_shadow=False, receive_shadow=False)
            self._drag_hook(ribbons, name)
            return [lines, ribbons]
        handles = []
        for k, (v, f) in enumerate(item.prototypes):
            sel = item.proto == k
            if not sel.any():
                handles.append(_Nothing())
                continue
            handles.append(scene.add_batched_meshes_simple(
                f"{path}/proto{k}", v, f, np.asarray(item.orientations[sel], np.float32),
                np.asarray(item.points[sel], np.float32), batched_colors=color, lod="off",
                cast_shadow=False, receive_shadow=False))
        return handles


class _Nothing:
    """Stand-in for a prototype with no instances this frame."""

    def remove(self):
        pass


def check_serving_args(*, port, max_points, host, draw_fps=None, what="ws.Viewer"):
    """``(draw_fps, port, max_points)`` checked before anything is built or served: ValueError /
    TypeError naming the argument, the value and a fix."""
    from ..core import checks

    if not isinstance(host, str) or not host.strip():
        raise TypeError(f"{what} host must be a host name or address as text, got {checks.show(host)}; e.g. "
                        "host='127.0.0.1'")
    port = checks.integer(port, f"{what} port", lo=0, hi=65535, fix="e.g. 8080 (0: any free port)")
    max_points = checks.integer(max_points, f"{what} max_points", lo=1, fix="points drawn per prim, e.g. 200000")
    if draw_fps is not None:
        draw_fps = checks.positive(draw_fps, f"{what} draw_fps", unit="frames/s", fix="e.g. 45")
    return draw_fps, port, max_points


class Viewer(Serving):
    """A live browser view of a scene (``warpsim view``; ``ws.Viewer`` in scripts and notebooks).

    Args:
        scene: a scene name (``"teapot"``), a registered Scene class, a built Scene instance,
            or a ``ws.Simulator`` that the caller steps (then call :meth:`update` after steps).
        params: {key: value} for a scene given by name or class.
        device: Warp device (None: CUDA when present, else the CPU).
        host, port: where to serve (127.0.0.1 by default: this machine only).
        fps, substeps: as ``warpsim run``.
        max_points: points drawn per points prim (strided subset beyond).
        record_dir: folder of recordings.
        paused: start paused (else the scene starts when the first browser tab connects, so the
            first picture a user sees is frame 0).
        draw_fps: most frames per second sent to the browser (the simulation may run faster).
        environment: light the scene with viser's environment map too (prettier; a browser
            without a GPU renders a frame in seconds instead of milliseconds with it).

    ``start()`` serves in background threads and returns at once (``url`` says where);
    ``run()`` serves until interrupted; ``stop()`` ends it, completing any recording. Example::

        v = ws.Viewer("teapot", params={"stiffness": 80.0}, device="cpu").start()
        print(v.url)   # open it; drag the teapot
    """

    def __init__(self, scene, params=None, device=None, *, host="127.0.0.1", port=8080, fps=None, substeps=None,
                 max_points=200_000, record_dir="usd_out", paused=False, draw_fps=45.0, environment=False,
                 verbose=False):
        from ..scenes import Scene, get_scene

        draw_fps, port, max_points = check_serving_args(port=port, max_points=max_points, host=host,
                                                        draw_fps=draw_fps, what="ws.Viewer")
        if device is None:
            import warp as wp

            device = "cuda:0" if wp.is_cuda_available() else "cpu"
        self.user_driven = False
        instance = None
        if isinstance(scene, str):
            cls = get_scene(scene)
        elif isinstance(scene, type) and issubclass(scene, Scene):
            cls = scene
        elif isinstance(scene, Scene):
            cls, instance = type(scene), scene
        elif hasattr(scene, "state") and hasattr(scene, "model"):
            from .adapter import SimulatorAdapter

            instance = SimulatorAdapter(scene)
            cls = type(instance)
            self.user_driven = True
        else:
            raise ValueError(f"ws.Viewer: {scene!r} is not a scene name, Scene class or instance, or ws.Simulator")
        if params is not None and not isinstance(params, dict):
            raise TypeError(f"ws.Viewer params must be a dict of parameter values, got {params!r}; e.g. "
                            "params={'stiffness': 80.0}")
        self.session = Session(cls, params, device, fps=fps, substeps=substeps, max_points=max_points,
                               record_dir=record_dir, scene=instance)
        if paused or self.user_driven:
            self.session.playing = False
        self.host, self.port, self.verbose = host, int(port), verbose
        self.server = None
        self._stop = threading.Event()
        self._thread = None
        self._drawn_frame = None
        self._drawn_at = 0.0
        self._redrawing = threading.Lock()  # the loop and a button's handler: one capture-and-draw at a time
        self._play_on_connect = False  # set by start() unless paused: the first tab starts the scene
        self.draw_count = 0  # frames sent to the browser
        self.draw_fps = float(draw_fps)
        self.environment = bool(environment)
        self.pace = None
        """The pages' round trips (:class:`~warpsim.viewer.pace.ClientPace`) when the scene draws long
        curve sets, else None."""
        self._first_frame_done = False

    @property
    def url(self):
        return f"http://{self.host}:{self.port}"

    # ------------------------------------------------------------------ serving
    def start(self):
        """Start serving (raises PortInUseError naming a free port when the port is taken)."""
        import viser

        from .controls import Controls
        from .params import build_param_panel

        check_port(self.host, self.port)
        with quiet_stdout(not self.verbose):  # viser's address box: the caller says the URL once
            self.server = viser.ViserServer(host=self.host, port=self.port, label="warpsim", verbose=self.verbose)
        self.server.scene.set_up_direction("+y")
        self.server.scene.configure_default_lights(True, cast_shadow=False)  # shadow maps cost most frames
        if not self.environment:  # image-based lighting re-renders its maps: slow in software WebGL
            self.server.scene.configure_environment_map(None)
        self._frame_camera()
        self.drawer = Drawer(self.server, on_drag=self._on_drag)
        self.controls = Controls(self)
        if self.session.cls.params:
            with self.server.gui.add_folder("Parameters"):
                self.param_handles = build_param_panel(self.server.gui, self.session, self._param_result)
        self.server.on_client_disconnect(self._on_disconnect)
        if not self.user_driven and self.session.playing:  # frame 0 waits for the first tab
            self._play_on_connect = True
            self.session.playing = False
            self.controls.play.label = "Play"
        self.server.on_client_connect(self._on_connect)
        if any(it.kind == "segments" and len(it.points) > THIN_SEGMENTS for it in self.session.items.values()):
            self.pace = ClientPace(self.server)  # long curve sets (hair): thinned while a page lags
        self.redraw()
        self._thread = threading.Thread(target=self._loop, name="warpsim-viewer", daemon=True)
        self._thread.start()
        return self

    def _frame_camera(self):
        """Point new clients' cameras at the subject over where it can go (see viewer.framing)."""
        from .framing import camera_pose, live_bounds

        s = self.session
        position, look_at = camera_pose(live_bounds(s.items, s.static))
        self.server.initial_camera.look_at = tuple(float(v) for v in look_at)
        self.server.initial_camera.position = tuple(float(v) for v in position)
        self.server.initial_camera.up = (0.0, 1.0, 0.0)

    def stop(self):
        """Stop stepping and serving; any recording is completed first."""
        self._stop.set()
        if self.pace is not None:
            self.pace.stop()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=5.0)
        self.session.close()
        if self.server is not None:
            with quiet_stdout(not self.verbose):  # viser's "Server stopped"
                self.server.stop()
            self.server = None

    # ------------------------------------------------------------------ frames
    def redraw(self):
        """Send the session's current frame to the browser."""
        with self._redrawing:  # in order: a frame captured before a Reset is never drawn after it
            self._redraw()

    def _redraw(self):
        s = self.session
        t0 = time.perf_counter()
        with s.lock:
            items, static, version, frame = dict(s.items), s.static, s.version, s.frame
            draggable = set(s.drag_map) & set(items)
            if s.grabbed is not None:  # the mouse's spring: grabbed particle -> target, drawn on top
                seg = np.stack([s.grabbed_position(), s.grabbed["target"]]).astype(np.float32)[None]
                items["_mouse_drag"] = DrawItem("_mouse_drag", "segments", seg, (0.9, 0.2, 0.1), radius=0.002)
            else:
                items["_mouse_drag"] = DrawItem("_mouse_drag", "segments", np.zeros((0, 2, 3), np.float32))
        # a page behind: one strand in `step` of the long curve sets drawn (the panel says so)
        self.drawer.thin = self.pace.step if self.pace is not None else 1
        if self.server is not None:
            self.drawer.draw(items, static, version, draggable)
        self._drawn_frame = (version, frame)
        self._drawn_at = time.perf_counter()
        if self.pace is not None:
            self.pace.sent(self._drawn_at)
        self.draw_count += 1
        ms = 1e3 * (self._drawn_at - t0)
        s.draw_ms = ms if s.draw_ms == 0.0 else 0.8 * s.draw_ms + 0.2 * ms

    def update(self):
        """Redraw a ``ws.Simulator`` the caller steps (``ws.Viewer(sim)``); call ``start()`` first."""
        if self.server is None:
            raise RuntimeError("ws.Viewer.update() before start(): call viewer.start() once, then update() after "
                               "each step you want drawn")
        self.session.redraw()
        self.redraw()
        self.controls.refresh()

    def _loop(self):
        s = self.session
        last_refresh = 0.0
        while not self._stop.is_set():
            t0 = time.perf_counter()
            stepped = False
            if s.playing and not self.user_driven:
                if not self._first_frame_done:  # said before the first step: it compiles kernels
                    self.controls.starting()
                stepped = s.advance(interruptible=True)  # a Pause stops it between sub-steps
                self._first_frame_done = self._first_frame_done or stepped
            due = time.perf_counter() - self._drawn_at >= 1.0 / self.draw_fps or not s.playing
            if (s.version, s.frame) != self._drawn_frame and due:
                try:
                    self.redraw()
                except Exception as exc:  # noqa: BLE001  (a drawing failure must not stop the server)
                    s.error = s.error or f"drawing failed: {exc}"
                    s.playing = False
            now = time.perf_counter()
            if now - last_refresh > 0.25:
                self.controls.refresh()
                last_refresh = now
            if stepped:
                wait = s.frame_period() - (time.perf_counter() - t0)
                if wait > 0:
                    self._stop.wait(wait)
                s.measure(1, time.perf_counter() - t0)
            else:
                self._stop.wait(0.02)

    # ------------------------------------------------------------------ input
    def _param_result(self, key, outcome, ok):
        value = f"`{self.session.shown(key)}`"  # the value it runs with, as the input shows it
        if ok:
            text = {"live": f"{value} applied live", "rebuilt": f"{value}: the scene was rebuilt (not live)",
                    "unchanged": f"{value} unchanged"}[outcome]
        else:
            text = f"`{key}` not changed (still {value}): {outcome}"
        self.controls.say(text)
        self.redraw()

    def _on_drag(self, prim, event):
        s = self.session
        cam = event.client.camera
        eye = np.asarray(cam.position, np.float64)
        view = np.asarray(cam.look_at, np.float64) - eye
        if event.phase == "start":
            if event.instance_index is not None and s.items.get(prim) is not None and \
                    s.items[prim].kind == "points":
                vertex = int(event.instance_index)
            else:
                origin, direction = pointer_ray(eye, event.start_position)
                vertex = s.pick(prim, origin, direction)
            s.grab(prim, vertex, client=event.client_id)
        elif event.phase == "update":
            origin, direction = pointer_ray(eye, event.end_position)
            s.drag_ray(origin, direction, view)
        else:
            s.release(client=event.client_id)

    def _on_connect(self, client):
        """The first tab starts the scene (from frame 0, unless ``paused``); every tab gets the
        error notification while there is one."""
        if self._play_on_connect:
            self._play_on_connect = False
            self.session.set_playing(True)
            self.controls.play.label = "Pause"
        self.controls.on_connect(client)

    def _on_disconnect(self, client):
        self.controls.on_disconnect(client)
        self.session.release(client=client.client_id)  # a tab closed mid-drag lets go
        if self.server is not None and not self.server.get_clients():
            self.session.stop_recording()  # the last tab closed: complete the recording
