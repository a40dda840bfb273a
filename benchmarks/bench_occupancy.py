"""What an occupancy record costs a sweep, and how fast a spacetime query answers over it.

Measured in one process, on one device, for N worlds of a scene (default: teapots with four
varied parameters, ``springs=false`` so a world's USD holds its surface only):
  stepping  F frames of the batch (``advance`` + metrics, eager) with the recorder's per-frame
            work (``update``, the 32-frame block copies to the host) timed apart with a device
            synchronisation around each, then ``finish`` + ``save``: the record's cost as % of
            stepping alone (a stricter base than the sweep, which also writes USD);
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

    python benchmarks/bench_occupancy.py --device cuda:0 --worlds 10000 --frames 120 --sweep-frames 6
    python benchmarks/bench_occupancy.py --device cpu --worlds 1000 --frames 120 --sweep-frames 12
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
from warpsim.worlds.occupancy import OccupancyRecord
from warpsim.worlds.query import Region, answer_region

VARY = ["stiffness=20:60", "height=0.4:0.6", "restitution=0.2:0.8", "friction=0.1:0.5"]


def sweep_seconds(args, worlds, folder, tag, occupancy, frames):
    layer = os.path.join(folder, f"{tag}.batch_0000.usdc")
    wp.synchronize_device(args.device)
    t0 = time.perf_counter()
    run_batch(args.scene, worlds, frames=frames, device=args.device, layer_path=layer,
              track=args.track_map, occupancy=occupancy and {**occupancy, "path": os.path.join(folder, f"{tag}.npz")})
    wp.synchronize_device(args.device)
    return time.perf_counter() - t0, layer


def stepping_record(args, worlds, folder):
    """(stepping seconds, recorder seconds, record path): F frames of a batch, the recorder's work
    timed apart (synchronised), its record saved. On CUDA both run as captured graphs, as in a
    sweep (``run_batch`` captures a frame's stepping, metrics and recording together)."""
    from warpsim.scenes import get_scene
    from warpsim.worlds.metrics import WorldMetrics
    from warpsim.worlds.sweep import _recorder, frame_timing, make_batch
    from warpsim.worlds.usd import BatchLayerWriter

    cls = get_scene(args.scene)
    fps, substeps, frame_dt = frame_timing(cls, cls.resolve_params(worlds[0]))
    batch = make_batch(cls, worlds, device=args.device)
    stats = WorldMetrics(batch)
    # the recorder a sweep makes (its grid also covers the static geometry the USD writer declares)
    writer = BatchLayerWriter(os.path.join(folder, "stepping.usdc"), batch.scene, 0, batch.world_count, fps)
    rec = _recorder(batch, {"resolution": args.resolution}, args.frames, args.track_map or None, fps, 0,
                    args.scene, writer)

    def step():
        batch.advance(frame_dt, substeps)
        stats.update()

    step()  # loads every module (this frame is not timed)
    use_graph = batch.device.is_cuda and batch.can_capture()
    if use_graph:
        with wp.ScopedCapture(device=batch.device) as capture:
            step()
        step_graph = capture.graph
        step = lambda: wp.capture_launch(step_graph)  # noqa: E731
    record_frame = rec.update
    wp.synchronize_device(args.device)
    t_step = t_record = 0.0
    for frame in range(args.frames + 1):
        t0 = time.perf_counter()
        if frame:
            step()
        wp.synchronize_device(args.device)
        t1 = time.perf_counter()
        record_frame()
        rec.after_frame()
        wp.synchronize_device(args.device)
        t_step, t_record = t_step + t1 - t0, t_record + time.perf_counter() - t1
        if frame == 0 and use_graph:  # frame 0 ran eagerly (module loaded): replay the rest
            with wp.ScopedCapture(device=batch.device) as capture:
                rec.update()
            record_graph = capture.graph
            record_frame = lambda: wp.capture_launch(record_graph)  # noqa: E731
    path = os.path.join(folder, "stepping.npz")
    t0 = time.perf_counter()
    rec.finish().save(path)
    return t_step, t_record + time.perf_counter() - t0, path


def panel_seconds(record, count, seed=1):
    """Seconds of ``QueryPanel.ask`` per released box (see the module docstring)."""
    import socket
    import threading

    from warpsim.worlds.browse import QueryPanel

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
    args = p.parse_args()
    wp.config.quiet = True
    wp.init()
    vary = args.vary or (VARY if args.scene == "teapot" else [])
    sets = args.sets if args.sets is not None else (["springs=false"] if args.scene == "teapot" else [])
    fixed = dict(item.split("=", 1) for item in sets)
    worlds = sample_worlds(args.scene, fixed, vary, args.worlds, "lhs", 0)
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
        sweep_seconds(args, worlds[: min(4, len(worlds))], folder, "warm", occupancy, 2)  # compiles every module
        t_step, t_record, rec_path = stepping_record(args, worlds, folder)
        t0 = time.perf_counter()
        record = OccupancyRecord.load(rec_path)
        t_load = time.perf_counter() - t0
        rec_bytes = os.path.getsize(rec_path)
        print(f"  {record.describe()}")
        print(f"  stepping {args.frames} frames      {t_step:9.3f} s")
        print(f"  recording them          {t_record:9.3f} s   {100 * t_record / t_step:6.2f} % of stepping alone; "
              f"record {rec_bytes / 1e6:.3f} MB ({rec_bytes / record.world_count / record.frame_count:.1f} bytes "
              "per world and frame)")
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
