"""Per-world step counts in a batch (issue 41, part 4): the cost of the mask.

One teapot sweep whose worlds need different automatic counts (stiffness varied: a stiffer world
needs more steps a frame), on the shared path, measured in one process on one device:
  own       every world takes its own count (``WorldBatch.world_steps``: the count its own run
            takes); the batch launches the largest count a frame and worlds past their count idle
            (the mask, ``kernels/world_step.py``);
  max       the same sweep with every world at the largest count (the former shared count);
  ideal     the ratio own / max if an idle world cost nothing: mean count / largest count.
Both ways step the same frames of the same batch, each frame captured as a CUDA graph on GPUs
(as a sweep does; eager on the CPU), ``--path`` ``step`` (one launch per sub-step, the sweep's
default) or ``block`` (``block_per_world=True``: a whole frame in one launch, a thread block per
world, whose blocks end at their own count). Reported: seconds per frame (median of
``--repeats``), the ratio own / max against the ideal, world-steps per second.

``--check``: on the device, small sweeps whose worlds take different counts (teapot on the shared
path, teapot with a sphere obstacle on the tiled path, cloth; and a teapot height sweep, whose
worlds start at shifted positions), their frames captured as CUDA graphs
where a sweep captures them, and each world compared bit for bit with its own run (a scene built
with its parameters and stepped as ``warpsim run`` steps it).

    python benchmarks/bench_world_steps.py --device cuda:0 --worlds 10000
    python benchmarks/bench_world_steps.py --device cuda:0 --check
    python benchmarks/bench_world_steps.py --device cpu --worlds 8 --frames 2 --repeats 1   # check

``--fuse-fp``: turn floating-point contraction (FMA fusion, Warp's default) back on in the modules
of the mass-spring step (``CONTRACTION_MODULES``; the library turns it off there so that the fused
shared step and a lone Simulator round alike on GPUs): the cost of that choice, in another process.
"""

import argparse
import time

import numpy as np
import warp as wp

from warpsim.cli_common import DefaultsHelpFormatter, device_arg, run_script
from warpsim.scenes import get_scene
from warpsim.sweeps import sample_worlds
from warpsim.sweeps.sweep import sweep_timing
from warpsim.verbosity import set_warp_verbosity
from warpsim.worlds import WorldBatch


CONTRACTION_MODULES = ("world_step", "forces", "integrate", "collide")  # kernels/ modules with fuse_fp off


def contraction(on):
    """Set ``fuse_fp`` of CONTRACTION_MODULES (before their first launch) and return the setting."""
    import importlib

    for name in CONTRACTION_MODULES:
        wp.set_module_options({"fuse_fp": bool(on)}, module=importlib.import_module(f"warpsim.kernels.{name}"))
    return bool(on)


def frames_seconds(batch, frame_dt, steps, frames, repeats):
    """Median seconds of a frame of ``batch.stepper.frame(frame_dt, steps)`` + the end-of-frame
    checks, over ``repeats`` runs of ``frames`` frames (a captured graph on CUDA)."""
    d = batch.device

    def body():
        batch.stepper.frame(frame_dt, steps)
        batch.end_frame()

    body()  # loads the modules and copies the counts to the device
    graph = None
    if d.is_cuda:
        with wp.ScopedCapture(device=d) as capture:
            body()
        graph = capture.graph
    out = []
    for _ in range(repeats):
        wp.synchronize_device(d)
        t0 = time.perf_counter()
        for _ in range(frames):
            if graph is not None:
                wp.capture_launch(graph)
            else:
                body()
        wp.synchronize_device(d)
        out.append((time.perf_counter() - t0) / frames)
    return float(np.median(out))


CHECKS = {  # name: (scene, fixed parameters, varied key and values)
    "teapot (shared path)": ("teapot", {"resolution": "low"}, "stiffness", (40.0, 160.0, 640.0)),
    "teapot + sphere (tiled)": ("teapot", {"resolution": "low", "obstacle": "sphere"}, "stiffness",
                                (40.0, 160.0, 640.0)),
    "teapot height (shared path)": ("teapot", {"resolution": "low"}, "height", (0.6, 0.45, 0.8)),
    "cloth (passes)": ("cloth", {"integrator": "semi_implicit_euler", "resolution": "16", "explicit_substeps": "1"},
                       "structural", (400.0, 1600.0, 6400.0)),
}


