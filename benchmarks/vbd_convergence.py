"""How close ``ws.VBD`` comes to backward Euler's step with N sweeps: the donut heap is settled with the
scene's VBD, then one step is taken from the same state with N sweeps (plain and Chebyshev-accelerated)
and compared with a step of ``--reference`` sweeps (the converged step): the largest position error
[mm] and its ratio to the step's largest displacement.

    python benchmarks/vbd_convergence.py --device cpu --count 4 --frames 30
"""

import argparse

import numpy as np
import warp as wp

import warpsim as ws
from warpsim.scenes import get_scene


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default=None)
    parser.add_argument("--count", type=int, default=4, help="tori (stacked in a 0.16 m box)")
    parser.add_argument("--frames", type=int, default=30, help="frames of 1/60 s before the step (4 steps each)")
    parser.add_argument("--reference", type=int, default=400, help="sweeps of the converged step")
    parser.add_argument("--sweeps", type=int, nargs="+", default=[2, 4, 8, 12, 20, 40])
    args = parser.parse_args()
    wp.config.quiet = True
    cls = get_scene("donuts")
    scene = cls(cls.resolve_params({"count": args.count, "box": 0.16, "integrator": "vbd"}), device=args.device)
    for _ in range(args.frames):
        scene.advance(1.0 / 60.0, 4)
    sim, h = scene.sim, 1.0 / 240.0
    start = tuple(a.numpy().copy() for a in (sim.state.positions, sim.state.velocities, sim.integrator.qd_prev))

    def one_step(sweeps, rho=0.0):
        integrator = sim.integrator
        integrator.iterations, integrator.chebyshev_rho = sweeps, rho
        integrator._omegas = ws.bodies.vbd.chebyshev_weights(rho, sweeps)
        integrator.reset()  # the Chebyshev buffers and recorded launches for these settings
        integrator.prepare(sim.system)
        for array, values in zip((sim.state.positions, sim.state.velocities, integrator.qd_prev), start):
            array.assign(values)
        integrator.step(sim.system, sim.state.positions, sim.state.velocities, sim._time, h)
        return sim.state.positions.numpy().astype(np.float64)

    reference = one_step(args.reference)
    moved = np.abs(reference - start[0]).max()
    print(f"{args.count} tori after {args.frames} frames; one step of {h:.4g} s; largest displacement "
          f"{moved * 1e3:.3f} mm; reference {args.reference} sweeps")
    for sweeps in args.sweeps:
        row = [f"{sweeps:4d} sweeps"]
        for rho in (0.0, 0.5, 0.9):
            error = np.abs(one_step(sweeps, rho) - reference).max()
            row.append(f"rho {rho:.1f}: {error * 1e3:8.4f} mm ({error / moved:.3f})")
        print("   ".join(row))


if __name__ == "__main__":
    main()
