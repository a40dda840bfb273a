"""A gallery of a sweep's worlds in the browser viewer: every world side by side, click one to
isolate it (``warpsim view SWEEP.usda`` on a root written by ``warpsim sweep``).

:class:`GalleryReader` reads the worlds of a sweep root (a ``world`` variant set or a grid; a
variant root is laid out as a grid in memory, exactly as ``write_sweep_root(layout="grid")``
does) frame by frame, each prim drawn as ``world_GGGGGG/NAME`` moved by its world's place on the
grid. :class:`GalleryViewer` is the playback viewer with a world menu: clicking a world's mesh in
the page (or picking it in the menu) shows that world alone and frames the camera on it, clicking
it again (or "all") shows every world and frames the whole gallery again. With a query panel
(an occupancy record beside the root) the first framing is world 0, in whose frame the query
box and its corner gizmos are drawn, so they are a usable size at once. The play button always
says what pressing it will do ("Pause" while playing), also when a listed world starts playing.
Drives no kernels; viser is imported when the viewer starts.
"""
from __future__ import annotations

import os
import tempfile

import numpy as np

from ..viewer.framing import aim
from ..viewer.playback import DYNAMIC_TYPES, CacheReader, PlaybackViewer
from .roots import root_worlds, write_sweep_root

__all__ = ["GalleryReader", "GalleryViewer", "is_sweep_root"]

ALL = "all worlds"


def is_sweep_root(path) -> bool:
    """Whether ``path`` is the root USD of a sweep (worlds referenced from batch layers)."""
    try:
        return root_worlds(path) is not None
    except Exception:  # noqa: BLE001  (not USD, unreadable: not a sweep root)
        return False


class GalleryReader(CacheReader):
    """Frames of every world of a sweep root, laid out on a grid (see the module docstring)."""

    def __init__(self, path, max_points=None):
        from pxr import Usd, UsdGeom

        from ..usd.validate import frame_codes

        found = root_worlds(path)
        if found is None:
            raise ValueError(f"{path} is not a sweep root (no 'world' variant set or world_ prims under /World)")
        layout, worlds = found
        self._tmp = None
        grid_path = os.fspath(path)
        if layout == "variants":  # the same worlds side by side, in memory
            self._tmp = tempfile.TemporaryDirectory(prefix="warpsim_gallery_")
            grid_path = os.path.join(self._tmp.name, "gallery.usda")
            layers = sorted({layer for _, layer in worlds})
            write_sweep_root(grid_path, layers, max(w for w, _ in worlds) + 1, layout="grid",
                             worlds=[w for w, _ in worlds])
            # references stay relative to the batch layers' folder: rewrite them absolute
            from pxr import Sdf

            layer = Sdf.Layer.FindOrOpen(grid_path)
            for (w, batch), child in zip(worlds, layer.GetPrimAtPath("/World").nameChildren.values()):
                ref = child.referenceList.prependedItems[0]
                child.referenceList.prependedItems = [Sdf.Reference(batch, ref.primPath)]
            layer.Save()
        self.stage = Usd.Stage.Open(grid_path)
        self.path = str(path)
        self.frames = frame_codes(self.stage)
        self.fps = float(self.stage.GetTimeCodesPerSecond() or 24.0)
        self.max_points = max_points
        self.worlds = [f"world_{w:06d}" for w, _ in worlds]
        self.dynamic, self.static = [], {}
        self.offsets = {}
        """Each world's place on the gallery's grid [m] (its frame's origin in the page)."""
        code0 = float(self.frames[0]) if self.frames else 0.0
        for world in self.worlds:
            top = self.stage.GetPrimAtPath(f"/World/{world}")
            offset = np.asarray(UsdGeom.Xformable(top).ComputeLocalToWorldTransform(code0).ExtractTranslation(),
                                np.float32)
            self.offsets[world] = offset
            for prim in Usd.PrimRange(top):
                t = prim.GetTypeName()
                if prim == top or "Prototypes" in str(prim.GetPath()) or t not in DYNAMIC_TYPES:
                    continue
                attr = prim.GetAttribute("positions" if t == "PointInstancer" else "points")
                if attr.ValueMightBeTimeVarying() or t == "PointInstancer":
                    self.dynamic.append((world, prim, offset))
                else:
                    item = self._placed(world, prim, offset, code0)
                    if item is not None:
                        item.static = True
                        self.static[item.name] = item
        self.version = 1

    def _placed(self, world, prim, offset, code):
        item = self._item(prim, code)
        if item is None:
            return None
        item.name = f"{world}/{prim.GetName()}"
        item.points = np.asarray(item.points, np.float32) + offset
        return item

    def world_bounds(self, world, samples=7):
        """[[lo], [hi]] [m] in the page of ``world``'s moving prims over ``samples`` frames spread
        across the sweep, and its static prims (as :func:`warpsim.viewer.framing.playback_bounds`
        frames a cache); None when it draws nothing."""
        from ..viewer.framing import item_points, item_radius, robust_bounds

        n = len(self.frames)
        clouds, pad = [], 0.0
        for index in sorted({int(round(k)) for k in np.linspace(0, max(n - 1, 0), min(samples, max(n, 1)))}):
            code = float(self.frames[index]) if n else 0.0
            for w, prim, offset in self.dynamic:
                item = self._placed(w, prim, offset, code) if w == world else None
                if item is not None:
                    clouds.append(item_points(item))
                    pad = max(pad, item_radius(item))
        b = robust_bounds(clouds, pad=pad)
        statics = [item_points(it) for name, it in self.static.items() if name.split("/")[0] == world]
        if b is None:
            return robust_bounds(statics, quantile=0.0)
        return b

    def items(self, index):
        code = float(self.frames[index]) if self.frames else 0.0
        out = {}
        for world, prim, offset in self.dynamic:
            item = self._placed(world, prim, offset, code)
            if item is not None:
                out[item.name] = item
        return out


