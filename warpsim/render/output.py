"""Image and animation files: PNG (one frame), GIF and MP4 (animations) through Pillow and imageio.

:func:`open_sink` checks the file name before anything is rendered and returns a sink with
``add(rgb)`` (one (h, w, 3) uint8 frame), ``close()`` and ``abort()`` (a failed render: nothing
left behind). Every picture is written under a temporary name and renamed onto its path, so a
link planted at the path or at the temporary name is never written through
(:mod:`warpsim.core.safe_files`).
"""
from __future__ import annotations

import os
import zlib

import numpy as np

from ..core.safe_files import temporary_name, write_replacing

FORMATS = {".png": "image", ".gif": "animation", ".mp4": "animation"}


def check_out(path, flag="--out"):
    """The extension of ``path`` (ValueError for an unknown one; :class:`UsageError`-worthy
    ValueError/OSError naming ``flag`` when ``path`` is a folder, a FIFO or a device, or when its
    folder cannot be written: a probe file is made there, so ``/proc/...`` is refused here, before
    anything is rendered)."""
    import tempfile

    from ..core.safe_files import check_replaceable

    ext = os.path.splitext(str(path))[1].lower()
    if ext not in FORMATS:
        raise ValueError(f"{flag} {path!r}: write a .png (one frame), .gif or .mp4 file")
    check_replaceable(path, flag)
    folder = os.path.dirname(os.path.abspath(path))
    try:
        os.makedirs(folder, exist_ok=True)
        tempfile.TemporaryFile(dir=folder).close()
    except OSError as exc:
        raise PermissionError(f"{flag} {path!r}: cannot write in folder {folder!r} ({exc.strerror or exc}); choose a "
                              "writable folder") from None
    return ext


class _Png:
    def __init__(self, path, fps):
        self.path, self.count = path, 0

    def add(self, rgb):
        if self.count:
            raise ValueError(f"{self.path}: a .png holds one frame; write a .gif or .mp4 for an animation")
        from .png import encode_png

        data = encode_png(rgb)
        write_replacing(self.path, lambda f: f.write(data), what=f"--out {self.path!r}")
        self.count += 1

    def close(self):
        return self.path

    def abort(self):
        pass


class _Gif:
    """Frames kept as zlib-compressed RGB until :meth:`close` (rendered frames compress about tenfold),
    then quantised to one palette of ``colors`` colours taken from up to 8 frames spread over the
    clip (so colours that appear late stay true and unchanged pixels stay identical between
    frames, which GIF stores once). Pillow stores identical consecutive frames once with their
    durations added (playback time is kept)."""

    def __init__(self, path, fps, colors=255):
        self.path, self.fps, self.colors = path, float(fps), int(colors)
        self.frames = []
        self.count = 0

    def add(self, rgb):
        rgb = np.ascontiguousarray(rgb, np.uint8)
        self.frames.append((rgb.shape, zlib.compress(rgb.tobytes(), 1)))
        self.count += 1

    def _frame(self, k):
        shape, data = self.frames[k]
        return np.frombuffer(zlib.decompress(data), np.uint8).reshape(shape)

    def close(self):
        from PIL import Image

        if not self.frames:
            raise ValueError(f"{self.path}: no frames to write")
        picks = np.unique(np.linspace(0, len(self.frames) - 1, min(8, len(self.frames))).round().astype(int))
        mosaic = Image.fromarray(np.concatenate([self._frame(k) for k in picks], axis=0))
        palette = mosaic.quantize(colors=self.colors, method=Image.Quantize.MEDIANCUT)
        images = [Image.fromarray(self._frame(k)).quantize(palette=palette, dither=Image.Dither.NONE)
                  for k in range(len(self.frames))]
        duration = max(20, round(1000.0 / self.fps / 10.0) * 10)  # GIF delays are in 1/100 s
        write_replacing(self.path, lambda f: images[0].save(f, format="GIF", save_all=True, append_images=images[1:],
                                                            duration=duration, loop=0, optimize=False, disposal=1),
                        what=f"--out {self.path!r}")
        self.frames = []
        return self.path

    def abort(self):
        self.frames = []


class _Mp4:
    """ffmpeg writes by name: into a private folder made beside ``path`` (``mkdtemp``, mode 0700,
    so nothing can be planted in it), renamed onto ``path`` when complete."""

    def __init__(self, path, fps):
        try:
            import imageio.v2 as iio
            import imageio_ffmpeg  # noqa: F401  (the encoder imageio uses)
        except ImportError as exc:
            raise ImportError(f"writing {path} needs imageio with its ffmpeg plugin: pip install 'warpsim[render]' "
                              f"(imageio, imageio-ffmpeg) [{exc}]") from None
        import tempfile

        self.path, self.count = path, 0
        self.folder = tempfile.mkdtemp(prefix=os.path.basename(temporary_name(path)) + ".",
                                       dir=os.path.dirname(os.path.abspath(path)))
        self.tmp = os.path.join(self.folder, "picture.mp4")
        try:
            self.writer = iio.get_writer(self.tmp, fps=float(fps), codec="libx264", quality=7, macro_block_size=1,
                                         pixelformat="yuv420p")
        except BaseException:
            self.abort()
            raise

    def add(self, rgb):
        h, w = rgb.shape[:2]
        rgb = np.pad(rgb, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge")  # yuv420p needs even sizes
        self.writer.append_data(rgb)
        self.count += 1

    def close(self):
        try:
            self.writer.close()
            os.replace(self.tmp, self.path)
        finally:
            self.abort()
        return self.path

    def abort(self):
        import shutil

        shutil.rmtree(self.folder, ignore_errors=True)


def open_sink(path, fps, gif_colors=255):
    """A frame sink for ``path`` (.png, .gif, .mp4) at ``fps`` frames per second (a GIF's palette
    has ``gif_colors`` <= 256 colours)."""
    ext = check_out(path)
    if not (np.isfinite(fps) and fps > 0):
        raise ValueError(f"--fps {fps}: it must be > 0")
    if ext == ".gif":
        return _Gif(str(path), fps, gif_colors)
    return {".png": _Png, ".mp4": _Mp4}[ext](str(path), fps)
