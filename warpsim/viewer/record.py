"""Recording a viewer session into a USD cache through the crash-safe ``UsdCacheWriter``.

The scene declares its prims on the writer exactly as ``warpsim run`` does, so a recording is
an ordinary warpsim cache (``warpsim info`` reads it; usdview, Blender, Houdini open it). Frame
0 is the frame shown when Record was pressed; every frame simulated afterwards (dragging
included) follows. The writer completes chunk files atomically, so a recording interrupted at
any moment keeps every completed chunk, and :meth:`Recorder.close` (called on Stop, on a
rebuild, when the last browser tab closes and when the server stops) completes the last one.
"""
from __future__ import annotations

import os
import threading
import time

from ..usd.writer import ROOT_EXTENSIONS, UsdCacheWriter

__all__ = ["Recorder", "default_recording_path"]


def default_recording_path(scene_name, folder="usd_out"):
    """``usd_out/<scene>_view_<YYYYmmdd-HHMMSS>.usda`` (a suffix keeps names unique)."""
    stamp = time.strftime("%Y%m%d-%H%M%S")
    path = os.path.join(folder, f"{scene_name}_view_{stamp}.usda")
    k = 1
    while os.path.exists(path):
        path = os.path.join(folder, f"{scene_name}_view_{stamp}_{k}.usda")
        k += 1
    return path


class Recorder:
    """Streams the frames of a running scene into a cache at ``path`` (.usd/.usda/.usdc) at
    ``fps`` [frames/s]; ``chunk_size`` frames per chunk file."""

    def __init__(self, scene, path, fps, chunk_size=24):
        if os.path.splitext(str(path))[1] not in ROOT_EXTENSIONS:
            raise ValueError(f"recording path {path!r} must end in .usd, .usda or .usdc")
        from ..usd.family import check_output

        check_output(path, (), "recording path")  # never a chunk, batch layer or table of another result
        self.writer = UsdCacheWriter(path, fps=fps, chunk_size=chunk_size)
        scene.declare(self.writer)
        self.writer.begin()
        self.path = self.writer.path
        self.frames = 0
        self._lock = threading.Lock()

    def write(self, data):
        """Append one frame of ``scene.frame_data()``."""
        with self._lock:
            self.writer.write_frame(self.frames, data)
            self.frames += 1

    @property
    def closed(self):
        return self.writer.closed

    def close(self):
        """Complete the last chunk; returns the path to open (idempotent)."""
        with self._lock:
            return self.writer.close()
