"""Playing a warpsim USD cache in the browser (``warpsim view CACHE.usd``).

:class:`CacheReader` opens any warpsim cache (a root layer with value clips over chunk files,
or a flattened file) and reads one frame at a time on demand (``items(frame)``): opening a long
cache costs only the stage composition, not its frames. Prims become the same
:class:`~warpsim.viewer.sink.DrawItem`\\ s the live viewer draws. :class:`PlaybackViewer` adds a
timeline slider, play / pause and loop.
"""
from __future__ import annotations

import threading
import time

import numpy as np

from ..usd.prims import segment_pairs
from .geometry import curve_segments, subsample, triangulate, unit_mesh, xyzw_to_wxyz
from .serving import Serving
from .sink import DrawItem

__all__ = ["DYNAMIC_TYPES", "CacheReader", "PlaybackViewer"]

DYNAMIC_TYPES = ("Points", "Mesh", "BasisCurves", "PointInstancer")
_GPRIMS = ("Sphere", "Cube", "Cone", "Capsule", "Cylinder")


def _opacity(prim):
    from pxr import UsdGeom

    pv = UsdGeom.PrimvarsAPI(prim).GetPrimvar("displayOpacity")
    value = pv.Get() if pv else None
    return float(value[0]) if value is not None and len(value) == 1 else None


def _color(prim, default):
    from pxr import UsdGeom

    pv = UsdGeom.PrimvarsAPI(prim).GetPrimvar("displayColor")
    value = pv.Get() if pv else None
    if value is not None and len(value):
        return tuple(float(c) for c in value[0])
    return default


class CacheReader:
    """Frames of a warpsim cache read on demand (see module docstring). ValueError when the
    file is missing or does not open."""

    def __init__(self, path, max_points=None):
        from pxr import UsdGeom

        from ..usd.validate import frame_codes, open_stage

        self.stage = open_stage(path)
        self.path = str(path)
        self.frames = frame_codes(self.stage)
        self.fps = float(self.stage.GetTimeCodesPerSecond() or 24.0)
        self.max_points = max_points
        self.dynamic, self.static = [], {}
        for prim in self.stage.Traverse():
            t = prim.GetTypeName()
            if "Prototypes" in str(prim.GetPath()):
                continue  # drawn through their instancer
            name = prim.GetName()
            if t in DYNAMIC_TYPES:
                attr = prim.GetAttribute("positions" if t == "PointInstancer" else "points")
                if attr.ValueMightBeTimeVarying() or t == "PointInstancer":
                    self.dynamic.append(prim)
                else:
                    item = self._item(prim, 0.0 if not self.frames else float(self.frames[0]))
                    if item is not None:
                        item.static = True
                        item.opacity = _opacity(prim)
                        self.static[name] = item
            elif t in _GPRIMS:
                attrs = {a.GetName(): a.Get() for a in prim.GetAttributes()}
                v, f = unit_mesh(t, attrs)
                m = np.asarray(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(0.0), np.float64)
                pts = (np.c_[v, np.ones(len(v))] @ m)[:, :3].astype(np.float32)
                self.static[name] = DrawItem(name, "mesh", pts, _color(prim, (0.6, 0.6, 0.6)), triangles=f,
                                             static=True, opacity=_opacity(prim))
        self.version = 1

    def __len__(self):
        return len(self.frames)

    def items(self, index):
        """{name: DrawItem} of the animated prims at frame ``frames[index]`` (read now)."""
        code = float(self.frames[index]) if self.frames else 0.0
        out = {}
        for prim in self.dynamic:
            item = self._item(prim, code)
            if item is not None:
                out[prim.GetName()] = item
        return out

    def _item(self, prim, code):
        t = prim.GetTypeName()
        name = prim.GetName()
        if t == "Points":
            pts = np.asarray(prim.GetAttribute("points").Get(code) or [], np.float32).reshape(-1, 3)
            widths = prim.GetAttribute("widths").Get(code)
            radius = 0.5 * float(np.mean(widths)) if widths is not None and len(widths) else 0.01
            pairs = segment_pairs(prim)  # a sweep's springs: curves drawn from the particles' points
            if pairs is not None and (not len(pairs) or pairs.max() < len(pts)):
                return DrawItem(name, "segments", pts[pairs], _color(prim, (0.35, 0.35, 0.35)), radius=radius)
            shown = subsample(len(pts), self.max_points)
            return DrawItem(name, "points", pts if shown is None else pts[shown], _color(prim, (0.2, 0.5, 0.9)),
                            radius=radius, shown=shown)
        if t == "Mesh":
            pts = np.asarray(prim.GetAttribute("points").Get(code) or [], np.float32).reshape(-1, 3)
            counts = np.asarray(prim.GetAttribute("faceVertexCounts").Get(code) or [], np.int64)
            idx = np.asarray(prim.GetAttribute("faceVertexIndices").Get(code) or [], np.int64)
            return DrawItem(name, "mesh", pts, _color(prim, (0.75, 0.75, 0.8)), triangles=triangulate(counts, idx),
                            topology=hash((len(counts), len(idx), int(idx.sum()) if len(idx) else 0)),
                            opacity=_opacity(prim))  # see-through containers, also in the sweep gallery
        if t == "BasisCurves":
            pts = np.asarray(prim.GetAttribute("points").Get(code) or [], np.float32).reshape(-1, 3)
            counts = prim.GetAttribute("curveVertexCounts").Get(code)
            widths = prim.GetAttribute("widths").Get(code)
            radius = 0.5 * float(widths[0]) if widths is not None and len(widths) else 0.0025
            return DrawItem(name, "segments", curve_segments(pts, counts or []), _color(prim, (0.35, 0.35, 0.35)),
                            radius=radius)
        if t == "PointInstancer":
            from pxr import UsdGeom

            inst = UsdGeom.PointInstancer(prim)
            pos = np.asarray(inst.GetPositionsAttr().Get(code) or [], np.float32).reshape(-1, 3)
            ori = inst.GetOrientationsAttr().Get(code)
            ori = xyzw_to_wxyz(np.array([[q.GetImaginary()[0], q.GetImaginary()[1], q.GetImaginary()[2], q.GetReal()]
                                         for q in ori], np.float32)) if ori else \
                np.tile(np.array([[1.0, 0, 0, 0]], np.float32), (len(pos), 1))
            proto = np.asarray(inst.GetProtoIndicesAttr().Get(code) or np.zeros(len(pos)), np.int64)
            protos, color = [], (0.9, 0.55, 0.2)
            for target in inst.GetPrototypesRel().GetTargets():
                p = self.stage.GetPrimAtPath(target)
                attrs = {a.GetName(): a.Get() for a in p.GetAttributes()}
                protos.append(unit_mesh(p.GetTypeName(), attrs))
                color = _color(p, color)
            return DrawItem(name, "instances", pos, color, orientations=ori, proto=proto, prototypes=protos)
        return None


