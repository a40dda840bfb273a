"""Roofline of warpsim's GPU workloads: per kernel, the bytes it moves per step, the GPU time it
takes and the fraction of the card's memory bandwidth that reaches, in one run.

Bandwidth: the card's copy bandwidth is measured first in the same process (``wp.copy`` of a
1 GiB float array: read + write bytes / time).

Bytes per launch (the model): the sum of ``nbytes`` of every array the launch is given (arrays
inside struct arguments included), each counted once. That is the compulsory DRAM traffic when
every element is read or written once; kernels that gather neighbours re-read their neighbours'
data, which L2 mostly serves, so the model is a lower bound on traffic and the printed fraction
a lower bound on the bandwidth reached (a kernel far below the roofline by this count is bound by
latency, atomics or arithmetic, not by DRAM). Work that is not a ``wp.launch`` (the hash grid's
radix sort, memsets, copies) is timed and listed with its bytes unknown.

Workloads (``--only`` picks some): ``sph`` (position-based dam break, ``--particles``), ``boids``
(``--agents``, periodic box at ~20 neighbours per perception sphere), ``smoke`` (``--grid``^3 smoke
step with the multigrid-preconditioned CG), ``cloth`` (``ws.Simulator`` semi-implicit on a
``--cloth``^2 grid cloth).

    python benchmarks/roofline.py --device cuda:0
    python benchmarks/roofline.py --device cpu --particles 8000 --agents 4000 --grid 16 --cloth 16   # smoke test
"""

import argparse
import collections
import sys
import time

import numpy as np
import warp as wp
from timing import activity_name

import warpsim as ws
from warpsim.cli_common import DefaultsHelpFormatter, device_arg, run_script
from warpsim.verbosity import set_warp_verbosity


def copy_bandwidth(device, nbytes=1 << 30, repeats=10):
    """Device copy bandwidth [bytes/s]: read + write of a ``nbytes`` float array."""
    n = nbytes // 4
    a = wp.zeros(n, dtype=float, device=device)
    b = wp.empty(n, dtype=float, device=device)
    wp.copy(b, a)
    wp.synchronize_device(device)
    t0 = time.perf_counter()
    for _ in range(repeats):
        wp.copy(b, a)
    wp.synchronize_device(device)
    return 2.0 * n * 4 * repeats / (time.perf_counter() - t0)


def _arg_bytes(value):
    if isinstance(value, wp.array):
        return value.size * wp.types.type_size_in_bytes(value.dtype)
    cls = getattr(value, "_cls", None)
    if cls is not None and hasattr(cls, "vars"):
        return sum(_arg_bytes(getattr(value, name)) for name in cls.vars)
    return 0


class LaunchRecorder:
    """Wraps ``wp.launch`` while active: launches and array bytes per kernel key."""

    def __init__(self):
        self.calls = collections.Counter()
        self.bytes = collections.Counter()

    def __enter__(self):
        self._launch = wp.launch
        recorder = self

        def launch(kernel, dim=None, inputs=(), outputs=(), *args, **kwargs):
            key = kernel.key
            recorder.calls[key] += 1
            recorder.bytes[key] += sum(_arg_bytes(v) for v in list(inputs) + list(outputs))
            return recorder._launch(kernel, dim, inputs, outputs, *args, **kwargs)

        wp.launch = launch
        return self

    def __exit__(self, *exc):
        wp.launch = self._launch


def gpu_by_kernel(results) -> collections.Counter:
    """Milliseconds of GPU activity per kernel name of ``wp.timing_end`` results, by the kernel's exact Python name
    (``timing.activity_name``: the key ``wp.launch`` saw, so ``integrate`` and ``integrate_particles`` stay apart)."""
    gpu: collections.Counter = collections.Counter()
    for r in results:
        gpu[activity_name(r)] += r.elapsed
    return gpu


def profile(run, device, steps):
    """Run ``run()`` once under the launch recorder and Warp's CUDA activity timing; returns rows
    (name, calls, gpu_ms, bytes or None) per step and the wall time per step [s]."""
    wp.synchronize_device(device)
    t0 = time.perf_counter()
    run()
    wp.synchronize_device(device)
    wall = time.perf_counter() - t0
    timed = device.is_cuda
    if timed:
        wp.timing_begin(cuda_filter=wp.TIMING_ALL)
    with LaunchRecorder() as rec:
        run()
    results = wp.timing_end() if timed else []
    gpu = gpu_by_kernel(results)
    rows = []
    for key in sorted(set(rec.calls) | set(gpu), key=lambda k: -gpu.get(k, 0.0)):
        rows.append((key, rec.calls.get(key, 0) / steps, gpu.get(key, 0.0) / steps,
                     rec.bytes[key] / steps if key in rec.calls else None))
    return rows, wall / steps


