"""One sweep of teapot worlds split over several GPUs of one host, against the same worlds on one.

Measured in one process, for each device set given (the first is the reference, e.g. cuda:0):
  step      the worlds split into contiguous blocks (``warpsim.distributed.devices.split_blocks``,
            sized from each device's free memory), one ``WorldBatch`` per block built with the
            whole sweep as its reference, each block's frame captured as a CUDA graph on its own
            device and replayed from its own thread; the wall time of ``--frames`` frames of
            every block (all threads released together, each synchronising its device) gives
            steps per second and the scaling efficiency t1 / (N x tN) against the reference;
  equal     whether every world's final positions and velocities equal the reference's bit
            for bit (they should: a world's arithmetic does not depend on its block);
  sweep     (``--sweep-worlds W``) the whole ``warpsim sweep`` with USD writing, table and
            occupancy record, on the reference device and on each device set: wall time, and the
            table, record and every world's samples compared byte for byte (needs ``pxr``).

    python benchmarks/bench_devices.py --worlds 100000 --devices cuda:0 cuda:0,cuda:1 all
    python benchmarks/bench_devices.py --worlds 100000 --devices cuda:0 cuda:0,cuda:1 all --sweep-worlds 1000 \
        --sweep-devices cuda:0 all
    python benchmarks/bench_devices.py --worlds 8 --devices cpu cpu,cpu --frames 2 --sweep-worlds 4   # check
"""

import argparse
import io
import os
import sys
import tempfile
import threading
import time

import numpy as np
import warp as wp

from warpsim.cli_common import DefaultsHelpFormatter, run_script
from warpsim.distributed.devices import device_capacity, parse_devices, split_blocks
from warpsim.scenes import get_scene
from warpsim.verbosity import set_warp_verbosity
from warpsim.sweeps import sample_worlds
from warpsim.worlds import WorldBatch
from warpsim.sweeps.preflight import estimate_sweep_bytes

VARY = ["stiffness=20:60", "height=0.4:0.6", "restitution=0.2:0.8", "friction=0.1:0.5"]
FIXED = {"resolution": "low", "springs": False}


def frame_of(batch, frame_dt, steps):
    """One frame of ``steps`` steps of a batch (the shared path's stepper: the count given, not the
    scene's automatic one, so every block and the reference take the same steps)."""
    def run():
        batch.stepper.frame(frame_dt, steps)
        batch.end_frame()
    return run


def in_threads(fns):
    """Run ``fns`` (one per block) each in its own thread; re-raise the first error."""
    errors = []

    def body(fn):
        try:
            fn()
        except BaseException as exc:  # noqa: BLE001
            errors.append(exc)

    threads = [threading.Thread(target=body, args=(fn,)) for fn in fns]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    if errors:
        raise errors[0]


def step_run(cls, worlds, devices, frames, frame_dt, steps):
    """(seconds of ``frames`` frames of every block, build seconds, blocks, final x, final v)."""
    base = cls(cls.resolve_params(worlds[0]), device="cpu")
    per_world = estimate_sweep_bytes(base.model.particle_count, base.model.spring_count, 1)["device"]
    blocks = split_blocks(len(worlds), [device_capacity(d, per_world) for d in devices])
    batches = [None] * len(blocks)
    runs = [None] * len(blocks)

    def build(k):
        first, count = blocks[k]
        device = wp.get_device(devices[k])
        batch = WorldBatch(cls, worlds[first:first + count], device=device, reference_params=worlds)
        run = frame_of(batch, frame_dt, steps)
        run()  # loads every module on this device
        if device.is_cuda:
            with wp.ScopedCapture(device=device) as capture:
                run()
            graph = capture.graph
            run = lambda: wp.capture_launch(graph)  # noqa: E731
        wp.synchronize_device(device)
        batches[k], runs[k] = batch, run

    t0 = time.perf_counter()
    in_threads([lambda k=k: build(k) for k in range(len(blocks))])
    built = time.perf_counter() - t0
    go = threading.Barrier(len(blocks) + 1)

    def replay(k):
        go.wait()
        for _ in range(frames):
            runs[k]()
        wp.synchronize_device(devices[k])

    threads = [threading.Thread(target=replay, args=(k,)) for k in range(len(blocks))]
    for t in threads:
        t.start()
    go.wait()
    t0 = time.perf_counter()
    for t in threads:
        t.join()
    seconds = time.perf_counter() - t0
    x = np.concatenate([b.sim.state.positions.numpy() for b in batches])
    v = np.concatenate([b.sim.state.velocities.numpy() for b in batches])
    bad = sum(int(b.world_bad.numpy().sum()) for b in batches)
    del batches, runs
    return seconds, built, blocks, x, v, bad


def sweep_run(devices, worlds, frames, folder, store="all"):
    """(wall seconds, exit code) of ``warpsim sweep teapot`` on ``devices`` (one: --device),
    ``--store store``."""
    from warpsim.cli import main

    flag = ["--device", devices[0]] if len(devices) == 1 else ["--devices", ",".join(devices)]
    argv = ["sweep", "teapot", "--worlds", str(worlds), "--sample", "lhs", "--frames", str(frames), "--substeps", "10",
            "--out", os.path.join(folder, "s.usda"), "--no-progress", "--store", store, *flag]
    for v in VARY:
        argv += ["--vary", v]
    for k, v in FIXED.items():
        argv += ["--set", f"{k}={str(v).lower()}"]
    err = io.StringIO()
    t0 = time.perf_counter()
    code = main(argv, out=io.StringIO(), err=err)
    seconds = time.perf_counter() - t0
    if code:
        print(f"  sweep on {','.join(devices)} failed ({code}): {err.getvalue().strip()[-400:]}")
    return seconds, code


