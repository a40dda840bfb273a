"""Browsing a sweep's worlds by where things go, in the gallery (``warpsim view SWEEP.usda``).

:class:`QueryPanel` adds to a :class:`warpsim.browse.gallery.GalleryViewer` whose sweep has an
occupancy record (:mod:`warpsim.browse.occupancy`):

- a translucent box in the page with a gizmo on each of two opposite corners: drag a gizmo's
  arrows or planes with the mouse to place and resize the box (or type its corners in
  "box min" / "box max"); the box is drawn in the frame of the isolated world (world 0's when
  none is), so its corners are the record's coordinates [m];
- the time window [s] (a two-handled slider), IN / NOT IN, the ranking (first entry, time
  inside, share of particles inside, world) and "show matches only" (hides the other worlds,
  except the first, in whose frame the box is drawn);
- the matching worlds, ranked, each a button (click: that world alone, playing from frame 0) and
  a small picture (warpsim's renderer, kept in ``<stem>.thumbs/world_GGGGGG.png``: made by the
  sweep itself, :func:`sweep_thumbnails`, unless ``--no-thumbnails``; else on first show).

A query is asked when a gizmo is released or a setting changes (not while dragging), from the
record (:func:`warpsim.browse.query.answer_region`; a change of the ranking alone reuses the last
answer): milliseconds for 10,000 worlds. The worlds' visibility is sent only when the set of
hidden worlds changes, and the list keeps its buttons and pictures, relabelled in place, so a
control that only re-ranks redraws no world. Exact when
the record keeps positions or at most :data:`REFINE_BUDGET` world-frames in doubt are read back
from the cache, else conservative to one cell (the summary says which).
"""
from __future__ import annotations

import os
import threading
import time

import numpy as np

from ..core.safe_files import clear_temporary
from .occupancy import OccupancyRecord, occupancy_path
from .query import Region, answer_region, cached_positions

__all__ = ["RANKS", "QueryPanel", "sweep_thumbnails", "thumbnail", "thumbnail_camera"]

RANKS = ("first entry", "time inside", "share inside", "world")
REFINE_BUDGET = 2_000
"""World-frames the gallery reads back from the cache to make an answer exact (more: cells only,
so an answer stays well under a second)."""
MODES = ("IN", "NOT IN")
VISIBILITY_DELAY = 0.2
"""Seconds between an answer and the worlds' visibility it implies (the answer is painted first)."""
THUMB_SIZE = (128, 96)
BOX_COLOR = (60, 140, 255)
EDGE_PIXELS = 2.0
"""Width of the query box's edges on screen [px]."""


def box_edges(lo, hi) -> np.ndarray:
    """The 12 edges of the axis-aligned box ``lo``..``hi`` [m] as segments, shape (12, 2, 3) float32."""
    corners = np.array([[(lo, hi)[(k >> a) & 1][a] for a in range(3)] for k in range(8)], np.float32)
    pairs = [(k, k | 1 << a) for k in range(8) for a in range(3) if not k >> a & 1]
    return corners[np.array(pairs)]


def thumbnail(root, world, camera=None, size=THUMB_SIZE, frame=None, device=None) -> str:
    """Path of a small picture of world ``world`` of the sweep ``root`` (rendered by
    :func:`warpsim.render.cache.render_cache` from the picked world, kept in
    ``<stem>.thumbs/world_GGGGGG.png``; rendered once)."""
    import tempfile

    from ..render.cache import render_cache
    from .pick import pick_world
    from .roots import world_prim_name

    folder = thumbnails_folder(root)
    path = os.path.join(folder, world_prim_name(world) + ".png")
    if os.path.exists(path):
        return path
    os.makedirs(folder, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="warpsim_thumb_") as tmp:
        picked = pick_world(root, world, os.path.join(tmp, "world.usda"))
        clear_temporary(path + ".tmp.png")
        render_cache(picked, path + ".tmp.png", frame=frame, size=size, camera=camera, device=device)
    os.replace(path + ".tmp.png", path)
    return path


def thumbnail_camera(record, size=THUMB_SIZE):
    """The one camera of every world's picture: framing where the record's worlds go."""
    from ..render.camera import frame_bounds

    return frame_bounds(np.array(record.occupied_bounds()), *size)


