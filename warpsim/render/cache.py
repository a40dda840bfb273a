"""Rendering a USD cache to a picture or an animation: :func:`render_cache`.

    render_cache("usd_out/teapot.usda", "teapot.gif", size=(480, 360))
    render_cache("usd_out/smoke.usda", "smoke.png", frames=[48], camera="2,1.5,3,0,0.7,0")

Every input is checked before the first ray is cast: the cache opens, the frames lie in its
range, the size and camera are valid and the output's extension is known.
"""
from __future__ import annotations

import time

import numpy as np

from .camera import Camera, frame_bounds, parse_camera
from .output import FORMATS, check_out, open_sink
from .renderer import Renderer, check_size
from ..usd.validate import DamagedCacheError, check_damage, describe_ranges
from .usd_scene import CacheScene


def parse_size(text):
    """(width, height) from ``"WxH"``; ValueError naming the text otherwise."""
    try:
        w, h = (int(v) for v in str(text).lower().split("x"))
    except ValueError:
        raise ValueError(f"--size {text!r} must be WIDTHxHEIGHT in pixels, e.g. --size 480x360") from None
    return check_size(w, h)


def select_frames(available, frame=None, frames=None):
    """The frames to draw: ``frame`` (one int), ``frames`` ("A:B" or "A:B:STEP", inclusive, either
    end may be left out) or, when both are None, every frame of the cache. ValueError when a
    frame lies outside ``available`` (the cache's time codes)."""
    if frame is not None and frames is not None:
        raise ValueError("give --frame N or --frames A:B, not both")
    if not available:
        if frame not in (None, 0) or frames is not None:
            raise ValueError("the cache has no time samples (a static file): omit --frame/--frames")
        return [None]
    first, last = available[0], available[-1]
    if frame is not None:
        if int(frame) != frame or not first <= frame <= last:
            raise ValueError(f"--frame {frame} is outside the cache's frames {first}..{last}")
        return [int(frame)]
    if frames is None:
        return list(available)
    parts = str(frames).split(":")
    try:
        if len(parts) not in (2, 3):
            raise ValueError
        a = int(parts[0]) if parts[0].strip() else first
        b = int(parts[1]) if parts[1].strip() else last
        step = int(parts[2]) if len(parts) == 3 and parts[2].strip() else 1
    except ValueError:
        raise ValueError(f"--frames {frames!r} must be A:B or A:B:STEP (inclusive frame numbers), e.g. "
                         f"--frames {first}:{last}") from None
    if step < 1:
        raise ValueError(f"--frames {frames!r}: the step must be >= 1")
    if not (first <= a <= b <= last):
        raise ValueError(f"--frames {frames!r} is outside the cache's frames {first}..{last} (or A > B)")
    return list(range(a, b + 1, step))


