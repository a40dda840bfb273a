"""What an occupancy record costs a sweep, and how fast a spacetime query answers over it.

Measured in one process, on one device, for N worlds of a scene (default: teapots with four
varied parameters, ``springs=false`` so a world's USD holds its surface only):
  stepping  F frames of the batch (``advance`` + metrics; CUDA graphs on CUDA) three times in
            one process: without a record, with the record marked inside the step (the default)
            and with the separate pass over the positions (``in_step=False``); the recorder's own
            per-frame work (``update``, the 32-frame flushes) is timed apart with a device
            synchronisation around it, then ``finish`` + ``save``. The record's cost = (stepping
            with marks + the recorder's work - stepping without a record) / stepping without,
            % (a stricter base than the sweep, which also writes USD);
  profile   (``--profile``) the same F frames launched eagerly under ``wp.timing_begin``: device
            time per kernel and copy, the bytes the flushes move to the host, the host time of the
            flushes and of ``finish``; for the separate pass also what the former host flush
            (whole-block copy + ``flatnonzero``) and finish (``np.unique`` of every key) take on
            the same blocks;
  sweep     whole ``run_batch`` sweeps (stepping, metrics, the USD batch layer) of
            ``--sweep-frames`` frames without and with a record, run alternately ``--repeat``
            times: the record's cost as the difference of the medians, % of the sweep; and the
            record's bytes against the USD layer's (0 skips this part: 10,000 teapots write ~1.6 GB
            of USD per 12 frames);
  query     ``answer_region`` over all N worlds of the F-frame record, loaded from disk as
            ``warpsim query`` does, for ``--queries`` random boxes (a tenth to a half of the grid
            per axis) and windows, IN and NOT IN alternately: median and largest [ms];
  panel     the gallery's answer after a box is released (``QueryPanel.ask`` on a real viser
            server: the query, the ranked list of buttons, and one visibility flag per world sent
            for N stand-in world nodes; no browser attached, no thumbnails).

    python benchmarks/bench_occupancy.py --device cuda:0 --worlds 10000 --frames 120 --sweep-frames 0 --profile
    python benchmarks/bench_occupancy.py --device cuda:0 --worlds 10000 --frames 120 --sweep-frames 6
    python benchmarks/bench_occupancy.py --device cpu --worlds 1000 --frames 120 --sweep-frames 12
    python benchmarks/bench_occupancy.py --device cpu --worlds 16 --frames 8 --repeat 1   # check
    python benchmarks/bench_occupancy.py --merge-check 105000   # host only: finish's merge
"""

import argparse
import os
import sys
import tempfile
import time

import numpy as np
import warp as wp

from warpsim.sweeps import run_batch, sample_worlds
from warpsim.browse.occupancy import OccupancyRecord
from warpsim.browse.query import Region, answer_region

VARY = ["stiffness=20:60", "height=0.4:0.6", "restitution=0.2:0.8", "friction=0.1:0.5"]


def sweep_seconds(args, worlds, folder, tag, occupancy, frames):
    layer = os.path.join(folder, f"{tag}.batch_0000.usdc")
    wp.synchronize_device(args.device)
    t0 = time.perf_counter()
    run_batch(args.scene, worlds, frames=frames, device=args.device, layer_path=layer,
              track=args.track_map, occupancy=occupancy and {**occupancy, "path": os.path.join(folder, f"{tag}.npz")})
    wp.synchronize_device(args.device)
    return time.perf_counter() - t0, layer


def make_recorder(args, batch, fps, folder, in_step):
    """The recorder a sweep makes (its grid also covers the static geometry the USD writer declares)."""
    from warpsim.usd.sink import PrimSink
    from warpsim.browse.occupancy import OccupancyRecorder

    sink = PrimSink()  # the static prims a batch layer declares, without pxr (the GPU machine may lack it)
    batch.scene.declare(sink)
    static = [np.asarray(getattr(d.attrs.get("points"), "value", None), np.float64).reshape(-1, 3)
              for d in sink.prims.values() if not d.is_dynamic and d.attrs.get("points") is not None]
    static = np.concatenate(static) if static else np.zeros((0, 3))
    static = static[np.isfinite(static).all(1)]
    static = np.array([static.min(0), static.max(0)]) if len(static) else None
    track = args.track_map or None
    return OccupancyRecorder(batch, args.frames, particles=list(track.values()) if track else None,
                             track_names=list(track) if track else (), resolution=args.resolution, fps=fps,
                             scene=args.scene, include=static, in_step=in_step)


