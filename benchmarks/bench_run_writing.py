"""How much of ``warpsim run SCENE`` is writing, with the chunks written by the run's own process
and by a worker process (issue 50, part 5), in one process, stage by stage.

For each scene and each worker count (``WARPSIM_WRITE_WORKERS``), the command itself
(``warpsim.cli.main(["run", ...])``) with timers around its stages:

  total     wall time of the command [s] (modules loaded and kernels compiled by a warm-up run)
  advance   Scene.advance [s] (on a GPU: launches, and the waits a frame's host work makes)
  data      Scene.frame_data: the frame's arrays brought to the host (surface meshing included) [s]
  write     UsdCacheWriter.write_frame: samples authored (0 workers) or staged for the worker [s]
  close     UsdCacheWriter.close: the last chunk, the root (and the worker's last chunks) [s]
  writing   (write + close) / total: the share of the command the writing holds it up

    python benchmarks/bench_run_writing.py --device cuda:0 --scenes dam_break smoke --frames 120
"""
from __future__ import annotations

import argparse
import contextlib
import io
import os
import shutil
import sys
import tempfile
import time

from bench_sweep_command import Timers

STAGES = ("advance", "data", "write", "close")


def timed_run(argv, seconds):
    """Run ``warpsim`` ``argv`` here with ``seconds[stage]`` accumulating each stage's time."""
    from warpsim.cli import main
    from warpsim.scenes import get_scene
    from warpsim.usd.writer import UsdCacheWriter

    scene_class = get_scene(argv[1])

    timers = Timers(seconds)  # (bench_sweep_command's; each stage counted once, not inside another)
    timers.wrap(scene_class, "advance", "advance")
    timers.wrap(scene_class, "frame_data", "data")
    timers.wrap(UsdCacheWriter, "write_frame", "write")
    timers.wrap(UsdCacheWriter, "close", "close")
    out, err = io.StringIO(), io.StringIO()
    t0 = time.perf_counter()
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            code = main(argv)
    finally:
        total = time.perf_counter() - t0
        timers.restore()
    if code not in (0, None):
        raise SystemExit(f"warpsim {' '.join(argv)} exited {code}: {err.getvalue().strip()[-400:]}")
    return total


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--device", default="cpu")
    p.add_argument("--scenes", nargs="+", default=["dam_break", "smoke"])
    p.add_argument("--frames", type=int, default=120)
    p.add_argument("--workers", nargs="+", default=["0", "1"], help="WARPSIM_WRITE_WORKERS values to compare")
    p.add_argument("--set", action="append", default=[], dest="sets", help="as warpsim run --set (every scene)")
    args = p.parse_args(argv)
    from warpsim.verbosity import set_warp_verbosity

    set_warp_verbosity()
    folder = tempfile.mkdtemp(prefix="bench_run_writing_")
    rows = []
    try:
        for scene in args.scenes:
            base = ["run", scene, "--device", args.device, "--no-progress", *[f"--set={s}" for s in args.sets]]
            timed_run([*base, "--frames", "2", "--out", os.path.join(folder, "warm", f"{scene}.usda")],
                      dict.fromkeys(STAGES, 0.0))
            for workers in args.workers:
                os.environ["WARPSIM_WRITE_WORKERS"] = workers
                seconds = dict.fromkeys(STAGES, 0.0)
                out = os.path.join(folder, f"{scene}_{workers}", f"{scene}.usda")
                total = timed_run([*base, "--frames", str(args.frames), "--out", out], seconds)
                written = sum(os.path.getsize(os.path.join(d, f)) for d, _, fs in os.walk(os.path.dirname(out))
                              for f in fs)
                rows.append((scene, workers, total, seconds, written))
                shutil.rmtree(os.path.dirname(out), ignore_errors=True)
    finally:
        os.environ.pop("WARPSIM_WRITE_WORKERS", None)
        shutil.rmtree(folder, ignore_errors=True)
    print(f"device {args.device}, {args.frames} frames")
    head = ["scene", "workers", "total", *STAGES, "writing", "MB"]
    print(" | ".join(f"{h:>10}" for h in head))
    for scene, workers, total, seconds, written in rows:
        share = (seconds["write"] + seconds["close"]) / total
        print(" | ".join([f"{scene:>10}", f"{workers:>10}", f"{total:10.2f}", *[f"{seconds[s]:10.2f}" for s in STAGES],
                          f"{100 * share:9.1f}%", f"{written / 1e6:10.1f}"]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
