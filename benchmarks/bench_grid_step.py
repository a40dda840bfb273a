"""Grid-fluid step throughput: cell updates per second of a full smoke step, and warpsim against
Warp's own 2D stable-fluids example (``warp/examples/core/example_fluid.py``) per cell update at
equal pressure iteration counts, in one process.

Part 1 (3D): ``Smoke.step`` = MacCormack advection of the velocity, density and temperature,
buoyancy, vorticity confinement and a pressure projection to a relative residual of 1e-5
(Jacobi-preconditioned CG), on n^3 grids with a solid sphere and an open top, seeded with a
rising plume. Printed: CG iterations per step, cell updates per second.

Part 2 (2D, 256 x 128 like the example): the example's kernels (semi-Lagrangian advection,
``--iterations`` Jacobi pressure sweeps, gradient, forces) against a warpsim 2D smoke step with
semi-Lagrangian advection and exactly ``--iterations`` Jacobi-preconditioned CG iterations
(tolerance out of reach, no refinement pass). Printed: seconds per step and the ratio
warpsim / example per cell update. A CG iteration does more work than a Jacobi sweep (an
operator application, a preconditioner, two dot products, three vector updates) and converges
far faster, so the ratio is a cost per iteration, not per accuracy.

    python benchmarks/bench_grid_step.py                           # 32^3, 64^3 on the CPU
    python benchmarks/bench_grid_step.py --sizes 64 128 256 --device cuda:0
"""

import argparse
import sys

import numpy as np
import warp as wp
from timing import time_per_call

from warpsim.cli_common import DefaultsHelpFormatter, device_arg, run_script
from warpsim.grid_fluids.mac_grid import MacGrid
from warpsim.grid_fluids.pressure import PressureSolver
from warpsim.grid_fluids.smoke import Smoke


def smoke_3d(n, device, graph=False):
    g = MacGrid((n, n, n), 1.0 / n, open_sides=("+y",), device=device)
    g.add_sphere((0.5, 0.6, 0.5), 0.15)
    s = Smoke(g, temperature_buoyancy=4.0, density_buoyancy=0.5, vorticity=2.0, graph=graph)
    s.add_source((0.38, 0.05, 0.38), (0.62, 0.2, 0.62))
    c = g.positions()
    plume = np.exp(-((c[..., 0] - 0.5) ** 2 + (c[..., 2] - 0.5) ** 2) / 0.02) * (c[..., 1] < 0.5)
    s.density.assign(plume.astype(np.float32))
    s.temperature.assign(plume.astype(np.float32))
    g.set_velocity(lambda p: np.stack([0 * p[..., 0], np.exp(-((p[..., 0] - 0.5) ** 2 + (p[..., 2] - 0.5) ** 2) / 0.02),
                                       0 * p[..., 0]], -1))
    return s


def example_fluid_step(mod, state, iterations, dt, device):
    """One sub-step of Warp's example_fluid with its own kernels (no rendering, no graph)."""
    shape = state["u0"].shape
    wp.launch(mod.init, dim=shape, inputs=[state["rho0"], state["u0"], 5, wp.vec2(400.0, 0.0)], device=device)
    wp.launch(mod.integrate, dim=shape, inputs=[state["u0"], state["rho0"], dt], device=device)
    wp.launch(mod.divergence, dim=shape, inputs=[state["u0"], state["div"]], device=device)
    state["p0"].zero_()
    state["p1"].zero_()
    for _ in range(iterations):
        wp.launch(mod.pressure_solve, dim=shape, inputs=[state["p0"], state["p1"], state["div"]], device=device)
        state["p0"], state["p1"] = state["p1"], state["p0"]
    wp.launch(mod.pressure_apply, dim=shape, inputs=[state["p0"], state["u0"]], device=device)
    wp.launch(mod.advect, dim=shape, inputs=[state["u0"], state["u1"], state["rho0"], state["rho1"], dt], device=device)
    state["u0"], state["u1"] = state["u1"], state["u0"]
    state["rho0"], state["rho1"] = state["rho1"], state["rho0"]


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=DefaultsHelpFormatter)
    parser.add_argument("--sizes", type=int, nargs="+", default=[32, 64])
    parser.add_argument("--device", default=None)
    parser.add_argument("--steps", type=int, default=3)
    parser.add_argument("--iterations", type=int, default=100, help="pressure iterations in part 2")
    args = parser.parse_args()
    device = wp.get_device(device_arg(args.device))
    print(f"device {device}")
    print("part 1: 3D smoke step (MacCormack, vorticity confinement, CG to 1e-5)")
    print(f"{'cells':>10} {'CG it/step':>11} {'s/step':>9} {'cell updates/s':>15}")
    for n in args.sizes:
        s = smoke_3d(n, device)
        its = []

        def step(s=s, its=its, n=n):
            s.step(0.5 / n)
            its.append(s.pressure.last_iterations)

        t = time_per_call(step, args.steps, device)
        cells = s.grid.cell_count
        print(f"{cells:>10} {np.mean(its):>11.0f} {t:>9.4f} {cells / t:>15.3e}")
        if device.is_cuda:  # the same step replayed as a CUDA graph (Smoke(graph=True): device-side CG checks)
            s = smoke_3d(n, device, graph=True)
            s.step(0.5 / n)
            t = time_per_call(lambda s=s, n=n: s.step(0.5 / n), args.steps, device)
            print(f"{cells:>10} {int(s.pressure.last_iterations.numpy()[0]):>11} {t:>9.4f} {cells / t:>15.3e}"
                  "  (CUDA graph)")

    print(f"part 2: 2D 256 x 128, {args.iterations} pressure iterations per step")
    from warp.examples.core import example_fluid as mod

    shape = (int(mod.grid_width), int(mod.grid_height))
    state = {k: wp.zeros(shape, dtype=wp.vec2, device=device) for k in ("u0", "u1")}
    state.update({k: wp.zeros(shape, dtype=float, device=device) for k in ("rho0", "rho1", "p0", "p1", "div")})
    t_example = time_per_call(lambda: example_fluid_step(mod, state, args.iterations, 1.0 / 120, device), args.steps, device)
    g = MacGrid(shape, 1.0 / shape[1], device=device)
    s = Smoke(g, scheme="semi_lagrangian", temperature_buoyancy=4.0)
    s.pressure = PressureSolver(g, tol=1e-12, atol=1e-30, max_iterations=args.iterations, refine=False)
    s.add_source((0.9, 0.05), (1.1, 0.2))
    t_warpsim = time_per_call(lambda: s.step(1.0 / 120), args.steps, device)
    its = s.pressure.last_iterations
    cells = shape[0] * shape[1]
    print(f"  example_fluid (Jacobi sweeps): {t_example:.4f} s/step, {cells / t_example:.3e} cell updates/s")
    print(f"  warpsim Smoke ({its} CG its):  {t_warpsim:.4f} s/step, {cells / t_warpsim:.3e} cell updates/s")
    print(f"  warpsim / example time per cell update: {t_warpsim / t_example:.2f}")


if __name__ == "__main__":
    sys.exit(run_script(main))