def check(device, frames):
    """Each world of the CHECKS sweeps against its own run on ``device``: prints one line each."""
    from warpsim.scenes.timing import resolve_timing

    ok = True
    for label, (name, fixed, key, values) in CHECKS.items():
        cls = get_scene(name)
        worlds = [{**fixed, key: v} for v in values]
        timing = sweep_timing(cls, worlds)
        batch = WorldBatch(cls, worlds, device=device)
        batch.use_timing(timing)
        counts = batch.world_steps(timing.frame_dt, timing.steps)
        graph = None
        for frame in range(frames):
            if graph is not None:
                wp.capture_launch(graph)
            elif frame == 1 and device.is_cuda and batch.can_capture():  # as run_batch: frame 1 eager
                with wp.ScopedCapture(device=device) as capture:
                    batch.advance(timing.frame_dt, timing.steps)
                graph = capture.graph
                wp.capture_launch(graph)
            else:
                batch.advance(timing.frame_dt, timing.steps)
        x = batch.sim.state.positions.numpy().reshape(len(worlds), -1, 3)
        same = []
        for w, p in enumerate(worlds):
            scene = cls(p, device=device)
            t = resolve_timing(cls, scene.params, given=tuple(p))
            scene.use_timing(t)
            for _ in range(frames):
                scene.advance(t.frame_dt, t.steps)
            same.append(scene.sim.state.positions.numpy().tobytes() == x[w].tobytes())
        ok = ok and all(same)
        print(f"check {label}: counts {counts.tolist()}, graph {'yes' if graph is not None else 'no'}, "
              f"each world equals its own run bit for bit: {same}")
    return ok


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=DefaultsHelpFormatter)
    ap.add_argument("--device", type=device_arg, default=None, help="Warp device (default: Warp's preferred)")
    ap.add_argument("--worlds", type=int, default=10000, help="teapot worlds in the batch")
    ap.add_argument("--vary", default="stiffness=20:160:log", help="the varied parameter (counts follow it)")
    ap.add_argument("--frames", type=int, default=20, help="frames per timed run")
    ap.add_argument("--repeats", type=int, default=5, help="timed runs (the median is reported)")
    ap.add_argument("--path", choices=("step", "block"), default="step", help="the shared path's launch shape")
    ap.add_argument("--check", action="store_true", help="compare small sweeps' worlds with their own runs only")
    ap.add_argument("--fuse-fp", action="store_true", help="FMA contraction on in the mass-spring step's modules")
    args = ap.parse_args(argv)
    set_warp_verbosity(False)
    wp.init()
    device = wp.get_device(args.device)
    print(f"FMA contraction in {', '.join(CONTRACTION_MODULES)}: {'on' if contraction(args.fuse_fp) else 'off'}")
    if args.check:
        return 0 if check(device, max(args.frames, 3)) else 1
    cls = get_scene("teapot")
    worlds = sample_worlds("teapot", {"resolution": "low", "springs": False}, [args.vary], args.worlds,
                           sample="lhs", seed=0)
    timing = sweep_timing(cls, worlds)
    t0 = time.perf_counter()
    batch = WorldBatch(cls, worlds, device=device, block_per_world=args.path == "block")
    batch.use_timing(timing)
    counts = batch.world_steps(timing.frame_dt, timing.steps)
    built = time.perf_counter() - t0
    assert batch.stepper is not None, "the teapot sweep takes the shared path"
    x0, v0 = wp.clone(batch.sim.state.positions), wp.clone(batch.sim.state.velocities)
    own = frames_seconds(batch, timing.frame_dt, counts, args.frames, args.repeats)
    wp.copy(batch.sim.state.positions, x0)
    wp.copy(batch.sim.state.velocities, v0)
    most = frames_seconds(batch, timing.frame_dt, int(counts.max()), args.frames, args.repeats)
    ideal = float(counts.mean() / counts.max())
    P = batch.model.world_particle_count
    print(f"device {device} ({device.name if device.is_cuda else 'cpu'}), warp {wp.__version__}")
    print(f"{args.worlds} teapots ({P} particles each), {args.vary}, path {args.path}; batch built in {built:.2f} s")
    print(f"counts a frame: min {counts.min()}, mean {counts.mean():.2f}, max {counts.max()} "
          f"({len(set(counts.tolist()))} distinct)")
    for name, seconds, steps in (("own", own, counts.sum()), ("max", most, counts.max() * args.worlds)):
        print(f"{name:>4}: {seconds * 1e3:9.3f} ms a frame, {steps / seconds:.4g} world-steps/s")
    print(f"own / max = {own / most:.3f} (ideal, idle worlds free: {ideal:.3f}); "
          f"mask overhead against the ideal: {own / (most * ideal):.3f}x")


if __name__ == "__main__":
    run_script(main)
