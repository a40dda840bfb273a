"""Many teapot worlds in one batched run against the same worlds run one after another.

Measured in one process, on one device:
  build     ``WorldBatch`` of N teapots (world 0 built by the scene, the rest tiled on the device)
            against N ``add_soft_body`` calls into one ModelBuilder + finalize (timed for
            ``--builder-worlds`` teapots and scaled to N: the builder's cost is linear in N);
  step      one batched step of all N worlds (a frame of ``substeps`` steps captured as a CUDA graph
            on GPUs; eager on the CPU) against N single-world runs stepped one after another (each
            world its own scene and simulator, its frame also captured on GPUs); ``--sequential K``
            worlds are run and the time scaled to N; also the batch through the fused step
            (``WorldBatch(fused=True)``: the cloth solver's particle-centric semi-implicit kernel,
            gather mode on GPUs, frames captured by its ClothSimulator);
  bytes     bytes per batched step from the array arguments of every launch (each array counted
            once per launch: the compulsory traffic, a lower bound) plus the simulator's position
            copy, and the fraction of the card's copy bandwidth (a ``wp.copy`` of a large array,
            read + write, measured here) that the batched step reaches;
  memory    device bytes of the batch's arrays per world (how many worlds fit).

    python benchmarks/bench_worlds.py --device cuda:0 --worlds 1024
    python benchmarks/bench_worlds.py --device cuda:0 --worlds 10000
    python benchmarks/bench_worlds.py --device cpu --worlds 32 --sequential 4 --frames 2   # check
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
from warpsim.scenes import get_scene
from warpsim.worlds import WorldBatch, sample_worlds
from warpsim.worlds.sweep import frame_timing

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


def measure_fused(batch, frames, frame_dt, substeps, device):
    """(seconds per step, bytes per step, mode) of a ``fused=True`` batch."""
    run = frame_runner(lambda: batch.advance(frame_dt, substeps), device, False)  # it captures its own graphs
    seconds = timed(lambda: [run() for _ in range(frames)], device) / (frames * substeps)
    batch.sim.use_graph = False  # an eager frame, so that every launch is seen
    with LaunchRecorder() as rec:
        batch.advance(frame_dt, substeps)
        wp.synchronize_device(device)
    return seconds, sum(rec.bytes.values()) / substeps, batch.sim.integrator.mode


def array_bytes(obj):
    return sum(v.size * wp.types.type_size_in_bytes(v.dtype) for v in vars(obj).values() if isinstance(v, wp.array))


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", default=None)
    p.add_argument("--worlds", type=int, default=1024)
    p.add_argument("--sequential", type=int, default=16, help="single-world runs actually timed (scaled to N)")
    p.add_argument("--builder-worlds", type=int, default=8, help="teapots built through add_soft_body (scaled)")
    p.add_argument("--frames", type=int, default=10, help="frames timed")
    p.add_argument("--resolution", default="low")
    p.add_argument("--no-fused", action="store_true", help="skip the fused-step batch (its host-side adjacency "
                                                             "build takes a while beyond ~1,000 worlds)")
    p.add_argument("--bandwidth-bytes", type=int, default=None, help="bytes of the bandwidth copy (default 1 GiB "
                                                                     "on GPUs, 256 MiB on the CPU)")
    args = p.parse_args()
    wp.config.quiet = True
    device = wp.get_device(args.device)
    cuda = device.is_cuda
    n = args.worlds
    cls = get_scene("teapot")
    fixed = {"resolution": args.resolution, "springs": False}
    worlds = sample_worlds("teapot", fixed, VARY, n, sample="lhs", seed=0)

    bandwidth = copy_bandwidth(device, args.bandwidth_bytes or ((1 << 30) if cuda else (256 << 20)))

    # ---------------------------------------------------------------- build
    get_scene("teapot")(cls.resolve_params(worlds[0]), device=device)  # warm: kernels, teapot cache
    t0 = time.perf_counter()
    batch = WorldBatch(cls, worlds, device=device)
    wp.synchronize_device(device)
    build_batch = time.perf_counter() - t0
    k = max(1, min(args.builder_worlds, n))
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
    build_builder = (time.perf_counter() - t0) * n / k

    P, S = batch.model.world_particle_count, batch.model.world_spring_count
    _, substeps, frame_dt = frame_timing(cls, batch.params[0])
    print(f"device {device}: {n} teapot worlds x {P} particles, {S} springs = {n * P} particles; "
          f"{substeps} steps per frame; copy bandwidth {bandwidth / 1e9:.1f} GB/s")
    print(f"build: batch {build_batch:.3f} s, builder {build_builder:.2f} s "
          f"({'measured' if k == n else f'{k} teapots scaled to {n}'}); ratio {build_builder / build_batch:.1f}x")

    # ---------------------------------------------------------------- batched step
    use_graph = cuda and batch.can_capture()
    run = frame_runner(lambda: batch.advance(frame_dt, substeps), device, use_graph)
    batched = timed(lambda: [run() for _ in range(args.frames)], device) / (args.frames * substeps)
    x = batch.sim.state.positions.numpy()
    bad = int(batch.world_bad.numpy().sum())

    # bytes per step: every launch's arrays once, plus the simulator's q_prev copy (read + write)
    with LaunchRecorder() as rec:
        batch.advance(frame_dt, substeps)
        wp.synchronize_device(device)
    copies = 2 * batch.sim.state.positions.size * 12 * substeps
    step_bytes = (sum(rec.bytes.values()) + copies) / substeps
    fraction = step_bytes / batched / bandwidth

    # ---------------------------------------------------------------- batched, fused step
    # the same worlds through the cloth solver's fused semi-implicit step (gather on GPUs)
    fused_batch = None if args.no_fused else WorldBatch(cls, worlds, device=device, fused=True)
    if fused_batch is not None:
        fused, fused_bytes, mode = measure_fused(fused_batch, args.frames, frame_dt, substeps, device)

    # ---------------------------------------------------------------- sequential
    ks = max(1, min(args.sequential, n))
    total = 0.0
    for w in range(ks):
        scene = cls(cls.resolve_params(worlds[w]), device=device)
        scene.sim.check_every = 0  # the batch checks once per frame on the device; so does this run
        one = frame_runner(lambda s=scene: s.advance(frame_dt, substeps), device, cuda)
        total += timed(lambda one=one: [one() for _ in range(args.frames)], device)
    sequential = total / ks / (args.frames * substeps) * n
    per_world = array_bytes(batch.model) + 4 * 12 * n * P  # model arrays + state, q_prev, forces, q_good
    print(f"step: batched {batched * 1e3:.4f} ms for {n} worlds; sequential {sequential * 1e3:.4f} ms "
          f"({ks} worlds timed, {sequential / n * 1e3:.4f} ms each, scaled to {n}); ratio {sequential / batched:.1f}x")
    print(f"bytes per batched step {step_bytes / 1e6:.2f} MB ({step_bytes / (n * P):.0f} B per particle): "
          f"{step_bytes / batched / 1e9:.1f} GB/s = {100 * fraction:.1f} % of the copy bandwidth")
    if fused_batch is not None:
        print(f"fused ({mode}): batched {fused * 1e3:.4f} ms per step, ratio {sequential / fused:.1f}x to sequential; "
              f"{fused_bytes / 1e6:.2f} MB per step = {100 * fused_bytes / fused / bandwidth:.1f} % of the copy "
              "bandwidth")
    print(f"memory: {per_world / n / 1e3:.1f} kB per world on the device (model + state arrays); "
          f"worlds blown up: {bad}; finite: {bool(np.isfinite(x).all())}")
    top = sorted(rec.bytes.items(), key=lambda kv: -kv[1])
    print("launch bytes per step: " + ", ".join(f"{key} {v / substeps / 1e6:.2f} MB" for key, v in top))
    if cuda:
        used = wp.get_mempool_used_mem_current(device)
        print(f"device memory in use {used / 1e9:.2f} GB of {device.total_memory / 1e9:.1f} GB")


if __name__ == "__main__":
    main()
