"""The whole ``warpsim sweep`` command, stage by stage, against its stepping alone (issue 50).

For each world count given, in one process: the command itself (``warpsim.cli.main(["sweep", ...])``:
preflight, stepping, frame data and USD writing, closing the layer, the table, the occupancy record
and thumbnails) with timers around its stages, then the same worlds stepped alone (a
``WorldBatch`` advancing ``--frames`` frames, no output) as the reference. Prints a table:

  total       wall time of the command [s] (modules already imported; ``startup`` below is a
              fresh process running a 1-world, 0-frame sweep)
  stepping    WorldBatch.advance inside the command [s]
  writing     host copies, frame data and USD samples (world_slices, batch_frame_data /
              world_frame_data, write_batch / write_worlds / observe) [s]
  closing     completing the layer (BatchLayerWriter.close) [s]
  record      the occupancy record completed and saved (OccupancyRecorder.finish, OccupancyRecord.save) [s]
  thumbs      thumbnails_after_sweep [s];   table: write_table [s]
  preflight   estimates before the first step (memory, disk, --store) [s]
  other       the rest (building the batch, stability limits, metrics, record, root) [s]
  alone       the same worlds stepped alone in this process [s];  ratio: total / alone
  us/wf       (total - alone) per world and frame [us] (frames stepped, frame 0 aside)
  MB          bytes the command wrote (layers, chunks, table, record, root, thumbnails) [MB]
  MB/s        MB / total;  MB/s w: MB / (writing + closing), the rate while writing held up the loop
  whole       with ``--whole N``: the command as a user runs it, ``python -m warpsim sweep ...`` in a fresh
              process (start-up, imports, Warp's start, the sweep, the pool workers' exit), N runs [s];
              the issue's "whole command" goal is this figure (``total`` + ``startup`` counts the
              1-world sweep's own building, writing and closing twice)

and, with two or more world counts, the extra cost per world and frame of the command between
the first and last counts, (T(W2) - T(W1)) / ((W2 - W1) x frames) [us] (issue 50's CPU goal:
``warpsim sweep bounce``, 2,000 worlds against 100, <= 30 us).

    python benchmarks/bench_sweep_command.py --scene bounce --worlds 100 2000 --frames 30 --device cpu
    python benchmarks/bench_sweep_command.py --scene teapot --worlds 4 16 --frames 12 --device cpu \\
        --vary stiffness=20:60 --store all
    PYTHONPATH=/tmp/base python benchmarks/bench_sweep_command.py ...   # an older tree (stages it lacks read 0)
"""
from __future__ import annotations

import argparse
import contextlib
import io
import os
import shutil
import subprocess
import sys
import tempfile
import time

STAGES = ("stepping", "writing", "closing", "record", "thumbs", "table", "preflight")


class Timers:
    """Wraps methods so their calls add to ``seconds[stage]`` (a call inside another timed one
    counts once); :meth:`restore` puts the methods back."""

    def __init__(self, seconds=None):
        self.seconds = dict.fromkeys(STAGES, 0.0) if seconds is None else seconds
        self._patched = []
        self._depth = 0

    def wrap(self, owner, name, stage):
        fn = getattr(owner, name, None)
        if fn is None:
            return
        timers = self

        def timed(*args, **kwargs):
            if timers._depth:  # a stage inside another counts once
                return fn(*args, **kwargs)
            timers._depth += 1
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                timers.seconds[stage] += time.perf_counter() - t0
                timers._depth -= 1

        self._patched.append((owner, name, fn))
        setattr(owner, name, timed)

    def restore(self):
        for owner, name, fn in reversed(self._patched):
            setattr(owner, name, fn)
        self._patched = []


def _install(timers):
    from warpsim.browse import panel
    from warpsim.sweeps import command, sweep, usd
    from warpsim.worlds import batch

    timers.wrap(batch.WorldBatch, "advance", "stepping")
    for name in ("world_slices", "batch_frame_data", "world_frame_data"):
        timers.wrap(batch.WorldBatch, name, "writing")
    for name in ("write_batch", "write_worlds", "observe", "observe_batch"):
        timers.wrap(usd.BatchLayerWriter, name, "writing")
    timers.wrap(usd.BatchLayerWriter, "close", "closing")
    timers.wrap(panel, "thumbnails_after_sweep", "thumbs")
    timers.wrap(sweep, "write_table", "table")
    timers.wrap(command, "_check_resources", "preflight")
    from warpsim.browse.occupancy import OccupancyRecorder

    finish = OccupancyRecorder.finish

    def said_finish(self):  # the record's own host timers, said once a run (stderr)
        t0 = time.perf_counter()
        try:
            return finish(self)
        finally:
            parts = ", ".join(f"{k} {v:.3f} s" for k, v in self.host_seconds.items())
            sys.__stderr__.write(f"occupancy record: finish {time.perf_counter() - t0:.3f} s ({parts})\n")

    timers._patched.append((OccupancyRecorder, "finish", finish))
    OccupancyRecorder.finish = said_finish
    from warpsim.browse.occupancy import OccupancyRecord

    timers.wrap(OccupancyRecorder, "finish", "record")
    timers.wrap(OccupancyRecord, "save", "record")