def fresh_batch(args, worlds):
    """(batch, metrics, fps, substeps, frame_dt): these worlds built anew, so every run of this
    bench steps the same frames 0..F from the same state."""
    from warpsim.scenes import get_scene
    from warpsim.sweeps.metrics import WorldMetrics
    from warpsim.sweeps.sweep import frame_timing, make_batch

    cls = get_scene(args.scene)
    fps, substeps, frame_dt = frame_timing(cls, cls.resolve_params(worlds[0]))
    batch = make_batch(cls, worlds, device=args.device)
    return batch, WorldMetrics(batch), fps, substeps, frame_dt


def stepping_record(args, worlds, folder, record=True, in_step=True):
    """(stepping seconds, recorder seconds, record path or None, recorder): F frames of a batch, the
    recorder's work timed apart (synchronised), its record saved. On CUDA both run as captured
    graphs, as in a sweep (``run_batch`` captures a frame's stepping, metrics and recording
    together). ``record=False``: stepping alone."""
    batch, stats, fps, substeps, frame_dt = fresh_batch(args, worlds)
    rec = None
    if record:
        rec = make_recorder(args, batch, fps, folder, in_step)
        rec.update()  # frame 0 (the step marks the cells from frame 1 on)
        rec.after_frame()

    def step():
        batch.advance(frame_dt, substeps)
        stats.update()

    record_frame = rec.update if rec is not None else (lambda: None)
    step()  # loads every module (this frame is not timed)
    record_frame()
    use_graph = batch.device.is_cuda and batch.can_capture()
    if use_graph:
        with wp.ScopedCapture(device=batch.device) as capture:
            step()
        step_graph = capture.graph
        step = lambda: wp.capture_launch(step_graph)  # noqa: E731
        if rec is not None:
            with wp.ScopedCapture(device=batch.device) as capture:
                rec.update()
            record_graph = capture.graph
            record_frame = lambda: wp.capture_launch(record_graph)  # noqa: E731
    wp.synchronize_device(args.device)
    t_step = t_record = 0.0
    for _ in range(args.frames):
        t0 = time.perf_counter()
        step()
        wp.synchronize_device(args.device)
        t1 = time.perf_counter()
        if rec is not None:
            record_frame()
            rec.after_frame()
            wp.synchronize_device(args.device)
        t_step, t_record = t_step + t1 - t0, t_record + time.perf_counter() - t1
    if rec is None:
        return t_step, 0.0, None, None
    path = os.path.join(folder, "stepping.npz")
    t0 = time.perf_counter()
    rec.finish().save(path)
    return t_step, t_record + time.perf_counter() - t0, path, rec


