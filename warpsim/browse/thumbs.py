"""A sweep's thumbnails, drawn when it ends: every world's last frame, one picture each.

For a sweep of many worlds, worker processes (:mod:`warpsim.process_pool`) draw slices of the
worlds side by side: each reads its worlds' geometry from the batch layer (opened once per
worker), renders them on the sweep's device in one launch a slice (its own renderer: one CUDA
context a worker on a GPU) and encodes the PNGs (:mod:`warpsim.render.png`). Few worlds are
drawn here (a worker starts in about a second). The pictures are the same either way: the same
geometry, camera and renderer.

A sweep starts those workers early (:func:`start_workers`, once its frames are stepped): they
import the renderer, start Warp and build their renderer while the sweep completes its layer,
its record, table and root, and draw as soon as the layer is whole.
"""
from __future__ import annotations

import os

from ..core.safe_files import open_temporary

__all__ = ["POOL_WORLDS", "draw_thumbnails", "save_pngs", "slice_pictures", "start_workers", "thumbnail_workers",
           "warm_worker", "world_geometry"]

POOL_WORLDS = 200
"""Sweeps with at least this many worlds read and encode their pictures in worker processes."""
MOST_WORKERS = 4
"""Thumbnail workers at most. They start while the sweep steps and writes (:func:`start_workers`)
and take cores from its chunk writers while they warm up; measured on an H200 with 16 host cores
(2,000 teapots x 60 frames, ``bench_sweep_command.py``): 4 / 8 / 16 workers, whole sweep 7.87 /
9.03 / 10.02 s, the pictures' stage about the same each way, 2.4-2.6 s)."""
SLICE_WORLDS = 32
"""Worlds a worker reads (or encodes) per job: small enough that rendering starts early."""


_OPENED: dict = {}
"""Layers opened by :func:`world_geometry` in this process: ``{path: (mtime, BatchScene)}`` (a
worker is handed many slices of one layer: it opens the layer and reads what its worlds share once)."""


def _opened(layer):
    from ..render.batch_scene import BatchScene

    mtime = os.path.getmtime(layer)
    known = _OPENED.get(layer)
    if known is None or known[0] != mtime:
        _OPENED.clear()  # one layer at a time
        known = _OPENED[layer] = (mtime, BatchScene(layer))
    return known[1]


def world_geometry(layer, names, frame="last"):
    """[(world name, FrameGeometry, ground height [m] or False)] of the worlds ``names``
    (``world_GGGGGG``) of the batch layer ``layer`` at ``frame`` ("last": its last frame)
    (:class:`warpsim.render.batch_scene.BatchScene`)."""
    batch = _opened(os.path.abspath(layer))
    frame = (batch.frames[-1] if batch.frames else None) if frame == "last" else frame
    return [(name, batch.geometry(name, frame), batch.ground(name, frame)) for name in names]


def save_pngs(items) -> int:
    """Write each ``(path, image (H, W, 3) uint8)`` as a PNG (:func:`warpsim.render.png.encode_png`;
    a temporary, then renamed: never through a planted link); returns how many."""
    from ..render.png import encode_png

    for path, image in items:
        data = encode_png(image)
        with open_temporary(path + ".tmp.png", "wb") as f:
            f.write(data)
        os.replace(path + ".tmp.png", path)
    return len(items)


def _layer_worlds(layer):
    """The world prim names of a batch layer, in order."""
    from pxr import Sdf

    data = Sdf.Layer.FindOrOpen(layer)
    worlds = data.GetPrimAtPath("/Worlds") if data is not None else None
    return [child.name for child in worlds.nameChildren] if worlds is not None else []


