"""A sweep on a local Ray cluster (batches as Ray tasks) against the same sweep in one process.

    python benchmarks/bench_ray_sweep.py [--scene springs] [--worlds 64] [--batches 4] [--frames 120]
                                         [--device cpu|cuda] [--ray-cpus 2] [--vary KEY=SPEC ...]

Both run through the command line in this process, on the same sampled worlds:

* single: ``warpsim sweep SCENE --worlds N ...`` (one batched run of every world);
* ray:    the same with ``--ray --batch-size N/B`` on a local cluster of ``--ray-cpus`` CPUs (one
  task per batch, one CPU each; one GPU each with ``--device cuda``, so on one GPU they queue).

A warm-up sweep of two worlds first puts every kernel in Warp's cache (``~/.cache/warp``), which
the Ray workers (fresh processes) then load instead of compiling. The cluster start-up
(``ray.init``) is timed on its own; the ray sweep reuses that connection. Prints both wall times,
the ratio ray / single (goal <= 1.5 on the 2-core machine) with and without the start-up, each
batch's seconds inside its task, and checks the two tables are identical byte for byte.
"""
import argparse
import io
import json
import logging
import os
import shutil
import sys
import tempfile
import time


def sweep(argv):
    from warpsim.cli import main

    out, err = io.StringIO(), io.StringIO()
    t0 = time.perf_counter()
    rc = main(["sweep", *argv, "--no-progress"], out=out, err=err)
    seconds = time.perf_counter() - t0
    if rc != 0:
        sys.exit(f"sweep {' '.join(argv)} failed ({rc}):\n{err.getvalue()}")
    return seconds


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scene", default="springs")
    p.add_argument("--worlds", type=int, default=64)
    p.add_argument("--batches", type=int, default=4)
    p.add_argument("--frames", type=int, default=120)
    p.add_argument("--device", default="cpu", help="cpu or cuda (Ray tasks then take one GPU each)")
    p.add_argument("--ray-cpus", type=int, default=os.cpu_count())
    p.add_argument("--vary", action="append", default=None,
                   help="--vary specs (default: springs stiffness=50:2000 and damping=0.01:0.5)")
    a = p.parse_args()
    vary = a.vary or ["stiffness=50:2000", "damping=0.01:0.5"]
    batch_size = -(-a.worlds // a.batches)
    folder = tempfile.mkdtemp(prefix="bench_ray_sweep_")
    try:
        common = [a.scene, "--worlds", str(a.worlds), "--frames", str(a.frames), "--device", a.device,
                  "--sample", "lhs"] + [f"--vary={v}" for v in vary]
        warm = [a.scene, "--worlds", "2", "--frames", "2", "--device", a.device, "--sample", "lhs"] + \
            [f"--vary={v}" for v in vary]
        sweep(warm + ["--out", os.path.join(folder, "warm.usda")])
        single = sweep(common + ["--out", os.path.join(folder, "single.usda")])

        import ray

        t0 = time.perf_counter()
        ray.init(num_cpus=a.ray_cpus, include_dashboard=False, log_to_driver=False, logging_level=logging.ERROR)
        startup = time.perf_counter() - t0
        try:
            distributed = sweep(common + ["--out", os.path.join(folder, "ray.usda"), "--ray",
                                          "--batch-size", str(batch_size)])
        finally:
            ray.shutdown()
        with open(os.path.join(folder, "ray.ray-manifest.json")) as fh:
            batches = json.load(fh)["batches"]
        with open(os.path.join(folder, "single.csv")) as f1, open(os.path.join(folder, "ray.csv")) as f2:
            same = f1.read() == f2.read()
        print(f"{a.scene}: {a.worlds} worlds x {a.frames} frames on {a.device}; Ray: {len(batches)} batches of "
              f"<= {batch_size} on a local cluster of {a.ray_cpus} CPUs")
        print(f"  single process        {single:8.2f} s")
        print(f"  ray (cluster up)      {distributed:8.2f} s   ratio ray/single {distributed / single:.2f}x")
        print(f"  ray cluster start-up  {startup:8.2f} s   ratio incl. start-up {(distributed + startup) / single:.2f}x")
        for k in sorted(batches, key=int):
            b = batches[k]
            print(f"  batch {k}: worlds {b['first_world']}..{b['first_world'] + b['world_count'] - 1}  "
                  f"{b['seconds']:.2f} s in its task on {b['host']} (pid {b['pid']})")
        print(f"  tables identical: {same}")
        if not same:
            sys.exit(1)
    finally:
        shutil.rmtree(folder, ignore_errors=True)


if __name__ == "__main__":
    main()