def profile_record(args, worlds, folder, in_step):
    """Eager frames under ``wp.timing_begin``: {(kind, name): [device ms, launches]}, the recorder,
    and for the separate pass the former host flush / finish timed on the same blocks."""
    batch, stats, fps, substeps, frame_dt = fresh_batch(args, worlds)
    rec = make_recorder(args, batch, fps, folder, in_step)
    former = {"copy": 0.0, "flatnonzero": 0.0, "gather": 0.0, "finish": 0.0}
    kept = []

    def former_flush():  # what _flush did before (whole block to the host, scanned there)
        t0 = time.perf_counter()
        words = rec.block.numpy()
        t1 = time.perf_counter()
        nz = np.flatnonzero(words)
        t2 = time.perf_counter()
        kept.append((nz, words[nz].copy()))
        former["copy"] += t1 - t0
        former["flatnonzero"] += t2 - t1
        former["gather"] += time.perf_counter() - t2

    kinds = {wp.TIMING_KERNEL: "kernel", wp.TIMING_MEMCPY: "copy", wp.TIMING_MEMSET: "memset",
             wp.TIMING_KERNEL_BUILTIN: "builtin"}
    table = {}
    wp.timing_begin(cuda_filter=wp.TIMING_ALL)
    rec.update()
    for frame in range(args.frames + 1):
        if frame:
            batch.advance(frame_dt, substeps)
            stats.update()
            rec.update()
        if not in_step and (rec._seen + 1) % 32 == 0:
            former_flush()
        rec.after_frame()
    if not in_step and rec._seen % 32:
        former_flush()
    record = rec.finish()
    for r in wp.timing_end():
        entry = table.setdefault((kinds.get(r.filter, str(r.filter)), r.name), [0.0, 0])
        entry[0] += r.elapsed
        entry[1] += 1
    if kept:
        t0 = time.perf_counter()
        keys = np.unique(np.concatenate([nz for nz, _ in kept]))
        bits = np.zeros((len(keys), len(kept)), np.uint32)
        for b, (nz, w) in enumerate(kept):
            bits[np.searchsorted(keys, nz), b] = w
        former["finish"] = time.perf_counter() - t0
        assert np.array_equal(keys % rec.grid.cell_count, record.pair_cell) and np.array_equal(bits, record.pair_bits)
    return table, rec, record, former


def merge_check(pairs, worlds=10000, cells=4212, blocks=4, seed=0):
    """Host only: the former ``finish`` (``np.unique`` of every flushed key, then a column per
    block) against the recorder's per-flush merges (sorted insertion), on ``blocks`` flushes of
    about ``pairs`` random keys each; prints both [ms]."""
    from warpsim.browse.occupancy import OccupancyRecorder

    rng = np.random.default_rng(seed)
    flushed = []
    for b in range(blocks):
        k = np.unique(rng.integers(0, worlds * cells, pairs)).astype(np.int64)
        flushed.append((b, k, rng.integers(1, 2 ** 32, len(k), dtype=np.uint64).astype(np.uint32)))
    t0 = time.perf_counter()
    keys = np.unique(np.concatenate([k for _, k, _ in flushed]))
    bits = np.zeros((len(keys), blocks), np.uint32)
    for b, k, w in flushed:
        bits[np.searchsorted(keys, k), b] = w
    former = time.perf_counter() - t0
    rec = OccupancyRecorder.__new__(OccupancyRecorder)
    rec._keys, rec._bits = np.zeros(0, np.int64), np.zeros((0, blocks), np.uint32)
    merges = []
    for b, k, w in flushed:
        t0 = time.perf_counter()
        rec._merge(b, k, w)
        merges.append(time.perf_counter() - t0)
    assert np.array_equal(rec._keys, keys) and np.array_equal(rec._bits, bits)
    print(f"  merge check, {len(keys)} pairs in {blocks} flushes: former finish {1e3 * former:.1f} ms; merges per "
          f"flush {', '.join(f'{1e3 * m:.1f}' for m in merges)} ms (finish waits for the last only)")


def print_profile(args, worlds, folder):
    for in_step in (False, True):
        table, rec, record, former = profile_record(args, worlds, folder, in_step)
        n, cells, F = rec.world_count, rec.grid.cell_count, args.frames + 1
        flushes = (F + 31) // 32
        print(f"  profile, {'marks inside the step' if in_step else 'separate pass over the positions'} "
              f"({F} frames eager, {n} worlds x {cells} cells = {n * cells * 4 / 1e6:.1f} MB block, "
              f"{len(record.pair_cell)} occupied (world, cell) pairs):")
        print("    | what | launches | device ms | ms per frame |")
        print("    | --- | --- | --- | --- |")
        for (kind, name), (ms, count) in sorted(table.items(), key=lambda kv: -kv[1][0]):
            print(f"    | {kind} {name} | {count} | {ms:.2f} | {ms / F:.3f} |")
        print(f"    host: flushes {1e3 * rec.host_seconds['flush']:.1f} ms ({flushes} flushes, "
              f"{rec.flushed_bytes / 1e6:.2f} MB to the host), finish {1e3 * rec.host_seconds['finish']:.1f} ms")
        if not in_step:
            print(f"    former host side on the same blocks: whole-block copies {1e3 * former['copy']:.1f} ms "
                  f"({flushes * n * cells * 4 / 1e6:.0f} MB), flatnonzero {1e3 * former['flatnonzero']:.1f} ms, "
                  f"gather {1e3 * former['gather']:.1f} ms, finish (np.unique of every key) "
                  f"{1e3 * former['finish']:.1f} ms")


