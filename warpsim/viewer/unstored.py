"""Playing a sweep that stored no frames (``--store none``): any world, re-run on demand.

A sweep run with ``--store none`` keeps its table, occupancy record, manifest and thumbnails, not
its frames: every world re-runs bit-exactly from the manifest. :class:`UnstoredSweepViewer` plays
one world re-run that way (``warpsim view ROOT --world N``) and adds a "world" box and a "re-run
and play" button: the chosen world is re-run in the background (the page says so and keeps
playing the current one), then played from frame 0. A failed re-run is said in the page; the
server goes on serving.
"""
from __future__ import annotations

import os
import tempfile
import threading
import time

from .playback import CacheReader, PlaybackViewer

__all__ = ["UnstoredSweepViewer"]


class UnstoredSweepViewer(PlaybackViewer):
    """Plays world ``world`` of the ``--store none`` sweep ``root`` (already re-run into ``path``,
    in the temporary folder ``folder``) and re-runs any other on demand with
    ``rerun(root, world, out_path) -> cache path`` (``warpsim.sweeps.rerun.pick_or_rerun``, given by
    the command: the viewer stands below the sweeps)."""

    def __init__(self, root, world, path, folder, world_count, rerun, *, host="127.0.0.1", port=8080,
                 max_points=200_000):
        super().__init__(path, host=host, port=port, max_points=max_points)
        self.rerun = rerun
        self.root, self.world, self.world_count = os.fspath(root), int(world), int(world_count)
        self.max_points = max_points
        self.rerun_folder = folder  # removed with the viewer (and replaced by each new world's)
        self._busy = threading.Lock()
        self.rerun_thread = None

    def start(self):
        super().start()
        gui = self.server.gui
        with gui.add_folder("sweep: no stored frames"):
            self.world_box = gui.add_number("world", self.world, min=0, max=max(self.world_count - 1, 0), step=1)
            self.rerun_button = gui.add_button("re-run and play")
            self.status = gui.add_markdown(f"world {self.world} of {self.world_count}, re-run exactly from the "
                                           "sweep's manifest")

        @self.rerun_button.on_click
        def _(_):
            self.request(int(self.world_box.value))

        return self

    def request(self, world):
        """Re-run ``world`` in the background and play it (ignored while a re-run is under way)."""
        world = int(world)
        if not 0 <= world < self.world_count:
            self.status.content = f"world {world} is out of range: the sweep holds worlds 0..{self.world_count - 1}"
            return None
        if not self._busy.acquire(blocking=False):
            self.status.content = "a re-run is under way; choose again when it is done"
            return None
        self.status.content = f"re-running world {world} exactly (the sweep stored no frames) ..."
        self.rerun_thread = threading.Thread(target=self._rerun, args=(world,), daemon=True)
        self.rerun_thread.start()
        return self.rerun_thread

    def _rerun(self, world):
        folder = tempfile.TemporaryDirectory(prefix="warpsim_view_world_")
        t0 = time.perf_counter()
        try:
            path = self.rerun(self.root, world, os.path.join(folder.name, f"world_{world:06d}.usda"))
            reader = CacheReader(path, max_points=self.max_points)
        except Exception as exc:  # noqa: BLE001  (any failure is said in the page; the server goes on)
            folder.cleanup()
            self.status.content = f"world {world} could not be re-run: {str(exc).splitlines()[0] if str(exc) else exc}"
            self._busy.release()
            return
        seconds = time.perf_counter() - t0
        old = self.rerun_folder
        self.playing = False
        reader.version = self.reader.version + 1  # its static prims drawn afresh
        self.reader, self.world, self.rerun_folder = reader, world, folder
        self.timeline.max = max(len(reader) - 1, 1)
        self.index, self.timeline.value = 0, 0
        self.show(0)
        self.playing = True
        self.play.label = "Pause"
        self.status.content = f"world {world} of {self.world_count}: re-ran exactly in {seconds:.2f} s; playing it"
        if old is not None:
            old.cleanup()
        self._busy.release()
