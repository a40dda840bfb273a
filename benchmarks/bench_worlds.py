"""Many teapot worlds in one batched run against the same worlds run one after another.

Measured in one process, on one device:
  build     ``WorldBatch`` of N teapots (world 0 built by the scene, the rest tiled on the device)
            against N ``add_soft_body`` calls into one ModelBuilder + finalize (timed for
            ``--builder-worlds`` teapots and scaled to N: the builder's cost is linear in N);
  step      one batched step of all N worlds (a frame of the scene's ``substeps`` steps, automatic
            sub-stepping off, captured as a CUDA graph
            on GPUs; eager on the CPU) against N single-world runs stepped one after another (each
            world its own scene and simulator, its frame also captured on GPUs); ``--sequential K``
            worlds are run and the time scaled to N. Paths (``--paths``): ``shared`` (the default
            of WorldBatch: topology stored once, one fused kernel per sub-step), ``block``
            (``block_per_world=True``: the shared path with a whole frame in one launch, a thread
            block per world), ``tiled``
            (``shared=False``: every array per world, one launch per stage) and ``fused``
            (``fused=True``: the cloth solver's particle-centric kernel);
  equal     whether the shared, block and tiled paths end in the same bits (they should: same
            arithmetic);
  bytes     bytes per batched step from the array arguments of every launch (each array counted
            once per launch: the compulsory traffic, a lower bound), the fraction of the H100's
            3.35 TB/s and of the card's copy bandwidth measured here (``wp.copy``, read + write);
  memory    device bytes per world (the memory pool's growth while building the batch on CUDA,
            the arrays' sizes on the CPU) and how many worlds would fit.

    python benchmarks/bench_worlds.py --device cuda:0 --worlds 1024
    python benchmarks/bench_worlds.py --device cuda:0 --worlds 10000 --paths shared,tiled --sequential 4
    python benchmarks/bench_worlds.py --device cuda:0 --worlds 100000 --paths shared --sequential 4
    python benchmarks/bench_worlds.py --device cpu --worlds 8 --sequential 2 --frames 2   # check
"""

import argparse
import os
import sys
import time

import numpy as np
import warp as wp

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from roofline import LaunchRecorder, copy_bandwidth

import warpsim as ws
from warpsim.bodies.softbody import add_soft_body
from warpsim.bodies.teapot import teapot_mesh
from warpsim.cli_common import DefaultsHelpFormatter, device_arg, run_script
from warpsim.scenes import get_scene
from warpsim.scenes.timing import resolve_timing
from warpsim.verbosity import set_warp_verbosity
from warpsim.sweeps import sample_worlds
from warpsim.worlds import WorldBatch
from warpsim.sweeps.sweep import frame_timing

VARY = ["stiffness=20:60", "height=0.4:0.6", "restitution=0.2:0.8", "friction=0.1:0.5"]


def timed(fn, device):
    wp.synchronize_device(device)
    t0 = time.perf_counter()
    fn()
    wp.synchronize_device(device)
    return time.perf_counter() - t0


def frame_runner(advance, device, use_graph):
    """A callable running one frame: a replayed CUDA graph of ``advance`` on GPUs."""
    advance()  # loads every module
    if not use_graph:
        return advance
    with wp.ScopedCapture(device=device) as capture:
        advance()
    return lambda: wp.capture_launch(capture.graph)


H100_BANDWIDTH = 3.35e12  # [bytes/s], the H100 SXM's HBM3 specification


def measure(batch, frames, frame_dt, substeps, device):
    """(seconds per step, bytes per step) of a batch: frames replayed as CUDA graphs where the batch
    allows it (a fused batch captures its own), then one eager frame under the launch recorder."""
    use_graph = device.is_cuda and batch.can_capture()
    run = frame_runner(lambda: batch.advance(frame_dt, substeps), device, use_graph)
    seconds = timed(lambda: [run() for _ in range(frames)], device) / (frames * substeps)
    if hasattr(batch.sim, "use_graph"):
        batch.sim.use_graph = False  # an eager frame, so that every launch is seen
    with LaunchRecorder() as rec, wp.Tape():  # a tape: cached (replayed) launches go through wp.launch
        batch.advance(frame_dt, substeps)
        wp.synchronize_device(device)
    copies = 0 if batch.shared or batch.fused else 2 * batch.sim.state.positions.size * 12 * substeps  # q_prev
    return seconds, (sum(rec.bytes.values()) + copies) / substeps, rec