def sweep_outputs(folder):
    """(table bytes, record bytes, {world: samples bytes}) of a finished sweep folder."""
    import glob

    from pxr import Usd

    def read(name):
        with open(os.path.join(folder, name), "rb") as f:
            return f.read()

    samples = {}
    for layer in sorted(glob.glob(os.path.join(folder, "s.batch_[0-9][0-9][0-9][0-9].usdc"))):
        stage = Usd.Stage.Open(layer)
        for world in stage.GetPrimAtPath("/Worlds").GetChildren():
            chunks = []
            for prim in Usd.PrimRange(world):
                for attr in prim.GetAttributes():
                    for t in attr.GetTimeSamples():
                        chunks.append(np.asarray(attr.Get(t)).tobytes())
            samples[world.GetName()] = b"".join(chunks)
    return read("s.csv"), read("s.occupancy.npz"), samples


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=DefaultsHelpFormatter)
    p.add_argument("--worlds", type=int, default=100_000)
    p.add_argument("--devices", nargs="+", default=["cuda:0", "all"],
                   help="device sets (each as --devices takes it); the first is the reference")
    p.add_argument("--frames", type=int, default=10, help="frames timed")
    p.add_argument("--sweep-worlds", type=int, default=0, help="worlds of the whole-sweep comparison (0: skip)")
    p.add_argument("--sweep-frames", type=int, default=6)
    p.add_argument("--sweep-store", nargs="+", default=["all"], choices=["all", "preview", "none"],
                   help="--store of the whole-sweep comparisons (each a run on every device set)")
    p.add_argument("--sweep-devices", nargs="+", default=None,
                   help="device sets of the whole-sweep comparison (default: those of --devices); the first is "
                        "the reference")
    args = p.parse_args()
    set_warp_verbosity()  # quiet unless $WARPSIM_VERBOSE=1 (Warp 1.19 ignores config.quiet)
    import warnings

    warnings.filterwarnings("ignore", message=".*above the stability limit")
    cls = get_scene("teapot")
    sets = [parse_devices(s) for s in args.devices]
    used = list(dict.fromkeys(d for s in sets for d in s))
    print(f"devices: {', '.join(f'{d} ({wp.get_device(d).name})' for d in used)}; Warp {wp.__version__}")
    worlds = sample_worlds("teapot", FIXED, VARY, args.worlds, sample="lhs", seed=0)
    steps, frame_dt = cls.substeps, cls.substeps * cls.params["dt"].default
    print(f"{args.worlds} teapot worlds, {steps} steps a frame (the scene's own count, fixed), {args.frames} frames "
          "timed")
    ref = None
    for devices in sets:
        seconds, built, blocks, x, v, bad = step_run(cls, worlds, devices, args.frames, frame_dt, steps)
        rate = args.frames * steps / seconds
        line = (f"{','.join(devices)}: blocks {[c for _, c in blocks]}; build {built:.1f} s; {seconds:.3f} s for "
                f"{args.frames} frames = {rate:.1f} steps/s ({rate * args.worlds:.3g} world-steps/s); blown up {bad}")
        if ref is None:
            ref = (seconds, x, v)
        else:
            n = len(devices)
            same = x.tobytes() == ref[1].tobytes() and v.tobytes() == ref[2].tobytes()
            line += (f"; speed-up {ref[0] / seconds:.2f}x, efficiency t1/(N tN) = {100 * ref[0] / (n * seconds):.1f} %"
                     f"; final state {'bit-identical' if same else 'DIFFERS'} to {','.join(sets[0])}"
                     f"{'' if same else f' (max |dx| {np.abs(x - ref[1]).max():.3g} m)'}")
        print(line, flush=True)
    for store in args.sweep_store if args.sweep_worlds else ():
        with tempfile.TemporaryDirectory() as tmp:
            outs = None
            for devices in [parse_devices(s) for s in args.sweep_devices] if args.sweep_devices else sets:
                folder = os.path.join(tmp, "_".join(d.replace(":", "") for d in devices))
                seconds, code = sweep_run(devices, args.sweep_worlds, args.sweep_frames, folder, store)
                if code:
                    continue
                t0 = time.perf_counter()
                got = sweep_outputs(folder)
                line = (f"sweep {args.sweep_worlds} worlds x {args.sweep_frames} frames, --store {store}, on "
                        f"{','.join(devices)}: {seconds:.1f} s")
                if outs is None:
                    outs = (seconds, got)
                else:
                    table, record, samples = got
                    same = [table == outs[1][0], record == outs[1][1], samples == outs[1][2]]
                    line += (f" ({outs[0] / seconds:.2f}x of one device); table {'identical' if same[0] else 'DIFFERS'}"
                             f", occupancy record {'identical' if same[1] else 'DIFFERS'}, samples of "
                             f"{len(samples)} worlds {'identical' if same[2] else 'DIFFER'} byte for byte"
                             f" (read back in {time.perf_counter() - t0:.1f} s)")
                print(line, flush=True)


if __name__ == "__main__":
    sys.exit(run_script(main))