class GalleryViewer(PlaybackViewer):
    """The playback viewer over a :class:`GalleryReader`, with world isolation (click or menu)."""

    def __init__(self, path, *, host="127.0.0.1", port=8080, max_points=200_000, thumbnails=True):
        self.reader = GalleryReader(path, max_points=max_points)
        self.root = os.fspath(path)
        self.thumbnails = bool(thumbnails)
        self.query = None
        """The spacetime query panel (:class:`warpsim.browse.panel.QueryPanel`) when the sweep
        has an occupancy record, else None."""
        self.host, self.port = host, int(port)
        self.index = 0
        self._playing = True
        self.loop = True
        self.server = None
        self.isolated = None
        """The world shown alone (``world_GGGGGG``) or None: every world."""
        self._hooked = set()
        import threading

        self._stop = threading.Event()
        self._shown = None
        self._lock = threading.Lock()
        self.gallery_pose = None
        """(position, look_at) [m] framing every world (the view "all worlds" returns to)."""

    @property
    def playing(self) -> bool:
        """Whether the frames advance; setting it also relabels the play button ("Pause" while
        playing, "Play" while paused), whoever sets it."""
        return self._playing

    @playing.setter
    def playing(self, value):
        self._playing = bool(value)
        button = getattr(self, "play", None)
        label = "Pause" if self._playing else "Play"
        if button is not None and button.label != label:
            button.label = label

    def start(self):
        super().start()
        self.menu = self.server.gui.add_dropdown("world", (ALL, *self.reader.worlds), initial_value=ALL)
        camera = self.server.initial_camera
        self.gallery_pose = (np.asarray(camera.position, np.float64), np.asarray(camera.look_at, np.float64))

        @self.menu.on_update
        def _(_):
            self.isolate(None if self.menu.value == ALL else self.menu.value)

        from .occupancy import occupancy_path

        if os.path.exists(occupancy_path(self.root)):
            from .panel import QueryPanel

            self.query = QueryPanel(self, thumbnails=self.thumbnails)
            if self.reader.worlds:  # the first view: world 0, where the box and its gizmos are drawn
                aim(camera, *self.world_pose(self.reader.worlds[0], self.query.box_bounds()))
        first = (np.asarray(camera.position, np.float64), np.asarray(camera.look_at, np.float64))
        self.server.on_client_connect(lambda client: self._first_view(client, first))
        self._refresh()
        return self

    def _first_view(self, client, pose):
        """A new tab (after its first camera report) is put at the first view (``pose``: (position,
        look_at) [m]) unless it is there: a page busy loading many worlds could miss the initial
        camera and keep its default, looking past the box from (3, 3, 3)."""
        camera = client.camera
        if not (np.allclose(camera.position, pose[0], atol=1e-4) and np.allclose(camera.look_at, pose[1], atol=1e-4)):
            with client.atomic():
                aim(camera, *pose)

    def world_pose(self, world, also=None):
        """(position, look_at) [m] of a camera framing ``world`` over the sweep (and the bounds
        ``also`` [[lo], [hi]] [m] in the page, e.g. the query box)."""
        from ..viewer.framing import camera_pose

        b = self.reader.world_bounds(world)
        if also is not None:
            also = np.asarray(also, np.float64)
            b = also if b is None else np.array([np.minimum(b[0], also[0]), np.maximum(b[1], also[1])])
        return camera_pose(b)

    def frame_camera(self, world):
        """Point every connected client's camera at ``world`` (None: the whole gallery)."""
        if self.server is None:
            return
        if world is None:
            position, look_at = self.gallery_pose
        else:
            position, look_at = self.world_pose(world)
        for client in self.server.get_clients().values():
            with client.atomic():
                aim(client.camera, position, look_at)

    def isolate(self, world):
        """Show ``world`` alone (None: every world)."""
        if world is not None and world not in self.reader.worlds:
            raise ValueError(f"world {world!r} is not in this gallery; worlds: {', '.join(self.reader.worlds)}")
        with self._lock:  # the handles first, then the state that says so (a reader never sees
            self._refresh(isolated=world)  # `isolated` ahead of the visibility it implies)
            self.isolated = world
        if self.menu.value != (world or ALL):
            self.menu.value = world or ALL
        if self.query is not None:
            self.query.follow(world)
        self._refresh()
        self.frame_camera(world)

    def show(self, index):
        with self._lock:
            super().show(index)
            self._refresh()

    def drawn_nodes(self):
        """(world, handle, clickable) of every drawn node. See-through containers (walls, tanks)
        take no clicks: a clickable node stops the pointer, so their near faces would catch every
        press on what is inside them (the query box's gizmos among it)."""
        for name, (node, _) in self.drawer.nodes.items():
            for h in node if isinstance(node, list) else [node]:
                yield name.split("/")[0], h, True
        for h in self.drawer.static_nodes:
            item = self.reader.static.get(h.name.split("/", 2)[2])
            yield h.name.split("/")[2], h, item is None or item.opacity is None or item.opacity >= 1.0

    def refresh_visibility(self):
        """Show and hide the worlds as the isolated world and the query's answer say now (the
        query panel calls it once an answer is painted)."""
        with self._lock:
            self._refresh()

    def _refresh(self, isolated=...):
        """Visibility per the isolated world (``isolated``: that world instead of
        ``self.isolated``); click handlers on new meshes."""
        if self.server is None or getattr(self, "menu", None) is None:
            return
        isolated = self.isolated if isolated is ... else isolated
        hidden = self.query.hidden if self.query is not None and isolated is None else ()
        for world, h, clickable in self.drawn_nodes():
            visible = (isolated is None or world == isolated) and world not in hidden
            if getattr(h, "visible", visible) != visible:
                h.visible = visible
            if clickable and id(h) not in self._hooked and hasattr(h, "on_click"):
                self._hooked.add(id(h))

                def clicked(_event, world=world):
                    self.isolate(None if self.isolated == world else world)

                h.on_click(clicked)
