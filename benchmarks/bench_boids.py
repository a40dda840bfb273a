"""Boids step throughput: warpsim's Warp kernels (wp.HashGrid neighbours) against a NumPy
cell-grid reference of the same rules (warpsim.agents.reference.boids_step), in one process.

Both run the same flock: separation, alignment and cohesion within a 270-degree field of view,
speed limits, hard minimum distance and a periodic box whose size keeps the density at about
``--neighbours`` agents per perception sphere. The printed figure is agent-steps per second and
the ratio Warp / NumPy; one step from the same state is compared first (max position
difference) so the two are known to compute the same thing.

    python benchmarks/bench_boids.py                       # 10,000 agents on the CPU
    python benchmarks/bench_boids.py --agents 1000000 --device cuda:0

NumPy's cost per agent-step is flat at a fixed density, so for very large runs the reference
is timed on at most ``--numpy-agents`` agents (same density) and the ratio compares throughputs.
"""

import argparse
import math
import sys
import time

import numpy as np
import warp as wp

from warpsim.agents import BoidParams, Flock
from warpsim.agents import reference as R
from warpsim.cli_common import DefaultsHelpFormatter, device_arg, run_script
from warpsim.verbosity import set_warp_verbosity

PERCEPTION = 2.0


def make_flock_state(n, neighbours, seed):
    volume = n * (4.0 / 3.0 * math.pi * PERCEPTION ** 3) / neighbours
    L = volume ** (1.0 / 3.0)
    rng = np.random.default_rng(seed)
    x = rng.uniform(0.0, L, (n, 3))
    v = rng.normal(0.0, 1.0, (n, 3))
    v = 3.0 * v / np.linalg.norm(v, axis=1, keepdims=True)
    return x, v, L


PARAMS = BoidParams(max_speed=4.0, min_speed=1.0, max_force=6.0, perception_radius=PERCEPTION,
                    separation_radius=0.8, min_distance=0.3, fov_deg=270.0)


def time_warp(x, v, L, device, steps, dt):
    flock = Flock(x, v, params=PARAMS, bounds=((0, 0, 0), (L, L, L)), wrap=True, device=device)
    flock.step(dt)  # compile and warm up
    wp.synchronize_device(device)
    t0 = time.perf_counter()
    for _ in range(steps):
        flock.step(dt)
    wp.synchronize_device(device)
    return time.perf_counter() - t0


def time_numpy(x, v, L, steps, dt):
    box = ((0.0, 0.0, 0.0), (L, L, L), (True, True, True))
    rules = [PARAMS.rule_values()]
    kind = np.zeros(len(x), dtype=int)
    weights = (PARAMS.separation_weight, PARAMS.alignment_weight, PARAMS.cohesion_weight, PARAMS.boundary_weight, 2.0)
    t0 = time.perf_counter()
    for _ in range(steps):
        pairs = R.grid_pairs(x, rules[0]["query_radius"], box)
        x, v = R.boids_step(x, v, kind, rules, weights, PARAMS.min_speed, dt, box, pairs)
    return time.perf_counter() - t0


def check_same_step(device, dt):
    x, v, L = make_flock_state(2000, 20, seed=1)
    flock = Flock(x, v, params=PARAMS, bounds=((0, 0, 0), (L, L, L)), wrap=True, device=device)
    flock.step(dt)
    box = ((0.0, 0.0, 0.0), (L, L, L), (True, True, True))
    rules = [PARAMS.rule_values()]
    weights = (PARAMS.separation_weight, PARAMS.alignment_weight, PARAMS.cohesion_weight, PARAMS.boundary_weight, 2.0)
    xr, _ = R.boids_step(x, v, np.zeros(len(x), int), rules, weights, PARAMS.min_speed, dt, box,
                         R.grid_pairs(x, rules[0]["query_radius"], box))
    d = flock.positions.numpy() - xr
    d -= L * np.round(d / L)
    return float(np.abs(d).max())


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=DefaultsHelpFormatter)
    ap.add_argument("--agents", type=int, default=10_000)
    ap.add_argument("--neighbours", type=float, default=20.0, help="mean agents per perception sphere")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--steps", type=int, default=20, help="timed Warp steps")
    ap.add_argument("--numpy-steps", type=int, default=3, help="timed NumPy steps")
    ap.add_argument("--numpy-agents", type=int, default=50_000, help="most agents for the NumPy reference")
    ap.add_argument("--dt", type=float, default=1.0 / 60.0)
    args = ap.parse_args()
    set_warp_verbosity()  # quiet unless $WARPSIM_VERBOSE=1 (Warp 1.19 ignores config.quiet)
    wp.init()
    device = wp.get_device(device_arg(args.device))

    diff = check_same_step(device, args.dt)
    print(f"one step, 2,000 agents: max |x_warp - x_numpy| = {diff:.2e} m")

    x, v, L = make_flock_state(args.agents, args.neighbours, seed=0)
    tw = time_warp(x, v, L, device, args.steps, args.dt)
    warp_rate = args.agents * args.steps / tw
    n_np = min(args.agents, args.numpy_agents)
    xn, vn, Ln = make_flock_state(n_np, args.neighbours, seed=0)
    tn = time_numpy(xn, vn, Ln, args.numpy_steps, args.dt)
    numpy_rate = n_np * args.numpy_steps / tn
    print(f"device {device} ({device.name}); density {args.neighbours:g} agents per perception sphere")
    print(f"warp  : {args.agents:>9,d} agents x {args.steps} steps in {tw:8.3f} s = {warp_rate:14,.0f} agent-steps/s")
    print(f"numpy : {n_np:>9,d} agents x {args.numpy_steps} steps in {tn:8.3f} s = {numpy_rate:14,.0f} agent-steps/s")
    print(f"ratio warp / numpy: {warp_rate / numpy_rate:.1f}x")


if __name__ == "__main__":
    sys.exit(run_script(main))
