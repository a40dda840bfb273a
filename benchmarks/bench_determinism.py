"""Cost of the bit-reproducible stages against the float-atomic ones they replace, in one process:

* FLIP particle-to-grid: the cell sort + gathers (``FlipLiquid(deterministic=True)``, default)
  against the atomic scatter (``deterministic=False``), the transfer alone and a whole step;
* FLIP particle density: the gather against the atomic scatter;
* the pressure solver's domain sums on an n^3 grid: the fixed-order slots + folding against the
  former 256-slot float atomics (kept below as the reference).

    python benchmarks/bench_determinism.py --device cuda:0 --resolution 64
    python benchmarks/bench_determinism.py --device cpu --resolution 20

Prints medians [ms] and ratios (deterministic / atomic); nothing is asserted.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from warpsim.kernels import flip as KF  # noqa: E402
from warpsim.kernels import grid as KG  # noqa: E402
from warpsim.kernels.grid import AIR, FLUID, axis_step, label_at  # noqa: E402

from warpsim.cli_common import DefaultsHelpFormatter, device_arg, run_script
from warpsim.core.reduction import FixedOrderReduction  # noqa: E402
from warpsim.grid_fluids.flip import FlipLiquid  # noqa: E402
from warpsim.grid_fluids.mac_grid import MacGrid  # noqa: E402


@wp.kernel
def former_fluid_sums(labels: wp.array3d(dtype=int), open_mask: int, rhs: wp.array(dtype=float),
                      partial_out: wp.array2d(dtype=float)):
    """The former float-atomic version of kernels/grid.py's fluid_sums (reference for timing only)."""
    i, j, k = wp.tid()
    if labels[i, j, k] != FLUID:
        return
    c = wp.vec3i(i, j, k)
    air = float(0.0)
    for a in range(3):
        for s in range(2):
            if label_at(labels, open_mask, c + axis_step(a) * (2 * s - 1)) == AIR:
                air += 1.0
    flat = (i * labels.shape[1] + j) * labels.shape[2] + k
    slot = flat % partial_out.shape[0]
    wp.atomic_add(partial_out, slot, 0, rhs[flat])
    wp.atomic_add(partial_out, slot, 1, 1.0)
    if air > 0.0:
        wp.atomic_add(partial_out, slot, 2, air)


def median_ms(fn, device, repeats):
    fn()  # warm-up (module loads)
    wp.synchronize_device(device)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        wp.synchronize_device(device)
        times.append(1e3 * (time.perf_counter() - start))
    return statistics.median(times)


def make_flip(resolution, deterministic, device):
    n = resolution
    g = MacGrid((n, (4 * n) // 5, n // 2), 1.0 / n, device=device)
    f = FlipLiquid(g, deterministic=deterministic, reseed_every=1)
    f.add_box((0.0, 0.0, 0.0), (1.0, 0.2, 0.5))
    f.add_box((0.35, 0.45, 0.1), (0.65, 0.7, 0.4))
    for _ in range(3):  # a splash under way: particles no longer on the seeding lattice
        f.step(1.0 / 60)
    return f


def report(name, ms_det, ms_atomic):
    print(f"{name:42s} {ms_det:9.3f} ms  vs atomics {ms_atomic:9.3f} ms   ratio {ms_det / ms_atomic:5.2f}")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=DefaultsHelpFormatter)
    parser.add_argument("--device", default=None, help="Warp device (default: Warp's preferred)")
    parser.add_argument("--resolution", type=int, default=48, help="FLIP cells along x (default 48)")
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--sum-grid", type=int, default=None,
                        help="cells per side of the domain-sum grid (default 128 on GPUs, 32 on the CPU)")
    args = parser.parse_args(argv)
    device = wp.get_device(device_arg(args.device))
    det, atomic = make_flip(args.resolution, True, device), make_flip(args.resolution, False, device)
    print(f"device {device}, FLIP grid {det.grid.shape}, {det.particle_count()} particles (deterministic run), "
          f"{atomic.particle_count()} (atomic run)")
    g, P = det.grid, det.particles

    def gather_p2g():
        P.count_cells(g, det.cell_count)
        for axis, f in enumerate(g.faces):
            wp.launch(KF.gather_face_velocity, f.shape, inputs=[det.cell_count, P.octant_start, P.octant_count,
                                                                P.sorted_ids, P["x"], P["v"], axis, g.wp_origin,
                                                                g.dx], outputs=[f],
                      device=device)

    ga, Pa = atomic.grid, atomic.particles

    def scatter_p2g():
        Pa.count_cells(ga, atomic.cell_count)  # the former path counted cells too (with atomic ranks)
        for s, w in zip(atomic._sums, atomic._weights):
            s.zero_()
            w.zero_()
        wp.launch(KF.particles_to_grid, Pa.capacity, inputs=[Pa.count, Pa["x"], Pa["v"], Pa["alive"], ga.wp_origin,
                                                             ga.dx],
                  outputs=[atomic._sums[0], atomic._weights[0], atomic._sums[1], atomic._weights[1], atomic._sums[2],
                           atomic._weights[2]], device=device)
        for f, s, w in zip(ga.faces, atomic._sums, atomic._weights):
            wp.launch(KF.normalize_faces, f.shape, inputs=[s, w], outputs=[f], device=device)

    report("FLIP P2G (sort + gathers)", median_ms(gather_p2g, device, args.repeats),
           median_ms(scatter_p2g, device, args.repeats))
    report("FLIP particle density (gather)", median_ms(det._splat_density, device, args.repeats),
           median_ms(atomic._splat_density, device, args.repeats))
    report("FLIP whole step (1/60 s)", median_ms(lambda: det.step(1.0 / 60), device, max(3, args.repeats // 4)),
           median_ms(lambda: atomic.step(1.0 / 60), device, max(3, args.repeats // 4)))

    n = args.sum_grid or (128 if device.is_cuda else 32)
    labels = wp.full((n, n, n), FLUID, dtype=int, device=device)
    rhs = wp.array(np.random.default_rng(0).normal(size=n ** 3).astype(np.float32), dtype=float, device=device)
    red = FixedOrderReduction(3, device=device)
    slots = wp.zeros((256, 3), dtype=float, device=device)
    open_top = 1 << 3  # +y open: FLUID cells below it touch AIR

    def fixed_sums():
        wp.launch(KG.fluid_sums, red.slots, inputs=[labels, open_top, rhs], outputs=[red.partials], device=device)
        red.finish()

    def former_sums():
        slots.zero_()
        wp.launch(former_fluid_sums, labels.shape, inputs=[labels, open_top, rhs], outputs=[slots], device=device)

    report(f"pressure domain sums {n}^3 (fixed order)", median_ms(fixed_sums, device, args.repeats),
           median_ms(former_sums, device, args.repeats))


if __name__ == "__main__":
    sys.exit(run_script(main))