def thumbnails_folder(root) -> str:
    return os.path.splitext(os.path.abspath(os.fspath(root)))[0] + ".thumbs"


def sweep_thumbnails(root, layers, record, *, size=THUMB_SIZE, device=None, progress=None, pool=None) -> dict:
    """Every world's picture of the sweep ``root`` (its last frame, as :func:`thumbnail` draws it,
    with :func:`thumbnail_camera`), rendered by warpsim's renderer on ``device`` straight from the
    batch ``layers`` into ``<stem>.thumbs/world_GGGGGG.png``, so the gallery finds them made
    (:func:`warpsim.browse.thumbs.draw_thumbnails`: many worlds are read and encoded in worker
    processes; ``progress()``: called after each picture; ``pool``: those processes started early,
    :func:`warpsim.browse.thumbs.start_workers`). Returns {"count", "seconds", "folder"}."""
    from ..render.renderer import Renderer
    from .thumbs import draw_thumbnails

    t0 = time.perf_counter()
    folder = thumbnails_folder(root)
    os.makedirs(folder, exist_ok=True)
    renderer = Renderer(int(size[0]), int(size[1]), device=device)
    count = draw_thumbnails(folder, layers, thumbnail_camera(record, size), renderer, progress=progress, pool=pool)
    return {"count": count, "seconds": time.perf_counter() - t0, "folder": folder}


OPT_IN_WORLDS = 10_000
"""Past this many worlds a sweep draws no thumbnails unless asked (``--thumbnails``): about 10 ms
a picture on a CPU, 100,000 worlds would add a quarter of an hour."""


def thumbnails_after_sweep(root, layers, record, device=None, enabled=True, progress=None, pool=None) -> str:
    """What ``warpsim sweep`` does for the gallery's pictures: draw them all
    (:func:`sweep_thumbnails`), or with ``enabled=False`` (``--no-thumbnails``, or past
    ``OPT_IN_WORLDS`` worlds without ``--thumbnails``: ``enabled="many"``) remove an older sweep's
    pictures of this root, so the gallery draws fresh ones on first show. ``progress()``: after
    each picture; ``pool``: the workers that draw them, started early (or None). Returns the line to print."""
    import shutil

    if enabled == "many":
        shutil.rmtree(thumbnails_folder(root), ignore_errors=True)
        return (f"thumbnails: none ({record.world_count:,} worlds, over {OPT_IN_WORLDS:,}: about "
                f"{record.world_count * 0.01 / 60:.0f} min of pictures on a CPU; --thumbnails draws them, or the "
                "gallery draws each on first show)")
    if not enabled:
        shutil.rmtree(thumbnails_folder(root), ignore_errors=True)
        return "thumbnails: none (--no-thumbnails; the gallery draws them on first show)"
    try:
        made = sweep_thumbnails(root, layers, record, device=device, progress=progress, pool=pool)
    except Exception as exc:  # noqa: BLE001  (a finished sweep stands; the gallery draws them on first show)
        return f"thumbnails: not drawn ({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''})"
    return (f"thumbnails: {made['count']} pictures of {THUMB_SIZE[0]}x{THUMB_SIZE[1]} in {made['seconds']:.2f} s "
            f"({1e3 * made['seconds'] / max(made['count'], 1):.1f} ms each; --no-thumbnails skips them): "
            f"{os.path.relpath(made['folder'])}")


