"""Cost of a gradient: forward plus backward of a differentiable cloth rollout against the forward
alone (goal: at most 3x).

A dim x dim cloth (``add_cloth_grid``, two corners pinned, structural/shear/bend springs, gravity,
a floor plane) is stepped ``--steps`` times with the cloth's semi-implicit Euler at 60 fps and
``--substeps`` sub-steps per frame, all in this process:

- reference: the ordinary ``ClothSimulator`` (``frame()``, each frame's sub-steps replayed as a
  captured graph), forward only;
- ``differentiable=True``: the forward alone (one State per step recorded on the tape), then
  forward + loss (mean squared distance of the last state to a target) + ``tape.backward``,
  eagerly and, with ``--graph`` (default), reset + forward + loss + backward captured once as a
  graph and replayed (the forward alone too).

It checks that the differentiable forward ends where the ordinary one does and prints the
seconds per rollout, the ratios and the rollout's memory (states, stages and their gradients).

    python benchmarks/bench_differentiable.py --device cpu --dims 16 32 64 --steps 1000
    python benchmarks/bench_differentiable.py --device cuda:0 --dims 64 128 256 --steps 1000
"""

from __future__ import annotations

import argparse
import sys

import numpy as np
import warp as wp

from warpsim.verbosity import set_warp_verbosity

set_warp_verbosity()  # quiet unless $WARPSIM_VERBOSE=1 (Warp 1.19 ignores config.quiet)

from timing import time_per_call, time_per_graph_launch

import warpsim as ws
from warpsim.cli_common import DefaultsHelpFormatter, device_arg, run_script

FPS = 60.0


def make(dim, differentiable, device):
    builder = ws.ModelBuilder()
    ws.add_cloth_grid(builder, dim - 1, 1.0, (0.0, 1.0, 0.0), particle_mass=0.01, pin=["corner_00", "corner_10"],
                      structural=(200.0, 0.05), shear=(50.0, 0.02), bend=(5.0, 0.005))
    return ws.ClothSimulator(builder.finalize(device), "semi_implicit_euler", [ws.Gravity()],
                             [ws.Plane((0.0, 1.0, 0.0), 0.2, restitution=0.0, friction=0.2, mode="project")],
                             check_every=0, differentiable=differentiable)


def rollout_bytes(rollout) -> int:
    arrays = [a for s in rollout.states for a in (s.positions, s.velocities, s.forces)]
    arrays += [a for stage in rollout._stages for pair in stage for a in pair]
    return sum(2 * a.capacity for a in arrays)  # values and gradients


def bench(dim, steps, substeps, device, graph):
    frames = max(1, steps // substeps)
    steps = frames * substeps
    ordinary = make(dim, False, device)

    def forward_ordinary():
        for _ in range(frames):
            ordinary.frame(1.0 / FPS, substeps)

    t_ref = time_per_call(forward_ordinary, 1, device)
    sim = make(dim, True, device)
    r = sim.rollout
    r.reserve(steps)
    target = wp.zeros(sim.model.particle_count, dtype=wp.vec3, device=sim.device)
    loss = wp.zeros(1, dtype=float, device=sim.device, requires_grad=True)

    def forward():
        r.reset()
        for _ in range(frames):
            sim.frame(1.0 / FPS, substeps)

    def forward_backward():
        forward()
        r.backward(r.trajectory_loss([target], 1.0 / sim.model.particle_count, loss))

    forward()
    ordinary2 = make(dim, False, device)
    for _ in range(frames):
        ordinary2.frame(1.0 / FPS, substeps)
    same = np.array_equal(sim.state.positions.numpy(), ordinary2.state.positions.numpy())
    gap = float(np.abs(sim.state.positions.numpy() - ordinary2.state.positions.numpy()).max())
    t_fwd = time_per_call(forward, 1, device)
    t_fb = time_per_call(forward_backward, 1, device)
    t_graph = t_graph_fwd = float("nan")
    if graph:
        t_graph_fwd = time_per_graph_launch(forward, 2, device)
        t_graph = time_per_graph_launch(forward_backward, 2, device)
    grad = float(np.abs(sim.model.spring_stiffness.grad.numpy()).max())
    return dict(dim=dim, steps=steps, ref=t_ref, fwd=t_fwd, fb=t_fb, graph_fwd=t_graph_fwd, graph=t_graph,
                same=same, gap=gap,
                mem=rollout_bytes(r), grad=grad)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=DefaultsHelpFormatter)
    parser.add_argument("--device", default=None)
    parser.add_argument("--dims", type=int, nargs="+", default=[16, 32, 64], help="particles per side")
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--substeps", type=int, default=10)
    parser.add_argument("--no-graph", dest="graph", action="store_false",
                        help="skip the captured forward + backward")
    args = parser.parse_args(argv)
    device = wp.get_device(device_arg(args.device))
    print(f"device {device}, {args.steps} steps ({args.substeps} sub-steps per frame), cloth semi-implicit Euler")
    print("eager: launched one by one from Python; graph: captured once and replayed (also on the CPU)")
    print(f"{'dim':>5} {'ref fwd [s]':>11} {'fwd [s]':>8} {'f+b [s]':>8} {'graph fwd':>9} {'graph f+b':>9} "
          f"{'f+b/fwd':>7} {'graph f+b/fwd':>13} {'graph f+b/ref':>13} {'memory':>9} {'same':>5}")
    for dim in args.dims:
        b = bench(dim, args.steps, args.substeps, device, args.graph)
        same = "yes" if b["same"] else f"{b['gap']:.0e}"
        print(f"{b['dim']:5d} {b['ref']:11.4f} {b['fwd']:8.4f} {b['fb']:8.4f} {b['graph_fwd']:9.4f} {b['graph']:9.4f} "
              f"{b['fb'] / b['fwd']:7.2f} {b['graph'] / b['graph_fwd']:13.2f} {b['graph'] / b['ref']:13.2f} "
              f"{b['mem'] / 2**20:7.0f} MB {same:>5}")
        assert np.isfinite(b["grad"]) and b["grad"] > 0.0, "no gradient reached the spring stiffness"


if __name__ == "__main__":
    sys.exit(run_script(main))
