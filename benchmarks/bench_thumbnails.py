"""Where a sweep's thumbnails spend their time (issue 50): the pictures of every world of a sweep
root, drawn as ``warpsim sweep`` draws them and stage by stage in one process.

Rows (seconds for all the root's worlds):

  pool        :func:`warpsim.browse.panel.sweep_thumbnails` as the sweep calls it (its workers
              started here: start-up included)
  open        the batch layers opened (:class:`warpsim.render.batch_scene.BatchScene`), one process
  geometry    every world's FrameGeometry and ground read from the layers, one process
  render      every world rendered on ``--device`` one at a time (Renderer.render), one process
  render_many the same in slices of SLICE_WORLDS, one launch a slice (Renderer.render_many, as the
              sweep draws them)
  pillow      every picture encoded as a PNG in memory by Pillow's default save (before 2026-12-02)
  encode      the same by warpsim.render.png.encode_png (as the sweep encodes them)

    python -m warpsim.cli sweep teapot --worlds 2000 --frames 60 --vary stiffness=20:60 --no-thumbnails \\
        --out /tmp/t/t.usda --device cuda:0
    python benchmarks/bench_thumbnails.py /tmp/t/t.usda --device cuda:0
"""
from __future__ import annotations

import argparse
import io
import os
import shutil
import sys
import tempfile
import time

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))


def kernel_table(renderer, geoms, camera, per_slice):
    """Print the device activity of render_many over ``geoms`` in slices of ``per_slice``: total [ms] and
    calls by kernel or copy, against the wall time of the same calls."""
    import warp as wp

    wp.synchronize_device(renderer.device)
    wp.timing_begin(cuda_filter=wp.TIMING_ALL)
    t0 = time.perf_counter()
    for i in range(0, len(geoms), per_slice):
        renderer.render_many(geoms[i:i + per_slice], camera)
    wp.synchronize_device(renderer.device)
    wall = time.perf_counter() - t0
    results = wp.timing_end()
    totals, calls = {}, {}
    for r in results:
        totals[r.name] = totals.get(r.name, 0.0) + r.elapsed
        calls[r.name] = calls.get(r.name, 0) + 1
    busy = sum(totals.values())
    print(f"render_many, {len(geoms)} pictures: wall {wall * 1e3:.1f} ms, device activity {busy:.1f} ms")
    for name in sorted(totals, key=totals.get, reverse=True)[:12]:
        print(f"  {name[:60]:60s} {calls[name]:7d} calls {totals[name]:9.2f} ms")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("root", help="a sweep root written by warpsim sweep (--store all or preview)")
    p.add_argument("--device", default="cpu")
    p.add_argument("--skip-pool", action="store_true", help="only the one-process stages")
    p.add_argument("--profile", action="store_true", help="also the GPU activity of render_many's slices by kernel "
                   "and copy (wp.timing_begin/end: what of its time the device spent)")
    args = p.parse_args(argv)

    import numpy as np
    import warp as wp
    from PIL import Image

    from warpsim.browse import panel, thumbs
    from warpsim.browse.occupancy import OccupancyRecord
    from warpsim.browse.roots import sweep_root_files
    from warpsim.render.batch_scene import BatchScene
    from warpsim.render.png import encode_png
    from warpsim.render.renderer import Renderer
    from warpsim.verbosity import set_warp_verbosity

    set_warp_verbosity()
    wp.init()
    files = sweep_root_files(args.root)
    layers = sorted({layer for _, layer in files["worlds"]})
    record = OccupancyRecord.load(files["record"])
    camera = panel.thumbnail_camera(record)
    rows = {}
    if not args.skip_pool:
        tmp = tempfile.mkdtemp(prefix="bench_thumbs_")
        root_copy = os.path.join(tmp, os.path.basename(args.root))
        t0 = time.perf_counter()
        pool = thumbs.start_workers(len(files["worlds"]), panel.THUMB_SIZE, args.device)
        try:
            made = panel.sweep_thumbnails(root_copy, layers, record, device=args.device, pool=pool)
        finally:
            if pool is not None:
                pool.close()
        rows["pool"] = time.perf_counter() - t0
        print(f"pool: {made['count']} pictures, {pool.workers if pool else 0} workers", flush=True)
        shutil.rmtree(tmp, ignore_errors=True)

    renderer = Renderer(*panel.THUMB_SIZE, device=args.device)
    t0 = time.perf_counter()
    scenes = {layer: BatchScene(layer) for layer in layers}
    rows["open"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    geoms = []
    for layer, scene in scenes.items():
        frame = scene.frames[-1]
        for name in scene.worlds:
            geoms.append((scene.geometry(name, frame), scene.ground(name, frame)))
    rows["geometry"] = time.perf_counter() - t0
    renderer.render(geoms[0][0], camera, ground_y=geoms[0][1])  # (compiles)
    t0 = time.perf_counter()
    images = [renderer.render(g, camera, ground_y=ground) for g, ground in geoms]
    rows["render"] = time.perf_counter() - t0
    many = Renderer(*panel.THUMB_SIZE, device=args.device)
    many.render_many(geoms[:thumbs.SLICE_WORLDS], camera)
    t0 = time.perf_counter()
    pictures = []
    for i in range(0, len(geoms), thumbs.SLICE_WORLDS):
        pictures += many.render_many(geoms[i:i + thumbs.SLICE_WORLDS], camera)
    rows["render_many"] = time.perf_counter() - t0
    if args.profile:
        kernel_table(many, geoms, camera, thumbs.SLICE_WORLDS)
    same = all(np.array_equal(a, b) for a, b in zip(images, pictures))
    t0 = time.perf_counter()
    size = 0
    for image in images:
        buf = io.BytesIO()
        Image.fromarray(image).save(buf, format="PNG")
        size += buf.tell()
    rows["pillow"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    ours = sum(len(encode_png(image)) for image in images)
    rows["encode"] = time.perf_counter() - t0
    n = len(geoms)
    print(f"{n} worlds, {args.device}, {panel.THUMB_SIZE[0]}x{panel.THUMB_SIZE[1]}, PNG {size / n:.0f} bytes each "
          f"(Pillow), {ours / n:.0f} (encode_png); render_many's pictures equal render's: {same}")
    print("| stage | s | ms a world |\n| --- | ---: | ---: |")
    for k, v in rows.items():
        print(f"| {k} | {v:.3f} | {1e3 * v / n:.3f} |")


if __name__ == "__main__":
    main()