class QueryPanel:
    """The spacetime query of a gallery (see the module docstring). ``viewer``: a started
    :class:`warpsim.browse.gallery.GalleryViewer`; ``record``: its occupancy record (default:
    read from beside ``viewer.root``); ``top``: worlds listed; ``thumbnails``: draw a picture per
    listed world (in a background thread)."""

    def __init__(self, viewer, *, record=None, top=12, thumbnails=True):
        self.viewer = viewer
        self.record = record if record is not None else OccupancyRecord.load(occupancy_path(viewer.root))
        self.top = int(top)
        self.positions = cached_positions(viewer.root, self.record) if viewer.root else None
        self.thumbnails = bool(thumbnails)
        self.hidden = set()
        """Worlds (``world_GGGGGG``) hidden because they do not match (with "show matches only")."""
        self.matches = []
        """The ranked matching worlds (global indices) of the last answer."""
        self.answer_seconds = None
        """How long the last answer took [s] (the record's query, the list and the summary; the
        worlds' visibility follows)."""
        self._syncing = False
        self._lock = threading.Lock()
        self._answered = None  # (region, answer) of the last query
        self._visibility = None  # the timer that applies the last answer's visibility
        self._slots = []  # per listed place: {"button", "image", "world"}
        self._more = None
        self._pictures = {}
        self._thumb_thread = None
        self._wanted = []
        self._lock_thumbs = threading.Lock()
        rec, server = self.record, viewer.server
        self.origin = self._origin(None)
        inner_lo, inner_hi = rec.occupied_bounds()  # where things go: the box starts in its middle,
        # a quarter of its largest extent on every axis (a quarter per axis made a sliver where things
        # move along one axis, as falling balls do, that nothing entered: every world hidden at once)
        center, size = 0.5 * (inner_lo + inner_hi), np.full(3, 0.25 * float(np.max(inner_hi - inner_lo)))
        self.lo, self.hi = center - 0.5 * size, center + 0.5 * size
        gui = server.gui
        with gui.add_folder("where things go"):
            gui.add_markdown(f"{rec.describe()}")
            self.box_lo = gui.add_vector3("box min [m]", tuple(self.lo), step=1e-3)
            self.box_hi = gui.add_vector3("box max [m]", tuple(self.hi), step=1e-3)
            self.window = gui.add_multi_slider("window [s]", 0.0, max(rec.duration, 1e-6), 1.0 / rec.fps,
                                               (0.0, max(rec.duration, 1e-6)))
            self.mode = gui.add_dropdown("mode", MODES, initial_value="IN")
            self.rank = gui.add_dropdown("rank by", RANKS, initial_value=RANKS[0])
            self.matches_only = gui.add_checkbox("show matches only", True)
            self.summary = gui.add_markdown("")
            self.listing = gui.add_folder("matches")
        self.gizmo_scale = scale = float(np.max(inner_hi - inner_lo)) * 0.15
        """Length [m] of the corner gizmos' arrows."""
        # drawn over see-through containers: a translucent mesh writes depth as an opaque one does, so
        # the near face of a scene's walls (drawn first when farther) hid a translucent box and the
        # gizmos behind it; the box's edges are opaque lines (drawn before anything translucent) and
        # the gizmos skip the depth test
        self.box = server.scene.add_box("/query/box", color=BOX_COLOR, dimensions=tuple(self.hi - self.lo),
                                        position=tuple(self.origin + center), opacity=0.3, cast_shadow=False,
                                        receive_shadow=False)
        self.edges = server.scene.add_line_segments("/query/edges", box_edges(self.origin + self.lo,
                                                                              self.origin + self.hi),
                                                    BOX_COLOR, thickness=EDGE_PIXELS, thickness_units="screen")
        self.gizmo_lo, self.gizmo_hi = (
            server.scene.add_transform_controls(f"/query/{name}", scale=scale, disable_rotations=True,
                                                depth_test=False, position=tuple(self.origin + corner))
            for name, corner in (("min", self.lo), ("max", self.hi)))
        for gizmo in (self.gizmo_lo, self.gizmo_hi):
            gizmo.on_update(self._gizmo_moved)
        for handle in (self.box_lo, self.box_hi):
            handle.on_update(lambda _e: self._typed())
        for handle in (self.window, self.mode, self.rank, self.matches_only):
            handle.on_update(lambda _e: self.ask())
        self.ask()

    # ------------------------------------------------------------------ the box
    def _origin(self, world):
        offsets = self.viewer.reader.offsets
        name = world or (self.viewer.reader.worlds[0] if self.viewer.reader.worlds else None)
        return np.asarray(offsets.get(name, np.zeros(3)), np.float64)

    def box_bounds(self):
        """[[lo], [hi]] [m] of the box and its corner gizmos in the page (the frame it is drawn in)."""
        pad = self.gizmo_scale
        return np.array([self.origin + self.lo - pad, self.origin + self.hi + pad])

    def follow(self, world):
        """Draw the box in the frame of ``world`` (None: the first world's)."""
        self.origin = self._origin(world)
        self._draw_box()

    def _draw_box(self):
        self._syncing = True
        try:
            self._shape(self.lo, self.hi)
            self.gizmo_lo.position = tuple(self.origin + self.lo)
            self.gizmo_hi.position = tuple(self.origin + self.hi)
            self.box_lo.value = tuple(float(v) for v in self.lo)
            self.box_hi.value = tuple(float(v) for v in self.hi)
        finally:
            self._syncing = False

    def _corners_from_gizmos(self):
        a = np.asarray(self.gizmo_lo.position, np.float64) - self.origin
        b = np.asarray(self.gizmo_hi.position, np.float64) - self.origin
        return np.minimum(a, b), np.maximum(a, b)

    def _gizmo_moved(self, event):
        """A gizmo's update: the end of a drag (its release) asks, the moves before only redraw."""
        if getattr(event, "phase", "end") == "end":
            self._released()
        else:
            self._dragging()

    def _dragging(self):
        """While a gizmo moves: the box follows (no query until it is released)."""
        if self._syncing:
            return
        self._shape(*self._corners_from_gizmos())

    def _shape(self, lo, hi):
        """The drawn box (fill and edges) from corner ``lo`` to ``hi`` [m] (the record's coordinates)."""
        self.box.position = tuple(self.origin + 0.5 * (lo + hi))
        self.box.dimensions = tuple(np.maximum(hi - lo, 1e-6))
        self.edges.points = box_edges(self.origin + lo, self.origin + hi)

    def _released(self):
        if self._syncing:
            return
        self.lo, self.hi = self._corners_from_gizmos()
        self._draw_box()
        self.ask()

    def _typed(self):
        if self._syncing:
            return
        a, b = np.asarray(self.box_lo.value, np.float64), np.asarray(self.box_hi.value, np.float64)
        self.lo, self.hi = np.minimum(a, b), np.maximum(a, b)
        self._draw_box()
        self.ask()

    def set_box(self, lo, hi):
        """Place the box at lo..hi [m] (the record's coordinates) and ask."""
        a, b = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
        self.lo, self.hi = np.minimum(a, b), np.maximum(a, b)
        self._draw_box()
        self.ask()

    # ------------------------------------------------------------------ the answer
    def region(self) -> Region:
        t0, t1 = (float(v) for v in self.window.value)
        return Region(self.mode.value == "IN", tuple(self.lo), tuple(self.hi), t0, t1,
                      f"{','.join(f'{v:.4g}' for v in (*self.lo, *self.hi))}@{t0:.4g}:{t1:.4g}")

    def ask(self):
        """Answer the current box, window and mode; list the matches; hide the others."""
        with self._lock:
            start = time.perf_counter()
            region = self.region()
            if self._answered is not None and self._answered[0] == region:  # re-ranked only
                answer = self._answered[1]
            else:
                try:
                    answer = answer_region(self.record, region, self.positions, budget=REFINE_BUDGET)
                except ValueError as exc:
                    self.summary.content = f"**{exc}**"
                    return
                self._answered = (region, answer)
            matched = np.flatnonzero(answer.match)
            key = {"first entry": answer.entry, "time inside": -answer.time, "share inside": -answer.share}
            by = key.get(self.rank.value)
            if by is not None and region.inside:
                values = np.nan_to_num(by[matched], nan=np.inf)
                matched = matched[np.lexsort((matched, values))]
            first = self.record.first_world
            self.matches = [int(first + w) for w in matched]
            self._list(answer, matched)
            names = {f"world_{g:06d}" for g in self.matches}
            anchor = {self.viewer.reader.worlds[0]} if self.viewer.reader.worlds else set()
            # the world the box is drawn in stays shown, as the box's reference
            hidden = set(self.viewer.reader.worlds) - names - anchor if self.matches_only.value else set()
            self.answer_seconds = time.perf_counter() - start
            self.summary.content = (f"**{len(self.matches)} of {self.record.world_count} worlds** "
                                    f"{'IN' if region.inside else 'NOT IN'} the box during "
                                    f"{self.window.value[0]:.3g}..{self.window.value[1]:.3g} s "
                                    f"({'exact' if answer.exact else f'to one cell of {self.record.grid.cell_size:.3g} m'}"
                                    f", {1e3 * self.answer_seconds:.1f} ms)")
            # then the worlds' visibility, only when it changes, a moment after the answer (the page
            # paints the answer before it re-renders every world; the viewer's lock may also wait
            # for a frame of every world being drawn)
            if hidden != self.hidden:
                self.hidden = hidden
                if self._visibility is not None:
                    self._visibility.cancel()
                self._visibility = threading.Timer(VISIBILITY_DELAY, self._apply_visibility)
                self._visibility.daemon = True
                self._visibility.start()

    def _apply_visibility(self):
        """Show and hide the worlds as ``hidden`` says now (the latest answer's)."""
        if self.viewer.server is None:
            return
        self.viewer.refresh_visibility()

    def settle(self, timeout=10.0):
        """Wait until the worlds' visibility follows the last answer (tests, scripts)."""
        timer = self._visibility
        if timer is not None:
            timer.join(timeout)

    def _list(self, answer, matched):
        """The ranked list: place k keeps its button (and picture) from answer to answer, relabelled
        and pointed at its new world; places are added or removed only as the count changes."""
        gui = self.viewer.server.gui
        shown = matched[: self.top]
        with self.listing:
            while len(self._slots) > len(shown):
                slot = self._slots.pop()
                for h in (slot["button"], slot["image"]):
                    if h is not None:
                        h.remove()
            for k, w in enumerate(shown):
                g = int(self.record.first_world + w)
                label = f"#{k + 1} world {g}"
                if answer.match[w] and self.mode.value == "IN":
                    label += f": in at {answer.entry[w]:.3g} s for {answer.time[w]:.3g} s"
                    if np.isfinite(answer.share[w]):
                        label += f", {100 * answer.share[w]:.0f}%"
                if k == len(self._slots):
                    slot = {"button": gui.add_button(label, order=2 * k + 1), "image": None, "world": g}
                    slot["button"].on_click(lambda _e, slot=slot: self.play(slot["world"]))
                    self._slots.append(slot)
                slot = self._slots[k]
                slot["world"] = g
                if slot["button"].label != label:
                    slot["button"].label = label
                picture = self._pictures.get(g)
                if picture is None and slot["image"] is not None:
                    slot["image"].remove()
                    slot["image"] = None
                elif picture is not None and slot["image"] is None:
                    slot["image"] = gui.add_image(picture, label=None, order=2 * k)
                elif picture is not None and slot.get("picture") != g:
                    slot["image"].image = picture
                slot["picture"] = g if picture is not None else None
            more = f"... and {len(matched) - len(shown)} more" if len(matched) > len(shown) else ""
            if self._more is not None and not more:
                self._more.remove()
                self._more = None
            elif more and self._more is None:
                self._more = gui.add_markdown(more, order=2 * self.top + 1)
            elif more and self._more.content != more:
                self._more.content = more
        if self.thumbnails:
            with self._lock_thumbs:
                for w in shown:
                    g = int(self.record.first_world + w)
                    if g not in self._pictures and g not in self._wanted:
                        self._wanted.append(g)
                if self._wanted and (self._thumb_thread is None or not self._thumb_thread.is_alive()):
                    self._thumb_thread = threading.Thread(target=self._make_thumbnails, daemon=True)
                    self._thumb_thread.start()

    def _make_thumbnails(self):
        """Render the wanted pictures one by one (a background thread), then list again."""
        from PIL import Image

        camera = thumbnail_camera(self.record)  # one camera for all
        while self.viewer.server is not None:
            with self._lock_thumbs:
                if not self._wanted:
                    self._thumb_thread = None
                    break
                world = self._wanted.pop(0)
            try:
                with Image.open(thumbnail(self.viewer.root, world, camera=camera)) as image:
                    self._pictures[world] = np.asarray(image.convert("RGB"))
            except Exception:  # noqa: BLE001  (a picture that fails leaves its button without one)
                self._pictures[world] = None
        if self.viewer.server is not None:
            self.ask()  # the list again, now with the pictures

    def play(self, world):
        """Show ``world`` (global index) alone and play it from frame 0."""
        self.viewer.isolate(f"world_{int(world):06d}")
        self.viewer.index = 0
        self.viewer.playing = True