def report(title, rows, wall_step, bandwidth, unit_count, unit):
    total_ms = sum(r[2] for r in rows)
    total_bytes = sum(r[3] for r in rows if r[3])
    print(f"\n## {title}")
    print(f"wall {wall_step * 1e3:.3f} ms/step ({unit_count / wall_step / 1e6:.1f} M {unit}-steps/s); "
          f"GPU kernels {total_ms:.3f} ms/step; modelled bytes {total_bytes / 1e6:.1f} MB/step -> "
          f"{total_bytes / max(wall_step, 1e-12) / 1e9:.0f} GB/s = "
          f"{100 * total_bytes / max(wall_step, 1e-12) / bandwidth:.1f} % of copy bandwidth over the wall step")
    print(f"{'kernel':48s} {'calls':>6s} {'ms/step':>8s} {'MB/step':>9s} {'GB/s':>7s} {'% bw':>6s}")
    for name, calls, ms, nbytes in rows[:14]:
        if nbytes is None or ms <= 0.0:
            tail = f"{'-' if nbytes is None else f'{nbytes / 1e6:9.2f}':>9s} {'-':>7s} {'-':>6s}"
        else:
            rate = nbytes / (ms * 1e-3)
            tail = f"{nbytes / 1e6:9.2f} {rate / 1e9:7.0f} {100 * rate / bandwidth:6.1f}"
        print(f"{name[:48]:48s} {calls:6.1f} {ms:8.3f} {tail}")


def sph_workload(n, device):
    from bench_sph import block_for

    spacing = 0.01
    pos, box = block_for(n, spacing)
    fluid = ws.ParticleFluid(pos, spacing=spacing, domain=((0.0, 0.0, 0.0), box), device=device)
    for _ in range(3):
        fluid.advance(1.0 / 60.0)
    steps0 = fluid.step_count
    fluid.advance(1.0 / 60.0)
    steps = max(fluid.step_count - steps0, 1)
    return (lambda: fluid.advance(1.0 / 60.0)), steps, fluid.active_count, "particle"


def boids_workload(n, device, cell_factor=1.0):
    from bench_boids import PARAMS, make_flock_state

    x, v, L = make_flock_state(n, 20.0, 0)
    flock = ws.Flock(x, v, params=PARAMS, bounds=((0, 0, 0), (L, L, L)), wrap=True, device=device)
    flock.cell_size *= cell_factor  # hash-grid cell edge as a multiple of the query radius (experiment)
    flock.step(1.0 / 60.0)
    return (lambda: flock.step(1.0 / 60.0)), 1, n, "agent"


def smoke_workload(n, device, graph=False):
    from bench_grid_step import smoke_3d

    s = smoke_3d(n, device, graph=graph)
    s.step(0.5 / n)
    s.step(0.5 / n)  # with graph=True the second step records the graph
    if graph:  # the replayed step against the same step launched eagerly, from the same state
        eager = smoke_3d(n, device, graph=False)
        eager.pressure = type(eager.pressure)(eager.grid, tol=s.pressure.tol, preconditioner=s.pressure.preconditioner,
                                              check_every=0)
        for _ in range(3):
            eager.step(0.5 / n)
        s.step(0.5 / n)
        diff = np.abs(eager.density.numpy() - s.density.numpy()).max()
        print(f"smoke graph replay vs eager after 3 steps: max |density difference| {diff:.3g}")
    return (lambda: s.step(0.5 / n)), 1, n ** 3, "cell"


def cloth_workload(n, device):
    b = ws.ModelBuilder()
    ws.add_cloth_grid(b, (n - 1, n - 1), (1.0, 1.0), (0.0, 1.0, 0.0), pin=["corner_00", "corner_10"])
    sim = ws.Simulator(b.finalize(device), forces=[ws.Gravity()], colliders=[ws.Plane()])
    dt = 2.0e-5  # below the stiffest spring's explicit limit at 1/256 m spacing
    sim.step(dt)
    return (lambda: sim.step(dt)), 1, n * n, "particle"


WORKLOADS = {"sph": (sph_workload, "particles"), "boids": (boids_workload, "agents"),
             "smoke": (smoke_workload, "grid"), "cloth": (cloth_workload, "cloth")}


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=DefaultsHelpFormatter)
    p.add_argument("--device", default=None)
    p.add_argument("--particles", type=int, default=1_000_000)
    p.add_argument("--agents", type=int, default=1_000_000)
    p.add_argument("--grid", type=int, default=128)
    p.add_argument("--cloth", type=int, default=256)
    p.add_argument("--boids-cell-factor", type=float, default=1.0,
                   help="boids: hash-grid cell edge / query radius (1: the library's choice)")
    p.add_argument("--smoke-graph", action="store_true",
                   help="smoke: Smoke(graph=True), the step replayed as a CUDA graph (CG checks on the device)")
    p.add_argument("--only", nargs="+", choices=sorted(WORKLOADS), default=sorted(WORKLOADS))
    args = p.parse_args()
    set_warp_verbosity()  # quiet unless $WARPSIM_VERBOSE=1 (Warp 1.19 ignores config.quiet)
    device = wp.get_device(device_arg(args.device))
    bandwidth = copy_bandwidth(device, nbytes=(1 << 30) if device.is_cuda else (1 << 26), repeats=10 if device.is_cuda else 3)
    print(f"device {device} ({device.name}); copy bandwidth {bandwidth / 1e9:.0f} GB/s (read + write)")
    if not device.is_cuda:
        print("(no CUDA: per-kernel GPU times are not available; wall times and byte counts only)")
    for name in args.only:
        make, size_arg = WORKLOADS[name]
        extra = {"smoke": {"graph": args.smoke_graph}, "boids": {"cell_factor": args.boids_cell_factor}}.get(name, {})
        run, steps, count, unit = make(getattr(args, size_arg), device, **extra)
        rows, wall = profile(run, device, steps)
        report(f"{name} ({count:,} {unit}s)", rows, wall, bandwidth, count, unit)


if __name__ == "__main__":
    sys.exit(run_script(main))