def thumbnail_workers(world_count, jobs=None) -> int:
    """Processes that draw the pictures of ``world_count`` worlds (``jobs``: slices of them, None:
    one per :data:`SLICE_WORLDS`): by the cores, from :data:`POOL_WORLDS` worlds on; 0: this process."""
    from ..process_pool import default_workers

    if world_count < POOL_WORLDS:
        return 0
    workers = default_workers(jobs=-(-int(world_count) // SLICE_WORLDS) if jobs is None else jobs, most=MOST_WORKERS)
    return workers if workers >= 2 else 0  # one worker beside this process gains nothing measurable


def start_workers(world_count, size, device):
    """The :class:`~warpsim.process_pool.ProcessPool` that will draw ``world_count`` worlds'
    pictures of ``size`` on ``device``, started now, each worker warming up (:func:`warm_worker`)
    while the caller goes on; hand it to :func:`draw_thumbnails` (``pool``) and close it after.
    None when this process draws them (:func:`thumbnail_workers`)."""
    from ..process_pool import ProcessPool

    workers = thumbnail_workers(world_count)
    if not workers:
        return None
    pool = ProcessPool(workers)
    for _ in range(workers):  # (one job a worker: each holds its worker until done)
        pool.submit("warpsim.browse.thumbs:warm_worker", tuple(size), str(device))
    return pool


def warm_worker(size, device) -> None:
    """A worker's first job: the modules a slice needs imported, Warp started and the renderer of
    ``size`` on ``device`` built (:func:`slice_pictures` keeps it)."""
    import warp as wp

    from ..render import usd_scene  # noqa: F401  (the layer's reader, and usd-core)
    from ..verbosity import set_warp_verbosity

    set_warp_verbosity()
    _renderer(size, wp.get_device(device).alias)  # (the name slice_pictures is given: the renderer's device)


def draw_thumbnails(folder, layers, camera, renderer, *, progress=None, workers=None, pool=None) -> int:
    """Every world of the batch ``layers`` drawn by ``renderer`` with ``camera`` into
    ``folder/world_GGGGGG.png``; ``workers``: processes that each read, render (on the renderer's
    device, with a renderer of the same size) and encode a slice of the worlds (None: by the
    worlds' count, :func:`thumbnail_workers`; 0: all here); ``pool``: those processes, already
    started (:func:`start_workers`; the caller closes it). Returns the pictures' count."""
    from ..process_pool import ProcessPool

    slices = [(layer, names[i:i + SLICE_WORLDS]) for layer in layers
              for names in [_layer_worlds(layer)] for i in range(0, len(names), SLICE_WORLDS)]
    total = sum(len(names) for _, names in slices)
    if pool is not None:
        workers = pool.workers
    elif workers is None:
        workers = thumbnail_workers(total, jobs=len(slices))
    if not workers:
        count = 0
        try:
            for layer, names in slices:
                count += save_pngs(_render(folder, world_geometry(layer, names), camera, renderer, progress))
        finally:
            _OPENED.clear()  # (this process keeps no stage of the layer once its pictures are drawn)
        return count
    device = renderer.device.alias
    size = (renderer.width, renderer.height)
    if pool is not None:
        return _draw_slices(pool, slices, folder, camera, size, device, progress)
    with ProcessPool(workers) as started:
        return _draw_slices(started, slices, folder, camera, size, device, progress)


def _draw_slices(pool, slices, folder, camera, size, device, progress) -> int:
    count = 0
    jobs = [pool.submit("warpsim.browse.thumbs:slice_pictures", layer, names, folder, camera, size, device)
            for layer, names in slices]
    for job in jobs:
        done = job.result()
        count += done
        for _ in range(done if progress is not None else 0):
            progress()
    return count


_RENDERERS: dict = {}


def slice_pictures(layer, names, folder, camera, size, device) -> int:
    """A worker's job: the pictures of the worlds ``names`` of ``layer``, read, rendered on
    ``device`` by a renderer of ``size`` (kept for the worker's next slices) and saved as PNGs."""
    return save_pngs(_render(folder, world_geometry(layer, names), camera, _renderer(size, device), None))


def _renderer(size, device):
    """This worker's renderer of ``size`` on ``device`` (built once, kept for its next slices)."""
    from ..render.renderer import Renderer
    from ..verbosity import set_warp_verbosity

    set_warp_verbosity()  # Warp's per-module lines only when asked (the worker shares the caller's stderr)
    key = (tuple(size), device)
    if key not in _RENDERERS:
        _RENDERERS.clear()
        _RENDERERS[key] = Renderer(int(size[0]), int(size[1]), device=device)
    return _RENDERERS[key]


def _render(folder, geometries, camera, renderer, progress):
    """``[(path, picture)]`` of a slice's worlds, drawn in one launch (:meth:`Renderer.render_many`)."""
    geometries = list(geometries)
    pictures = renderer.render_many([(geom, ground) for _, geom, ground in geometries], camera)
    items = []
    for (name, _, _), picture in zip(geometries, pictures):
        items.append((os.path.join(folder, name + ".png"), picture))
        if progress is not None:
            progress()
    return items
