"""A sweep on a local Ray cluster (batches as Ray tasks) against the same sweep in one process.

    python benchmarks/bench_ray_sweep.py [--scene teapot] [--worlds 64] [--batches 4] [--frames 60]
                                         [--device cpu|cuda] [--ray-cpus N] [--vary KEY=SPEC ...]

The same sampled worlds are swept four ways, each through the command line:

* single, warm: ``warpsim sweep SCENE --worlds N ...`` in this process, after a warm-up sweep of two
  worlds (kernels loaded, modules imported);
* ray, warm driver: the same with ``--ray --batch-size N/B`` in this process, on a local cluster of
  ``--ray-cpus`` CPUs started beforehand (one task per batch, one CPU each; one GPU each with
  ``--device cuda``, so on one GPU the tasks queue); the workers are fresh processes;
* single, fresh process: ``python -m warpsim sweep ...`` as a new process (what a user types);
* ray, fresh process: ``python -m warpsim sweep ... --ray ADDRESS`` as a new process joining the
  running cluster (what a user types once ``ray start --head`` has run).

The cluster start-up (``ray.init``) is timed on its own. Kernels come from Warp's cache
(``~/.cache/warp``; the warm-up fills it), so no run compiles. Prints the wall times, the ratios
ray / single (goal <= 1.5 on the 2-core machine), each batch's seconds inside its task (from the
manifest) and checks that every table is identical byte for byte.
"""
import argparse
import io
import json
import logging
import os
import shutil
import subprocess
import sys
import tempfile
import time

from warpsim.cli_common import DefaultsHelpFormatter, run_script


def sweep(argv):
    """Seconds of ``warpsim sweep ARGV`` run in this process."""
    from warpsim.cli import main

    out, err = io.StringIO(), io.StringIO()
    t0 = time.perf_counter()
    rc = main(["sweep", *argv, "--no-progress"], out=out, err=err)
    seconds = time.perf_counter() - t0
    if rc != 0:
        sys.exit(f"sweep {' '.join(argv)} failed ({rc}):\n{err.getvalue()}")
    return seconds


def sweep_process(argv):
    """Seconds of ``python -m warpsim sweep ARGV`` as a new process (interpreter start included)."""
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "warpsim", "sweep", *argv, "--no-progress"],
                       check=False, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    seconds = time.perf_counter() - t0
    if r.returncode != 0:
        sys.exit(f"sweep {' '.join(argv)} failed ({r.returncode}):\n{r.stderr}")
    return seconds


def batch_lines(folder, name):
    with open(os.path.join(folder, f"{name}.ray-manifest.json")) as fh:
        batches = json.load(fh)["batches"]
    return [f"    batch {k}: worlds {b['first_world']}..{b['first_world'] + b['world_count'] - 1}  "
            f"{b['seconds']:.2f} s in its task on {b['host']} (pid {b['pid']})" for k, b in
            sorted(batches.items(), key=lambda kv: int(kv[0]))]


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0], formatter_class=DefaultsHelpFormatter)
    p.add_argument("--scene", default="teapot")
    p.add_argument("--worlds", type=int, default=64)
    p.add_argument("--batches", type=int, default=4)
    p.add_argument("--frames", type=int, default=60)
    p.add_argument("--device", default="cpu", help="cpu or cuda (Ray tasks then take one GPU each)")
    p.add_argument("--ray-cpus", type=int, default=os.cpu_count())
    p.add_argument("--vary", action="append", default=None,
                   help="--vary specs (default for teapot: stiffness=20:80 restitution=0.2:0.8; springs: "
                        "stiffness=50:2000 damping=0.01:0.5)")
    a = p.parse_args()
    vary = a.vary or (["stiffness=20:80", "restitution=0.2:0.8"] if a.scene == "teapot" else
                      ["stiffness=50:2000", "damping=0.01:0.5"] if a.scene == "springs" else None)
    if vary is None:
        sys.exit(f"give --vary for scene {a.scene!r}")
    batch_size = -(-a.worlds // a.batches)
    folder = tempfile.mkdtemp(prefix="bench_ray_sweep_")
    try:
        def args(name, worlds=a.worlds, frames=a.frames):
            return [a.scene, "--worlds", str(worlds), "--frames", str(frames), "--device", a.device, "--sample",
                    "lhs", "--out", os.path.join(folder, f"{name}.usda")] + [f"--vary={v}" for v in vary]

        ray_args = ["--batch-size", str(batch_size)]
        sweep(args("warm", worlds=2, frames=2))
        single = sweep(args("single"))
        single_cold = sweep_process(args("single_cold"))

        import ray

        t0 = time.perf_counter()
        ray.init(num_cpus=a.ray_cpus, include_dashboard=False, log_to_driver=False, logging_level=logging.ERROR)
        startup = time.perf_counter() - t0
        try:
            address = ray.get_runtime_context().gcs_address
            distributed = sweep(args("ray") + ["--ray"] + ray_args)
            distributed_cold = sweep_process(args("ray_cold") + ["--ray", address] + ray_args)
        finally:
            ray.shutdown()
        tables = []
        for name in ("single", "single_cold", "ray", "ray_cold"):
            with open(os.path.join(folder, f"{name}.csv")) as fh:
                tables.append(fh.read())
        same = all(t == tables[0] for t in tables)
        print(f"{a.scene}: {a.worlds} worlds x {a.frames} frames on {a.device}; Ray: {a.batches} batches of "
              f"<= {batch_size} worlds on a local cluster of {a.ray_cpus} CPUs (vary {' '.join(vary)})")
        print(f"  single, warm (in process)       {single:8.2f} s")
        print(f"  ray, warm driver (in process)   {distributed:8.2f} s   ray/single {distributed / single:.2f}x")
        print(*batch_lines(folder, "ray"), sep="\n")
        print(f"  single, fresh process           {single_cold:8.2f} s")
        print(f"  ray, fresh driver process       {distributed_cold:8.2f} s   ray/single "
              f"{distributed_cold / single_cold:.2f}x")
        print(*batch_lines(folder, "ray_cold"), sep="\n")
        print(f"  local cluster start-up          {startup:8.2f} s   (ray fresh + start-up)/single fresh "
              f"{(distributed_cold + startup) / single_cold:.2f}x")
        print(f"  tables identical: {same}")
        if not same:
            sys.exit(1)
    finally:
        shutil.rmtree(folder, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(run_script(main))