class StackSampler:
    """Samples the main thread's Python stack every ``interval`` s in a thread (wall time, waits
    included: a frame blocked in a lock or a sleep is counted where it waits) and prints, for the
    functions of the ``warpsim`` package, the wall time they were on the stack (inclusive) and at
    its top among warpsim's frames (self), the ``top`` largest of each."""

    def __init__(self, interval=0.005):
        import threading

        self.interval, self.samples, self._stop = interval, [], threading.Event()
        self._main = threading.main_thread().ident
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self):
        while not self._stop.wait(self.interval):
            frame = sys._current_frames().get(self._main)
            stack = []
            while frame is not None:
                code = frame.f_code
                if "warpsim" in code.co_filename and "benchmarks" not in code.co_filename:
                    rel = code.co_filename.split("warpsim", 1)[1].lstrip("/")
                    stack.append(f"{rel}:{code.co_name}")
                frame = frame.f_back
            self.samples.append(stack)

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()

    def report(self, top=30, file=None):
        from collections import Counter

        inclusive, own = Counter(), Counter()
        for stack in self.samples:
            for name in set(stack):
                inclusive[name] += 1
            if stack:
                own[stack[0]] += 1
        dt = self.interval
        print(f"stack samples: {len(self.samples)} every {1e3 * dt:.0f} ms", file=file)
        for title, counts in (("inclusive", inclusive), ("self (innermost warpsim frame)", own)):
            print(f"  {title}:", file=file)
            for name, c in counts.most_common(top):
                print(f"    {c * dt:7.2f} s  {name}", file=file)


def run_command(argv, stacks=False):
    """(seconds, stage seconds, stdout) of ``warpsim`` ``argv`` run in this process; ``stacks``:
    print where the main thread's wall time went (:class:`StackSampler`)."""
    from warpsim.cli import main

    timers = Timers()
    _install(timers)
    out, err = io.StringIO(), io.StringIO()
    sampler = StackSampler() if stacks else contextlib.nullcontext()
    t0 = time.perf_counter()
    try:
        with sampler, contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            code = main(argv)
    finally:
        total = time.perf_counter() - t0
        timers.restore()
    if stacks:
        sampler.report()
    if code not in (0, None):
        raise SystemExit(f"warpsim {' '.join(argv)} exited {code}: {err.getvalue().strip()[-400:]}")
    return total, timers.seconds, out.getvalue()


def step_alone(scene, world_params, frames, device, substeps=None):
    """Seconds of ``frames`` frames of these worlds stepped alone (a WorldBatch, no output)."""
    import warp as wp

    from warpsim.scenes import get_scene
    from warpsim.sweeps.sweep import make_batch, sweep_timing, timed_params

    cls = get_scene(scene)
    timing = sweep_timing(cls, world_params, None, substeps)
    params = timed_params(cls, world_params, timing)
    batch = make_batch(cls, params, device=device)
    taken = batch.use_timing(timing)
    wp.synchronize_device(batch.device)
    t0 = time.perf_counter()
    for _ in range(int(frames)):
        batch.advance(timing.frame_dt, taken.steps if not getattr(batch, "own_counts", False) else timing.steps)
    wp.synchronize_device(batch.device)
    return time.perf_counter() - t0


def whole_seconds(argv, folder):
    """``python -m warpsim`` ``argv`` in a fresh process, its outputs removed after [s]."""
    shutil.rmtree(folder, ignore_errors=True)
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "warpsim", *argv], check=True, capture_output=True)
    seconds = time.perf_counter() - t0
    shutil.rmtree(folder, ignore_errors=True)
    return seconds