class PlaybackViewer(Serving):
    """Serves a cache: timeline slider, play / pause, loop; frames read when shown."""

    def __init__(self, path, *, host="127.0.0.1", port=8080, max_points=200_000):
        from .server import check_serving_args

        _, port, max_points = check_serving_args(port=port, max_points=max_points, host=host,
                                                 what="PlaybackViewer")
        self.reader = CacheReader(path, max_points=max_points)
        self.host, self.port = host, int(port)
        self.index = 0
        self.playing = True
        self.loop = True
        self.server = None
        self._stop = threading.Event()
        self._shown = None

    @property
    def url(self):
        return f"http://{self.host}:{self.port}"

    def start(self):
        import viser

        from .server import Drawer, check_port, quiet_stdout

        check_port(self.host, self.port)
        with quiet_stdout():  # viser's address box: ``warpsim view`` says the URL itself
            self.server = viser.ViserServer(host=self.host, port=self.port, label="warpsim playback", verbose=False)
        self.server.scene.set_up_direction("+y")
        self.server.scene.configure_default_lights(True, cast_shadow=False)
        self.server.scene.configure_environment_map(None)
        self.drawer = Drawer(self.server)
        from .framing import camera_pose, playback_bounds

        position, look_at = camera_pose(playback_bounds(self.reader))  # the subject over the whole cache
        self.server.initial_camera.look_at = tuple(float(v) for v in look_at)
        self.server.initial_camera.position = tuple(float(v) for v in position)
        self.server.initial_camera.up = (0.0, 1.0, 0.0)
        gui = self.server.gui
        n = max(len(self.reader), 1)
        gui.add_markdown(f"**{self.reader.path}**  \n{len(self.reader)} frames at {self.reader.fps:g} fps")
        self.timeline = gui.add_slider("frame", 0, max(n - 1, 1), 1, 0)
        self.play = gui.add_button("Pause")
        self.loop_box = gui.add_checkbox("loop", True)

        @self.timeline.on_update
        def _(_):
            self.index = int(self.timeline.value)

        @self.play.on_click
        def _(_):
            self.playing = not self.playing
            self.play.label = "Pause" if self.playing else "Play"

        @self.loop_box.on_update
        def _(_):
            self.loop = bool(self.loop_box.value)

        self.show(0)
        self._thread = threading.Thread(target=self._run_loop, daemon=True)
        self._thread.start()
        return self

    def show(self, index):
        """Read and draw frame ``index``."""
        if not len(self.reader):
            self.drawer.draw({}, self.reader.static, self.reader.version)
            return
        self.drawer.draw(self.reader.items(index), self.reader.static, self.reader.version)
        self._shown = index

    def _run_loop(self):
        period = 1.0 / self.reader.fps
        while not self._stop.is_set():
            t0 = time.perf_counter()
            if self.playing and len(self.reader) > 1:
                nxt = self.index + 1
                if nxt >= len(self.reader):
                    nxt = 0 if self.loop else self.index
                self.index = nxt
                if int(self.timeline.value) != nxt:
                    self.timeline.value = nxt
            if self.index != self._shown:
                self.show(self.index)
            self._stop.wait(max(0.0, period - (time.perf_counter() - t0)))

    def stop(self):
        from .server import quiet_stdout

        self._stop.set()
        if self.server is not None:
            with quiet_stdout():  # viser's "Server stopped"
                self.server.stop()
            self.server = None