def array_bytes(obj):
    return sum(v.size * wp.types.type_size_in_bytes(v.dtype) for v in vars(obj).values() if isinstance(v, wp.array))


def build(cls, worlds, device, **kwargs):
    """(batch, seconds, device bytes it holds)."""
    used = wp.get_mempool_used_mem_current(device) if device.is_cuda else 0
    t0 = time.perf_counter()
    batch = WorldBatch(cls, worlds, device=device, **kwargs)
    batch.use_timing(resolve_timing(cls, batch.params[0], substeps=cls.substeps))  # fixed sub-steps, as sequential
    wp.synchronize_device(device)
    seconds = time.perf_counter() - t0
    if device.is_cuda:
        held = wp.get_mempool_used_mem_current(device) - used
    else:
        st = batch.sim.state
        held = array_bytes(batch.model) + 3 * st.positions.size * 12 * 2  # model + state, q_prev, q_good, forces...
        held += batch.stepper.device_bytes() if batch.stepper is not None else 0
    return batch, seconds, held


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=DefaultsHelpFormatter)
    p.add_argument("--device", default=None)
    p.add_argument("--worlds", type=int, default=1024)
    p.add_argument("--sequential", type=int, default=16, help="single-world runs actually timed (scaled to N)")
    p.add_argument("--builder-worlds", type=int, default=8, help="teapots built through add_soft_body (scaled; "
                                                                   "0: skip)")
    p.add_argument("--frames", type=int, default=10, help="frames timed")
    p.add_argument("--resolution", default="low")
    p.add_argument("--paths", default="shared,block,tiled,fused",
                   help="batch paths to measure: shared, block (shared, a frame per launch), tiled, fused")
    p.add_argument("--no-fused", action="store_true", help="(as --paths without fused)")
    p.add_argument("--bandwidth-bytes", type=int, default=None, help="bytes of the bandwidth copy (default 1 GiB "
                                                                     "on GPUs, 256 MiB on the CPU)")
    args = p.parse_args()
    set_warp_verbosity()  # quiet unless $WARPSIM_VERBOSE=1 (Warp 1.19 ignores config.quiet)
    import warnings

    # the stiffest sampled teapots sit just past dt's limit (as in the earlier figures); a world
    # that blows up is frozen and counted below
    warnings.filterwarnings("ignore", message=".*above the stability limit")
    device = wp.get_device(device_arg(args.device))
    cuda = device.is_cuda
    n = args.worlds
    paths = [x for x in args.paths.split(",") if x and not (args.no_fused and x == "fused")]
    bad_paths = [x for x in paths if x not in ("shared", "block", "tiled", "fused")]
    if bad_paths or not paths:
        p.error(f"--paths {args.paths!r}: give some of shared, block, tiled, fused")
    cls = get_scene("teapot")
    fixed = {"resolution": args.resolution, "springs": False}
    worlds = sample_worlds("teapot", fixed, VARY, n, sample="lhs", seed=0)
    bandwidth = copy_bandwidth(device, args.bandwidth_bytes or ((1 << 30) if cuda else (256 << 20)))
    scene0 = cls(cls.resolve_params(worlds[0]), device=device)  # warm: kernels, teapot cache
    P, S = scene0.model.particle_count, scene0.model.spring_count
    _, substeps, frame_dt = frame_timing(cls, cls.resolve_params(worlds[0]))
    print(f"device {device}: {n} teapot worlds x {P} particles, {S} springs = {n * P} particles; "
          f"{substeps} steps per frame; copy bandwidth {bandwidth / 1e9:.1f} GB/s (H100 spec 3,350 GB/s)")

    # ---------------------------------------------------------------- sequential reference
    ks = max(1, min(args.sequential, n))
    total = 0.0
    for w in range(ks):
        scene = cls(cls.resolve_params(worlds[w]), device=device)
        scene.use_timing(resolve_timing(cls, scene.params, substeps=cls.substeps))  # fixed: its limit is not timed
        scene.sim.check_every = 0  # the batch checks once per frame on the device; so does this run
        one = frame_runner(lambda s=scene: s.advance(frame_dt, substeps), device, cuda)
        total += timed(lambda one=one: [one() for _ in range(args.frames)], device)
    sequential = total / ks / (args.frames * substeps) * n
    print(f"sequential: {sequential * 1e3:.4f} ms per step of {n} worlds ({ks} worlds timed, "
          f"{sequential / n * 1e3:.4f} ms each{', CUDA graphs' if cuda else ''}, scaled to {n})")

    # ---------------------------------------------------------------- batched paths
    final = {}
    for path in paths:
        kwargs = {"shared": path in ("shared", "block"), "fused": path == "fused", "block_per_world": path == "block"}
        if path == "fused":
            kwargs = {"fused": True}
        batch, seconds_build, held = build(cls, worlds, device, **kwargs)
        step, step_bytes, rec = measure(batch, args.frames, frame_dt, substeps, device)
        x = batch.sim.state.positions.numpy()
        final[path] = x
        bad = int(batch.world_bad.numpy().sum())
        mode = f" ({batch.sim.integrator.mode})" if path == "fused" else ""
        print(f"{path}{mode}: build {seconds_build:.3f} s; step {step * 1e3:.4f} ms = {n / step:.3g} world-steps/s "
              f"({1.0 / step:.0f} batched steps/s); ratio {sequential / step:.1f}x to sequential")
        print(f"  bytes per step {step_bytes / 1e6:.2f} MB ({step_bytes / (n * P):.0f} B per particle): "
              f"{step_bytes / step / 1e9:.1f} GB/s = {100 * step_bytes / step / H100_BANDWIDTH:.1f} % of 3.35 TB/s, "
              f"{100 * step_bytes / step / bandwidth:.1f} % of the measured copy bandwidth")
        print(f"  memory {held / n / 1e3:.1f} kB per world ({'memory pool growth' if cuda else 'array sizes'}); "
              f"{int(0.9 * device.total_memory // max(held / n, 1)) if cuda else 'n/a'} worlds would fit in 90 % "
              f"of the device; blown up {bad}; finite {bool(np.isfinite(x).all())}")
        top = sorted(rec.bytes.items(), key=lambda kv: -kv[1])[:6]
        print("  launches per step: " + ", ".join(f"{key} x{rec.calls[key] / substeps:g} {v / substeps / 1e6:.2f} MB"
                                                for key, v in top))
        del batch
    for other in ("block", "tiled"):
        if "shared" in final and other in final:
            a, b = final["shared"], final[other]
            print(f"shared vs {other} after the same frames: "
                  f"{'bit-identical' if a.tobytes() == b.tobytes() else 'DIFFER'} (max |dx| {np.abs(a - b).max():.3g} m)")

    # ---------------------------------------------------------------- build: builder reference
    k = max(0, min(args.builder_worlds, n))
    if k:
        mesh = teapot_mesh(args.resolution, scale=0.1)
        t0 = time.perf_counter()
        b = ws.ModelBuilder()
        for w in range(k):
            q = cls.resolve_params(worlds[w])
            add_soft_body(b, mesh.points, mesh.faces, position=(0.0, q["height"], 0.0), total_mass=q["mass"],
                          mass_distribution="uniform", stiffness=q["stiffness"], damping=q["damping"],
                          lattice_cells=q["lattice_cells"])
        b.finalize(device)
        wp.synchronize_device(device)
        print(f"builder: {(time.perf_counter() - t0) * n / k:.2f} s for {n} teapots ({k} built, scaled)")
    if cuda:
        print(f"device memory in use {wp.get_mempool_used_mem_current(device) / 1e9:.2f} GB of "
              f"{device.total_memory / 1e9:.1f} GB")


if __name__ == "__main__":
    sys.exit(run_script(main))