def startup_seconds(scene, device):
    """A fresh process running a 1-world, 0-frame sweep (imports, Warp's start, one world) [s]."""
    folder = tempfile.mkdtemp(prefix="bench_sweep_start_")
    try:
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-m", "warpsim", "sweep", scene, "--worlds", "1", "--frames", "0", "--device",
                        device, "--out", os.path.join(folder, "s.usda"), "--no-progress", "--no-thumbnails"],
                       check=True, capture_output=True)
        return time.perf_counter() - t0
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scene", default="bounce")
    p.add_argument("--worlds", type=int, nargs="+", default=[100, 2000])
    p.add_argument("--frames", type=int, default=30)
    p.add_argument("--device", default="cpu")
    p.add_argument("--vary", action="append", default=[], help="as warpsim sweep --vary (default: none)")
    p.add_argument("--sample", default=None, help="as warpsim sweep --sample (grid, random, lhs; default grid)")
    p.add_argument("--seed", default=None, help="as warpsim sweep --seed")
    p.add_argument("--store", default=None, help="all, preview or none (default: the command's choice)")
    p.add_argument("--thumbnails", action="store_true", help="draw thumbnails (default: --no-thumbnails)")
    p.add_argument("--no-startup", action="store_true", help="skip the fresh-process start-up measurement")
    p.add_argument("--whole", type=int, default=0, metavar="N",
                   help="also run the command N times in a fresh process each and report the wall time")
    p.add_argument("--stacks", action="store_true", help="where the main thread's wall time went, by warpsim function")
    p.add_argument("--workers", nargs="+", default=["auto"],
                   help="chunk-writing worker processes, each value a run of every world count (auto: the "
                        "sweep's choice; N: WARPSIM_WRITE_WORKERS=N), e.g. --workers 0 auto")
    args = p.parse_args(argv)
    from warpsim.verbosity import set_warp_verbosity

    set_warp_verbosity()
    import warp as wp

    wp.init()
    import warpsim

    folder = tempfile.mkdtemp(prefix="bench_sweep_command_")
    print(f"warpsim {warpsim.__version__} from {os.path.dirname(warpsim.__file__)}; scene {args.scene}, "
          f"{args.frames} frames, device {args.device}, store {args.store or 'default'}, thumbnails "
          f"{'on' if args.thumbnails else 'off'}")
    rows = []
    sampling = [*(["--sample", args.sample] if args.sample else []), *(["--seed", args.seed] if args.seed else [])]
    try:
        # warm: every module and kernel loaded before the first timed run
        run_command(["sweep", args.scene, "--worlds", "2", "--frames", "1", "--device", args.device, "--out",
                     os.path.join(folder, "warm", "s.usda"), "--no-progress", "--no-thumbnails",
                     *[f"--vary={v}" for v in args.vary], *sampling])
        for workers, n in [(w, n) for w in args.workers for n in args.worlds]:
            if workers == "auto":
                os.environ.pop("WARPSIM_WRITE_WORKERS", None)
            else:
                os.environ["WARPSIM_WRITE_WORKERS"] = workers
            argv = ["sweep", args.scene, "--worlds", str(n), "--frames", str(args.frames), "--device", args.device,
                    "--out", os.path.join(folder, f"w{n}", "s.usda"), "--no-progress",
                    *[f"--vary={v}" for v in args.vary], *sampling]
            if args.store:
                argv += ["--store", args.store]
            if not args.thumbnails:
                argv += ["--no-thumbnails"]
            total, stages, _ = run_command(argv, stacks=args.stacks)
            from warpsim.sweeps import sample_worlds

            alone = step_alone(args.scene, sample_worlds(args.scene, {}, args.vary, n, args.sample or "grid",
                                                         int(args.seed or 0)), args.frames, args.device)
            written = sum(os.path.getsize(os.path.join(d, f)) for d, _, fs in os.walk(os.path.join(folder, f"w{n}"))
                          for f in fs)
            rows.append((workers, n, total, stages, alone, written))
            shutil.rmtree(os.path.join(folder, f"w{n}"), ignore_errors=True)
            wholes = [whole_seconds(argv, os.path.join(folder, f"w{n}")) for _ in range(args.whole)]
            if wholes:
                print(f"whole command, {n} worlds, fresh process: " + ", ".join(f"{w:.2f}" for w in wholes)
                      + f" s (best {min(wholes):.2f} s, {min(wholes) / max(alone, 1e-9):.1f}x the stepping alone)")
        start = None if args.no_startup else startup_seconds(args.scene, args.device)
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    os.environ.pop("WARPSIM_WRITE_WORKERS", None)
    head = ["workers", "worlds", "total", *STAGES, "other", "alone", "ratio", "us/wf", "MB", "MB/s", "MB/s w"]
    print(" | ".join(f"{h:>9}" for h in head))
    for workers, n, total, stages, alone, written in rows:
        other = total - sum(stages.values())
        per = 1e6 * (total - alone) / (n * max(args.frames, 1))
        cells = [f"{workers:>9}", f"{n:>9}", f"{total:9.3f}", *[f"{stages[s]:9.3f}" for s in STAGES], f"{other:9.3f}",
                 f"{alone:9.4f}", f"{total / max(alone, 1e-9):9.1f}", f"{per:9.1f}", f"{written / 1e6:9.1f}",
                 f"{written / 1e6 / total:9.1f}", f"{written / 1e6 / max(stages['writing'] + stages['closing'], 1e-9):9.1f}"]
        print(" | ".join(cells))
    if len(rows) >= 2 and len(args.worlds) >= 2:
        (_, n1, t1, _, a1, _), (_, n2, t2, _, a2, _) = rows[0], rows[len(args.worlds) - 1]
        extra = 1e6 * (t2 - t1) / ((n2 - n1) * max(args.frames, 1))
        step = 1e6 * (a2 - a1) / ((n2 - n1) * max(args.frames, 1))
        print(f"extra cost per world and frame, {n2} worlds against {n1}: {extra:.1f} us (stepping alone: "
              f"{step:.1f} us of it)")
    if start is not None:
        print(f"startup (fresh process, 1 world, 0 frames): {start:.2f} s")


if __name__ == "__main__":
    main()