def render_cache(cache, out, frame=None, frames=None, size=(480, 360), camera=None, fps=None, device=None,
                 guides=False, only=None, progress=None, gif_colors=255, max_frames=None, allow_damaged=False,
                 on_skip=None):
    """Render ``cache`` into ``out`` (.png: one frame, the last unless ``frame`` is given; .gif
    or .mp4: ``frames``, every frame by default). ``camera``: None (frame the scene's bounds
    over the drawn frames), a :class:`Camera` or ``"ex,ey,ez,tx,ty,tz"``. ``fps``: playback
    rate (default the cache's). ``only``: names of the prims to draw (default all). ``max_frames``:
    when no frames are named, draw every k-th frame so that at most this many are drawn (and play
    them at fps / k, in real time). ``progress``: called with (frames done, frames in all) after each frame.
    Damaged caches (chunk files missing, truncated or changed since written, checked against the
    chunk index as ``warpsim info`` does; every batch layer of a sweep root) raise
    :class:`warpsim.usd.validate.DamagedCacheError`; with ``allow_damaged`` their frames are left
    out and ``on_skip(line)`` is told which.
    Returns ``{"path", "frames", "seconds", "camera"}``."""
    width, height = parse_size(size) if isinstance(size, str) else check_size(*size)
    ext = check_out(out)
    if max_frames is not None:
        from ..core import checks

        max_frames = checks.integer(max_frames, "render_cache max_frames", lo=1,
                                    fix="the most frames to draw, e.g. max_frames=300 (None: every frame)")
    if isinstance(camera, str):
        camera = parse_camera(camera)
    elif camera is not None and not isinstance(camera, Camera):
        raise ValueError(f"camera must be a Camera or 'ex,ey,ez,tx,ty,tz', got {camera!r}")
    bad = check_damage(cache, allow_damaged)  # before USD reads a damaged chunk (pxr errors, NaN or empty frames)
    scene = CacheScene(cache, guides=guides, only=only)
    if bad:
        scene.frames = [f for f in scene.frames if f not in bad]
        if not scene.frames:
            raise DamagedCacheError(f"cache {str(cache)!r}: every frame lies in a damaged chunk file; nothing to draw",
                                    {"damaged": [], "readable": []})
        if on_skip is not None:
            on_skip(f"skipping {len(bad)} frame(s) of damaged chunk files: {describe_ranges(_ranges(bad))}")
    if FORMATS[ext] == "image" and frame is None and frames is None:
        frame = scene.frames[-1] if scene.frames else None
    chosen = select_frames(scene.frames, frame, frames)
    if bad:
        chosen = [f for f in chosen if f not in bad]
        if not chosen:
            raise DamagedCacheError(f"cache {str(cache)!r}: the frames asked for lie in damaged chunk files; "
                                    f"readable frames: {describe_ranges(_ranges(scene.frames))}",
                                    {"damaged": [], "readable": []})
    if FORMATS[ext] == "image" and len(chosen) != 1:
        raise ValueError(f"--out {out!r}: a .png holds one frame but {len(chosen)} were asked; give --frame N "
                         "or write a .gif/.mp4")
    step = 1
    if max_frames is not None and frame is None and frames is None and len(chosen) > max_frames:
        step = -(-len(chosen) // int(max_frames))
        chosen = chosen[::step]
    fps = scene.fps / step if fps is None else float(fps)
    if not (np.isfinite(fps) and fps > 0):
        raise ValueError(f"--fps {fps}: it must be > 0")
    if camera is None:  # frame the subject (what moves, robustly); else what the scene holds, guides not framed
        bounds = scene.subject_bounds(None if chosen == [None] else chosen)
        if bounds is None:
            bounds = (CacheScene(cache, only=only) if guides else scene).bounds(None if chosen == [None] else chosen)
        if bounds is None:
            bounds = np.array([[-1.0, 0.0, -1.0], [1.0, 1.0, 1.0]])
        camera = frame_bounds(bounds, width, height)
    renderer = Renderer(width, height, device=device)
    sink = open_sink(out, fps, gif_colors)
    t0 = time.perf_counter()
    ground_y = ground_height(scene, chosen)
    try:
        for k, f in enumerate(chosen):
            sink.add(renderer.render(scene.geometry(f), camera, ground_y=ground_y))
            if progress is not None:
                progress(k + 1, len(chosen))
        path = sink.close()
    except BaseException:
        sink.abort()  # no temporary picture left behind
        raise
    return {"path": path, "frames": len(chosen), "seconds": time.perf_counter() - t0, "camera": camera}


def _ranges(frames):
    """Merged (first, last) runs of a set of integer frames."""
    out = []
    for f in sorted(frames):
        if out and f == out[-1][1] + 1:
            out[-1] = (out[-1][0], f)
        else:
            out.append((f, f))
    return out


def ground_height(scene, chosen):
    """Ground height [m]: the bottom of everything in the cache, guides included (a box's floor)."""
    return ground_below(ground_scene(scene).bounds(None if chosen == [None] else chosen))


def ground_scene(scene):
    """A copy of the CacheScene ``scene`` that also draws ``guide`` prims (what the ground is under)."""
    full = CacheScene.__new__(CacheScene)
    full.__dict__.update(scene.__dict__)
    full.purposes = scene.purposes + ("guide",)
    return full


def ground_below(bounds):
    """The ground height [m] under ``bounds`` [[lo], [hi]] [m] (False when None): just below, so floors
    do not flicker."""
    if bounds is None:
        return False
    return float(bounds[0][1] - 2e-3 * max(np.max(bounds[1] - bounds[0]), 1e-3))
