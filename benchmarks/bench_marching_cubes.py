"""Marching cubes throughput: warpsim vs Warp's own and scikit-image, in one process.

Fields: a sphere of radius 0.7 in [-1, 1]^3 (sparse surface: most blocks are skipped) and a
gyroid (surface everywhere: nothing to skip). Reports grid nodes per second [Mvox/s] and the
ratio of warpsim's rate to each reference. scikit-image runs only on the CPU device, on a NumPy
copy of the field (its time excludes that copy).

    python benchmarks/bench_marching_cubes.py --device cpu --sizes 64 128 256
"""
import argparse
import sys
import time

import numpy as np
import warp as wp
import warp.geometry

from warpsim.cli_common import DefaultsHelpFormatter, device_arg, run_script
from warpsim.meshing.marching_cubes import MarchingCubes
from warpsim.verbosity import set_warp_verbosity


def make_field(kind, n):
    x = np.linspace(-1.0, 1.0, n, dtype=np.float32)
    X, Y, Z = np.meshgrid(x, x, x, indexing="ij", copy=False)
    if kind == "sphere":
        return np.sqrt(X * X + Y * Y + Z * Z) - np.float32(0.7), x[1] - x[0]
    w = np.float32(2.0 * np.pi)  # two gyroid periods across the box
    return (
        np.sin(w * X) * np.cos(w * Y) + np.sin(w * Y) * np.cos(w * Z) + np.sin(w * Z) * np.cos(w * X),
        x[1] - x[0],
    )


def best_time(fn, device, repeats, budget_s=3.0):
    """Fastest of `repeats` warm runs (fewer if a run is slow)."""
    fn()  # warm-up: compile, allocate
    wp.synchronize_device(device)
    best = float("inf")
    start = time.perf_counter()
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        wp.synchronize_device(device)
        best = min(best, time.perf_counter() - t0)
        if time.perf_counter() - start > budget_s:
            break
    return best


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=DefaultsHelpFormatter)
    parser.add_argument("--device", default=None, help="Warp device (default: preferred)")
    parser.add_argument("--sizes", type=int, nargs="+", default=[64, 128, 256])
    parser.add_argument("--fields", nargs="+", default=["sphere", "gyroid"], choices=["sphere", "gyroid"])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--block-size", type=int, default=None, help="warpsim block size (default per device)")
    parser.add_argument("--no-skimage", action="store_true")
    args = parser.parse_args()

    set_warp_verbosity()  # quiet unless $WARPSIM_VERBOSE=1 (Warp 1.19 ignores config.quiet)
    wp.init()
    device = wp.get_device(device_arg(args.device))
    measure = None
    if device.is_cpu and not args.no_skimage:
        try:
            from skimage import measure
        except ImportError:
            print("scikit-image not installed: skipping it")

    print(f"device {device} ({device.name})")
    header = f"{'field':>7} {'n':>4} {'tris':>9} {'warpsim':>9} {'warp':>9} {'skimage':>9}   ratios (warpsim / other)"
    print(header + "\n" + "-" * len(header))
    for kind in args.fields:
        for n in args.sizes:
            field_np, h = make_field(kind, n)
            field = wp.array(field_np, dtype=wp.float32, device=device)
            mesher = MarchingCubes(field_np.shape, h, (-1.0, -1.0, -1.0), device, block_size=args.block_size)
            t_ours = best_time(lambda m=mesher, f=field: m.mesh(f), device, args.repeats)
            tri_count = mesher.mesh(field).face_count
            t_warp = best_time(
                lambda f=field: warp.geometry.IsoSurfaceMarchingCubes.extract(f, 0.0), device, args.repeats
            )
            t_sk = float("nan")
            if measure is not None:
                t_sk = best_time(lambda f=field_np: measure.marching_cubes(f, 0.0), device, args.repeats)
            rate = [n**3 / t / 1e6 for t in (t_ours, t_warp, t_sk)]
            ratios = f"x{t_warp / t_ours:6.1f} vs warp"
            if measure is not None:
                ratios += f", x{t_sk / t_ours:6.2f} vs skimage"
            print(
                f"{kind:>7} {n:>4} {tri_count:>9} {rate[0]:>9.1f} {rate[1]:>9.1f} {rate[2]:>9.1f}   {ratios}"
            )
    print("rates in Mvox/s (grid nodes per second), best of warm runs")


if __name__ == "__main__":
    sys.exit(run_script(main))
