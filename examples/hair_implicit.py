"""Hair stepped implicitly at the frame rate: strands on a head, sag-free, 4 steps per frame.

A fan of straight strands grows from the top of a spherical head (``ws.add_strands``), the groom is
made the equilibrium under gravity (``ws.sag_free``), and ``StrandImplicitEuler`` (backward Euler,
one block-band direct solve per strand) steps it at 4 steps per 1/60 s frame while the head turns.
The explicit step would need ``Simulator.stable_dt()`` (printed) per step instead. The table lists,
per 10 frames, the tips' largest distance from where they started and the fastest vertex.

    python examples/hair_implicit.py --frames 120 --strands 200 --segments 16
"""

import argparse
import math

import numpy as np

import warpsim as ws
from warpsim.cli_common import DefaultsHelpFormatter, device_arg, run_script
from warpsim.strands import StrandImplicitEuler
from warpsim.verbosity import set_warp_verbosity


def build(strands=200, segments=16, device=None):
    """(model, hair handle, simulator, head) of a fan of strands over a turning head."""
    center, radius = np.array([0.0, 0.55, 0.0]), 0.1
    phi = np.linspace(0.0, 2.0 * math.pi, strands, endpoint=False)
    normals = np.stack([0.6 * np.cos(phi), np.full(strands, 0.8), 0.6 * np.sin(phi)], axis=1)
    roots = center + radius * normals
    directions = normals + np.array([0.0, 0.3, 0.0])  # up and out: they droop over the head
    head = ws.Sphere(tuple(center), radius, restitution=0.0, friction=0.3, mode="project",
                     motion=lambda t: (np.zeros(3), np.array([0.0, math.sin(0.5 * min(t, 1.0) * math.sin(2.0 * t)),
                                                               0.0, math.cos(0.5 * min(t, 1.0) * math.sin(2.0 * t))])))
    b = ws.ModelBuilder()
    hair = ws.add_strands(b, roots, directions, segments, length=0.2, mass=1e-3, head=head)
    model = b.finalize(device)
    sim = ws.Simulator(model, integrator=StrandImplicitEuler(hair),
                       forces=[ws.Gravity(), ws.StrandForce(hair), ws.Drag(linear=2e-4)],
                       colliders=[head, ws.StrandRoots(hair, head), ws.Plane()])
    return model, hair, sim, head


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=DefaultsHelpFormatter)
    parser.add_argument("--frames", type=int, default=120)
    parser.add_argument("--strands", type=int, default=200)
    parser.add_argument("--segments", type=int, default=16)
    parser.add_argument("--steps", type=int, default=4, help="strand steps per 1/60 s frame")
    parser.add_argument("--device", default=None)
    parser.add_argument("--verbose", action="store_true", help="show Warp's banner and module-load lines")
    args = parser.parse_args(argv)
    set_warp_verbosity(args.verbose)
    args.device = device_arg(args.device)
    model, hair, sim, _ = build(args.strands, args.segments, args.device)
    report = ws.sag_free(sim)
    print(report)
    explicit = ws.Simulator(model, forces=list(sim.forces), colliders=[]).stable_dt()
    print(f"implicit step: {args.steps} steps per frame; the explicit step would need <= {explicit * 1e6:.1f} us "
          f"({math.ceil((1.0 / 60.0) / explicit)} steps per frame); stable_dt() here: {sim.stable_dt()}")
    tips = hair.tip_particles()
    x0 = sim.state.positions.numpy()[tips].copy()
    print(f"{'frame':>5} {'tip moved [m]':>14} {'fastest [m/s]':>14}")
    h = (1.0 / 60.0) / args.steps
    for frame in range(1, args.frames + 1):
        for _ in range(args.steps):
            sim.step(h)
        if frame % 10 == 0 or frame == args.frames:
            x = sim.state.positions.numpy()
            speed = float(np.linalg.norm(sim.state.velocities.numpy(), axis=1).max())
            print(f"{frame:5d} {float(np.linalg.norm(x[tips] - x0, axis=1).max()):14.4f} {speed:14.4f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(run_script(main))
