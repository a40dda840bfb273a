"""Cost of the stability estimate (``Simulator.stability()``: power iteration over the springs)
against one simulated frame of the same model, and the sub-steps ``substeps="auto"`` picks; and
the cost of the energy-balance blow-up check (``warpsim.core.energy``) per frame against the frame.

    python benchmarks/bench_stability.py --device cuda:0 [--cloth 256] [--frames 5] [--worlds 100000]

Prints, for a grid cloth of N x N cells (semi-implicit Euler) and the teapot: particles,
springs, the limit [s], the sub-steps auto picks for a 1/60 s frame, the wall time of one
estimate and of one frame at those sub-steps, and their ratio (the estimate runs once per
parameter change, frames every 1/60 s).
"""

from __future__ import annotations

import argparse
import sys
import time

import warp as wp

from warpsim.cli_common import DefaultsHelpFormatter, device_arg, run_script
from warpsim.verbosity import set_warp_verbosity


def _time(fn, repeat):
    fn()  # warm-up: kernels loaded
    wp.synchronize()
    t0 = time.perf_counter()
    for _ in range(repeat):
        fn()
    wp.synchronize()
    return (time.perf_counter() - t0) / repeat


def report(name, sim, frame_dt, frames):
    limit = sim.stability()
    n = sim.auto_substeps(frame_dt)
    estimate = _time(sim.stability, 3)

    def frame():
        for _ in range(n):
            sim.step(frame_dt / n)

    per_frame = _time(frame, frames)
    print(f"{name:<14} particles {sim.model.particle_count:>8} springs {sim.model.spring_count:>8}  "
          f"limit {limit.dt:.4g} s ({limit.limiting} {limit.index})  auto sub-steps {n:>4}  "
          f"estimate {1e3 * estimate:8.2f} ms  frame {1e3 * per_frame:8.2f} ms  ratio {estimate / per_frame:6.2f}")


def energy_report(name, check, frame, frames):
    """Wall time of one energy check against one frame (both synchronised), and their ratio."""
    per_check = _time(check, frames)
    per_frame = _time(frame, frames)
    print(f"energy check {name:<24} check {1e3 * per_check:8.3f} ms  frame {1e3 * per_frame:8.3f} ms  "
          f"check / frame {100.0 * per_check / per_frame:6.2f} %")


def energy_costs(device, cloth, worlds, frames):
    """The balance on one Simulator (a grid cloth: fixed-order strided sums) and on a sweep of
    ``worlds`` teapots (one thread per world, as ``warpsim sweep`` runs it)."""
    import warpsim as ws
    from warpsim.scenes import get_scene
    from warpsim.sweeps import sample_worlds
    from warpsim.worlds import WorldBatch
    from warpsim.sweeps.metrics import WorldMetrics

    b = ws.ModelBuilder()
    ws.add_cloth_grid(b, resolution=(cloth, cloth), size=(1.0, 1.0), origin=(0.0, 1.0, 0.0), pin=[0, cloth])
    sim = ws.Simulator(b.finalize(device), integrator="semi_implicit_euler")
    n = sim.auto_substeps(1.0 / 60.0)
    sim.step(1.0 / 60.0 / n)  # starts the balance

    def cloth_frame():
        for _ in range(n):
            sim.step(1.0 / 60.0 / n)

    energy_report(f"cloth {cloth}^2 ({n} steps)", lambda: sim._energy.update(sim.state, 1.0 / 60.0 / n, 1.0 / 60.0,
                                                                          time=sim._time), cloth_frame, frames)
    cls = get_scene("teapot")
    params = sample_worlds("teapot", {}, ["stiffness=20:60", "restitution=0.2:0.8"], worlds, sample="lhs", seed=1)
    batch = WorldBatch(cls, params, device=device)
    steps = cls.substeps
    metrics = WorldMetrics(batch, frame_dt=1.0 / 60.0, step_dt=1.0 / 60.0 / steps)
    metrics.update()  # frame 0: the balance's reference
    st = batch.sim.state
    energy_report(f"{worlds} teapot worlds ({steps} steps)",
                  lambda: metrics.energy.update(st, 1.0 / 60.0 / steps, 1.0 / 60.0, time=batch.sim._time,
                                                world_bad=batch.world_bad),
                  lambda: batch.advance(1.0 / 60.0, steps), frames)
    print("energy check PBF fluids: not applied (ws.ParticleFluid projects positions; it has its own checks)")


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=DefaultsHelpFormatter)
    p.add_argument("--device", default=None)
    p.add_argument("--cloth", type=int, default=256, help="cells per side of the grid cloth")
    p.add_argument("--frames", type=int, default=5)
    p.add_argument("--worlds", type=int, default=1000, help="teapot worlds for the sweep's energy check")
    p.add_argument("--energy-only", action="store_true", help="only the energy-check costs")
    args = p.parse_args()
    set_warp_verbosity()  # quiet unless $WARPSIM_VERBOSE=1 (Warp 1.19 ignores config.quiet)
    import warnings

    import warpsim as ws
    from warpsim.scenes import get_scene

    warnings.simplefilter("ignore", ws.StabilityWarning)
    device = wp.get_device(device_arg(args.device))
    energy_costs(device, args.cloth, args.worlds, args.frames)
    if args.energy_only:
        print(f"device: {device}")
        return
    b = ws.ModelBuilder()
    ws.add_cloth_grid(b, resolution=(args.cloth, args.cloth), size=(1.0, 1.0), origin=(0.0, 1.0, 0.0), pin=[0, args.cloth])
    sim = ws.Simulator(b.finalize(device), integrator="semi_implicit_euler", check_every=0)
    report(f"cloth {args.cloth}^2", sim, 1.0 / 60.0, args.frames)
    scene = get_scene("teapot")({}, device=device)
    scene.sim.check_every = 0
    report("teapot", scene.sim, 1.0 / 60.0, args.frames)
    print(f"device: {device}")


if __name__ == "__main__":
    sys.exit(run_script(main))
