"""What an occupancy record costs a sweep, and how fast a spacetime query answers over it.

Measured in one process, on one device, for N worlds of a scene (default: teapots with four
varied parameters) x F frames:
  sweep     ``run_batch`` (stepping, metrics, USD batch layer) without a record and with one
            (``occupancy=...``), run alternately ``--repeat`` times; the record's cost is the
            difference of the medians, as % of the sweep without it;
  isolated  the recorder's own work (``update`` per frame, the 32-frame block copies, ``finish``
            and ``save``) re-run on the final state of the batch, as % of the sweep: the same
            cost without the run-to-run noise of whole sweeps;
  bytes     the record file against the sweep's USD batch layer;
  query     ``answer_region`` over all N worlds for ``--queries`` random boxes (a tenth to a half
            of the record's extent per axis) and windows, IN and NOT IN: median and largest time
            [ms], with the record loaded from disk (as ``warpsim query`` does).

    python benchmarks/bench_occupancy.py --device cuda:0 --worlds 10000 --frames 120
    python benchmarks/bench_occupancy.py --device cpu --worlds 1000 --frames 24
    python benchmarks/bench_occupancy.py --device cpu --worlds 16 --frames 8 --repeat 1   # check
"""

import argparse
import os
import sys
import tempfile
import time

import numpy as np
import warp as wp

from warpsim.worlds import run_batch, sample_worlds
from warpsim.worlds.occupancy import OccupancyRecord, OccupancyRecorder
from warpsim.worlds.query import Region, answer_region

VARY = ["stiffness=20:60", "height=0.4:0.6", "restitution=0.2:0.8", "friction=0.1:0.5"]


def sweep_seconds(args, worlds, folder, tag, occupancy):
    layer = os.path.join(folder, f"{tag}.batch_0000.usdc")
    wp.synchronize_device(args.device)
    t0 = time.perf_counter()
    run_batch(args.scene, worlds, frames=args.frames, device=args.device, layer_path=layer,
              track=args.track_map, occupancy=occupancy and {**occupancy, "path": os.path.join(folder, f"{tag}.npz")})
    wp.synchronize_device(args.device)
    return time.perf_counter() - t0, layer


def isolated_seconds(args, worlds, folder):
    """The recorder alone over F + 1 frames of a batch (its state does not move: the kernels,
    copies and compression do the same work per frame as during a sweep of that many frames)."""
    from warpsim.scenes import get_scene
    from warpsim.worlds.sweep import make_batch

    batch = make_batch(get_scene(args.scene), worlds, device=args.device)
    for _ in range(3):  # move the worlds off their start a little
        batch.advance(1.0 / 60.0, 4)
    particles = list(args.track_map.values()) if args.track_map else None
    rec = OccupancyRecorder(batch, args.frames, particles=particles, resolution=args.resolution)
    rec.update()  # loads the module
    rec = OccupancyRecorder(batch, args.frames, particles=particles, resolution=args.resolution)
    wp.synchronize_device(args.device)
    t0 = time.perf_counter()
    for _ in range(args.frames + 1):
        rec.update()
        rec.after_frame()
    rec.finish().save(os.path.join(folder, "isolated.npz"))
    wp.synchronize_device(args.device)
    return time.perf_counter() - t0


def query_times(record, count, seed=0):
    rng = np.random.default_rng(seed)
    lo, hi = record.grid.lo, record.grid.hi
    out, matches = [], []
    for k in range(count):
        size = (hi - lo) * rng.uniform(0.1, 0.5, 3)
        a = lo + (hi - lo - size) * rng.uniform(0, 1, 3)
        f0, f1 = sorted(rng.integers(0, record.frame_count, 2))
        t0, t1 = f0 / record.fps, f1 / record.fps
        region = Region(k % 2 == 0, tuple(a), tuple(a + size), t0, t1, "bench")
        start = time.perf_counter()
        answer = answer_region(record, region)
        out.append(time.perf_counter() - start)
        matches.append(int(answer.match.sum()))
    return np.array(out), matches


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", default="cuda:0" if wp.is_cuda_available() else "cpu")
    p.add_argument("--worlds", type=int, default=1000)
    p.add_argument("--frames", type=int, default=120)
    p.add_argument("--scene", default="teapot")
    p.add_argument("--vary", action="append", default=None, help=f"default: {' '.join(VARY)} (teapot)")
    p.add_argument("--track", action="append", default=[], metavar="NAME=INDEX", help="record these particles only")
    p.add_argument("--resolution", type=int, default=16, help="occupancy cells along the longest side")
    p.add_argument("--repeat", type=int, default=2, help="sweeps with and without a record (alternating)")
    p.add_argument("--queries", type=int, default=20)
    args = p.parse_args()
    wp.config.quiet = True
    wp.init()
    vary = args.vary or (VARY if args.scene == "teapot" else [])
    worlds = sample_worlds(args.scene, {}, vary, args.worlds, "lhs", 0)
    args.track_map = {}
    if args.track:
        from warpsim.scenes import get_scene
        from warpsim.worlds.command import resolve_track

        cls = get_scene(args.scene)
        args.track_map = resolve_track(cls, cls.resolve_params(worlds[0]), args.track, "cpu")
    device = wp.get_device(args.device)
    print(f"{args.scene} x {args.worlds} worlds x {args.frames} frames on {device} ({device.name}), "
          f"record resolution {args.resolution}{', tracked ' + ', '.join(args.track_map) if args.track_map else ''}")
    occupancy = {"resolution": args.resolution}
    with tempfile.TemporaryDirectory(prefix="bench_occupancy_") as folder:
        sweep_seconds(args, worlds[: min(4, len(worlds))], folder, "warm", occupancy)  # compiles every module
        plain, recorded = [], []
        for r in range(args.repeat):
            t, layer = sweep_seconds(args, worlds, folder, "plain", None)
            plain.append(t)
            t, layer = sweep_seconds(args, worlds, folder, "rec", occupancy)
            recorded.append(t)
        t_plain, t_rec = float(np.median(plain)), float(np.median(recorded))
        iso = isolated_seconds(args, worlds, folder)
        usd_bytes = os.path.getsize(layer)
        rec_path = os.path.join(folder, "rec.npz")
        rec_bytes = os.path.getsize(rec_path)
        t0 = time.perf_counter()
        record = OccupancyRecord.load(rec_path)
        t_load = time.perf_counter() - t0
        times, matches = query_times(record, args.queries)
    print(f"  {record.describe()}")
    print(f"  sweep without record   {t_plain:9.3f} s   (runs: {', '.join(f'{t:.3f}' for t in plain)})")
    print(f"  sweep with record      {t_rec:9.3f} s   (runs: {', '.join(f'{t:.3f}' for t in recorded)})")
    print(f"  record cost (difference)   {100 * (t_rec - t_plain) / t_plain:6.2f} % of the sweep   (goal <= 5 %)")
    print(f"  record cost (isolated)     {100 * iso / t_plain:6.2f} % of the sweep   ({iso:.3f} s)")
    print(f"  bytes: record {rec_bytes / 1e6:.3f} MB, USD batch layer {usd_bytes / 1e6:.3f} MB: "
          f"{100 * rec_bytes / usd_bytes:.2f} %   (goal <= 10 %)")
    print(f"  query over {record.world_count} worlds: median {1e3 * np.median(times):.2f} ms, largest "
          f"{1e3 * times.max():.2f} ms over {len(times)} boxes (goal <= 100 ms); record load {1e3 * t_load:.1f} ms; "
          f"matches per box {min(matches)}..{max(matches)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
