"""A sweep's thumbnails, drawn when it ends: every world's last frame, one picture each.

The host work around each picture (its geometry read from the batch layer, its PNG encoding) runs
in worker processes (:mod:`warpsim.process_pool`) while this process renders on the sweep's device
what they have read: for a sweep of many worlds the pictures take about the renderer's time, not
the sum of reading, rendering and encoding. Few worlds are drawn here (a worker starts in about a
second). The pictures are the same either way: the same geometry, camera and renderer.
"""
from __future__ import annotations

import os

from ..core.safe_files import open_temporary

__all__ = ["POOL_WORLDS", "draw_thumbnails", "save_pngs", "world_geometry"]

POOL_WORLDS = 200
"""Sweeps with at least this many worlds read and encode their pictures in worker processes."""
SLICE_WORLDS = 32
"""Worlds a worker reads (or encodes) per job: small enough that rendering starts early."""


def world_geometry(layer, names, frame="last"):
    """[(world name, FrameGeometry, ground height [m] or False)] of the worlds ``names``
    (``world_GGGGGG``) of the batch layer ``layer`` at ``frame`` ("last": its last frame)."""
    from ..render.cache import ground_height
    from ..render.usd_scene import CacheScene

    scene = CacheScene(layer)
    prims = scene.prims
    frame = (scene.frames[-1] if scene.frames else None) if frame == "last" else frame
    wanted = set(names)
    worlds: dict = {}
    for prim in prims:  # /Worlds/world_GGGGGG/...
        parts = str(prim.GetPath()).split("/")
        if len(parts) > 3 and parts[2] in wanted:
            worlds.setdefault(parts[2], []).append(prim)
    out = []
    for name in names:
        scene.prims = worlds.get(name, [])
        out.append((name, scene.geometry(frame), ground_height(scene, [frame])))
    scene.prims = prims
    return out


def save_pngs(items) -> int:
    """Write each ``(path, image (H, W, 3) uint8)`` as a PNG (a temporary, then renamed: never
    through a planted link); returns how many."""
    from PIL import Image

    for path, image in items:
        with open_temporary(path + ".tmp.png", "wb") as f:
            Image.fromarray(image).save(f, format="PNG")
        os.replace(path + ".tmp.png", path)
    return len(items)


def _layer_worlds(layer):
    """The world prim names of a batch layer, in order."""
    from pxr import Sdf

    data = Sdf.Layer.FindOrOpen(layer)
    worlds = data.GetPrimAtPath("/Worlds") if data is not None else None
    return [child.name for child in worlds.nameChildren] if worlds is not None else []


def draw_thumbnails(folder, layers, camera, renderer, *, progress=None, workers=None) -> int:
    """Every world of the batch ``layers`` drawn by ``renderer`` with ``camera`` into
    ``folder/world_GGGGGG.png``; ``workers``: processes reading and encoding (None: by the worlds'
    count, :data:`POOL_WORLDS`; 0: none). Returns the pictures' count."""
    from ..process_pool import ProcessPool, default_workers

    slices = [(layer, names[i:i + SLICE_WORLDS]) for layer in layers
              for names in [_layer_worlds(layer)] for i in range(0, len(names), SLICE_WORLDS)]
    total = sum(len(names) for _, names in slices)
    if workers is None:
        workers = default_workers(jobs=len(slices)) if total >= POOL_WORLDS else 0
        workers = workers if workers >= 2 else 0  # one worker beside the renderer gains nothing measurable
    if not workers:
        count = 0
        for layer, names in slices:
            count += save_pngs(_render(folder, world_geometry(layer, names), camera, renderer, progress))
        return count
    with ProcessPool(workers) as pool:
        reads = [pool.submit("warpsim.browse.thumbs:world_geometry", layer, names) for layer, names in slices]
        writes = [pool.submit("warpsim.browse.thumbs:save_pngs",
                              _render(folder, read.result(), camera, renderer, progress)) for read in reads]
        return sum(w.result() for w in writes)


def _render(folder, geometries, camera, renderer, progress):
    items = []
    for name, geom, ground in geometries:
        items.append((os.path.join(folder, name + ".png"), renderer.render(geom, camera, ground_y=ground)))
        if progress is not None:
            progress()
    return items