def panel_seconds(record, count, seed=1):
    """Seconds of ``QueryPanel.ask`` per released box (see the module docstring)."""
    import socket
    import threading

    from warpsim.browse.panel import QueryPanel

    class Reader:  # what the panel reads of a gallery: its worlds and their places
        worlds = [f"world_{record.first_world + w:06d}" for w in range(record.world_count)]
        offsets = {}

    class Gallery:  # a stand-in GalleryViewer: one node per world whose visibility follows the answer
        def __init__(self, server):
            self.server, self.reader, self.root, self.query = server, Reader(), None, None
            self._lock = threading.Lock()
            self.nodes = {w: server.scene.add_icosphere(f"/w/{w}", radius=0.01, subdivisions=1)
                          for w in self.reader.worlds}

        def _refresh(self):
            hidden = self.query.hidden if self.query is not None else ()
            for w, h in self.nodes.items():
                if h.visible != (w not in hidden):
                    h.visible = w not in hidden

    import viser

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    server = viser.ViserServer(host="127.0.0.1", port=port, verbose=False)
    try:
        gallery = Gallery(server)
        gallery.query = QueryPanel(gallery, record=record, thumbnails=False)
        rng = np.random.default_rng(seed)
        lo, hi = record.grid.lo, record.grid.hi
        out = []
        for _ in range(count):
            size = (hi - lo) * rng.uniform(0.1, 0.5, 3)
            a = lo + (hi - lo - size) * rng.uniform(0, 1, 3)
            gallery.query.set_box(a, a + size)
            out.append(gallery.query.answer_seconds)
        return np.array(out)
    finally:
        server.stop()


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
    p.add_argument("--sweep-frames", type=int, default=12, help="frames of the whole sweeps with USD (0: skip)")
    p.add_argument("--set", dest="sets", action="append", default=None, metavar="KEY=VALUE",
                   help="fixed scene parameters (default for teapot: springs=false)")
    p.add_argument("--repeat", type=int, default=2, help="sweeps with and without a record (alternating)")
    p.add_argument("--queries", type=int, default=20)
    p.add_argument("--profile", action="store_true", help="device time per kernel and copy, host time per step")
    p.add_argument("--merge-check", type=int, default=0, metavar="PAIRS",
                   help="only compare the former finish with the per-flush merges on 4 flushes of PAIRS random keys")
    args = p.parse_args()
    if args.merge_check:
        merge_check(args.merge_check)
        return 0
    wp.config.quiet = True
    wp.init()
    vary = args.vary or (VARY if args.scene == "teapot" else [])
    sets = args.sets if args.sets is not None else (["springs=false"] if args.scene == "teapot" else [])
    fixed = dict(item.split("=", 1) for item in sets)
    worlds = sample_worlds(args.scene, fixed, vary, args.worlds, "lhs", 0)
    args.track_map = {}
    if args.track:
        from warpsim.scenes import get_scene
        from warpsim.sweeps.command import resolve_track

        cls = get_scene(args.scene)
        args.track_map = resolve_track(cls, cls.resolve_params(worlds[0]), args.track, "cpu")
    device = wp.get_device(args.device)
    print(f"{args.scene} x {args.worlds} worlds x {args.frames} frames on {device} ({device.name}), "
          f"record resolution {args.resolution}{', tracked ' + ', '.join(args.track_map) if args.track_map else ''}")
    occupancy = {"resolution": args.resolution}
    t_start = time.perf_counter()

    def stage(what):  # progress on stderr (a run cut short still says where it was)
        print(f"  [{time.perf_counter() - t_start:7.1f} s] {what}", file=sys.stderr, flush=True)

    with tempfile.TemporaryDirectory(prefix="bench_occupancy_") as folder:
        small = worlds[: min(4, len(worlds))]
        if args.sweep_frames:
            sweep_seconds(args, small, folder, "warm", occupancy, 2)  # compiles every module
        else:  # no USD written (the GPU machine may lack pxr): compile through the stepping itself
            stepping_record(argparse.Namespace(**{**vars(args), "frames": 2}), small, folder)
            stepping_record(argparse.Namespace(**{**vars(args), "frames": 2}), small, folder, in_step=False)
        if args.profile:
            stage("profile")
            print_profile(args, worlds, folder)
        stage("stepping without a record")
        t_plain, _, _, _ = stepping_record(args, worlds, folder, record=False)
        stage("stepping with the separate pass")
        t_apart, t_apart_rec, _, _ = stepping_record(args, worlds, folder, in_step=False)
        stage("stepping with marks in the step")
        t_step, t_record, rec_path, rec = stepping_record(args, worlds, folder)
        t0 = time.perf_counter()
        record = OccupancyRecord.load(rec_path)
        t_load = time.perf_counter() - t0
        rec_bytes = os.path.getsize(rec_path)
        print(f"  {record.describe()}")
        print(f"  stepping {args.frames} frames without a record   {t_plain:9.3f} s")
        print(f"  separate pass: stepping {t_apart:.3f} s + recording {t_apart_rec:.3f} s = "
              f"{100 * (t_apart + t_apart_rec - t_plain) / t_plain:6.2f} % of stepping alone")
        print(f"  marks in the step ({'on' if rec.in_step else 'not eligible'}): stepping {t_step:.3f} s + recording "
              f"{t_record:.3f} s = {100 * (t_step + t_record - t_plain) / t_plain:6.2f} % of stepping alone "
              f"(goal <= 5 %); record {rec_bytes / 1e6:.3f} MB "
              f"({rec_bytes / record.world_count / record.frame_count:.1f} bytes per world and frame)")
        times, matches = query_times(record, args.queries)
        print(f"  query over {record.world_count} worlds: median {1e3 * np.median(times):.2f} ms, largest "
              f"{1e3 * times.max():.2f} ms over {len(times)} boxes (goal <= 100 ms); record load "
              f"{1e3 * t_load:.1f} ms; matches per box {min(matches)}..{max(matches)}")
        try:
            panel = panel_seconds(record, max(3, args.queries // 4))
        except ImportError as exc:  # the viewer extra (viser) is not installed
            print(f"  gallery answer after release: skipped ({exc})")
        else:
            print(f"  gallery answer after release: median {1e3 * np.median(panel):.1f} ms, largest "
                  f"{1e3 * panel.max():.1f} ms over {len(panel)} boxes, {record.world_count} world nodes "
                  "(goal < 1 s)")
        if args.sweep_frames:
            plain, recorded = [], []
            for _ in range(args.repeat):
                t, layer = sweep_seconds(args, worlds, folder, "plain", None, args.sweep_frames)
                plain.append(t)
                t, layer = sweep_seconds(args, worlds, folder, "rec", occupancy, args.sweep_frames)
                recorded.append(t)
            t_plain, t_rec = float(np.median(plain)), float(np.median(recorded))
            usd_bytes = os.path.getsize(layer)
            sweep_rec_bytes = os.path.getsize(os.path.join(folder, "rec.npz"))
            print(f"  sweep of {args.sweep_frames} frames without record {t_plain:9.3f} s   (runs: "
                  f"{', '.join(f'{t:.3f}' for t in plain)})")
            print(f"  sweep of {args.sweep_frames} frames with record    {t_rec:9.3f} s   (runs: "
                  f"{', '.join(f'{t:.3f}' for t in recorded)})")
            print(f"  record cost (difference of sweeps)   {100 * (t_rec - t_plain) / t_plain:6.2f} % of the sweep "
                  "(goal <= 5 %)")
            print(f"  bytes: record {sweep_rec_bytes / 1e6:.3f} MB, USD batch layer {usd_bytes / 1e6:.3f} MB: "
                  f"{100 * sweep_rec_bytes / usd_bytes:.2f} %   (goal <= 10 %)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
