"""The donut heap frame by frame: contacts, kinetic energy, heights and, every ``--check-every``
frames, the two properties the heap tests assert (the deepest vertex of a torus inside another,
against the contact thickness, and the surface edges passing through another torus's triangles,
NumPy oracles from ``tests/test_soft_contact_scale.py``). For finding where a step size or a contact
setting stops holding, at any resolution and on any device (the tests run small tori on the CPU).

    python benchmarks/check_heap.py --device cpu --count 2 --dt 1/240 --frames 40 --check-every 5
    python benchmarks/check_heap.py --device cuda:0 --count 12 --dt 1/240 --frames 60 --check-every 10 \\
        --set newton_iterations=2
    python benchmarks/check_heap.py --device cpu --count 4 --segments 14 --sides 7 --lattice-cells 6 \\
        --set box=0.16 --dt 1/240 --frames 40 --check-every 2

Defaults: the benchmark's tori (50 x 40 surface vertices, ``bench_donuts.py``), implicit Euler. Each
line: frame, vertex and edge contacts (speculative ones included; ``--integrator vbd``: the pairs its
contact listed), the energy balance's gain so far (checked every frame), kinetic energy [J], fastest
particle [m/s], mean height of all particles [m], CG iterations of the last step, wall time [s], the
mean height of each torus (up to 4), then ``depth`` [mm] and ``crossings`` on checked frames.
"""

import argparse
import os
import sys
import time
from fractions import Fraction

import numpy as np
import warp as wp
from bench_donuts import add_heap_arguments

from warpsim.scenes import get_scene

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests"))
# the tests' NumPy oracles
from test_soft_contact_scale import deepest_vertex, edges_through_other_bodies


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_heap_arguments(parser)
    parser.add_argument("--integrator", default="implicit_euler", help="the scene's integrator")
    parser.add_argument("--dt", default="1/240", help="step [s], e.g. 1/240 (a frame of 1/60 s is split into steps)")
    parser.add_argument("--frames", type=int, default=40, help="frames of 1/60 s")
    parser.add_argument("--check-every", type=int, default=5, help="check depth and crossings every N frames (0: never)")
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                        help="another donuts parameter (repeatable), e.g. contact_iterations=8")
    args = parser.parse_args()
    wp.config.quiet = True
    dt = float(Fraction(args.dt))
    cls = get_scene("donuts")
    extra = dict(item.split("=", 1) for item in args.set)
    params = cls.resolve_params({"count": args.count, "segments": args.segments, "sides": args.sides,
                                 "lattice_cells": args.lattice_cells, "integrator": args.integrator, "dt": dt, **extra})
    scene = cls(params, device=wp.get_device(args.device))
    steps = round(1.0 / 60.0 / dt)
    per_torus = scene.torus.particle_count
    t0 = time.perf_counter()
    for frame in range(args.frames):
        scene.advance(1.0 / 60.0, steps)
        sim, contact = scene.sim, scene.contact
        sim.check_frame(1.0 / 60.0)  # the energy balance (raises past its margin)
        x = sim.state.positions.numpy()
        # integrator=vbd: the pairs its contact listed (vertex-triangle, edge-edge), else SoftContact's contacts
        counts = scene.vbd_contact.pair_counts() if getattr(scene, "vbd_contact", None) is not None else \
            (contact.contact_count if contact else 0, contact.edge_contact_count if contact else 0)
        line = (f"{frame} contacts {counts[0]} {counts[1]} gain {sim.energy_gain:.3g}"
                f" ke {scene.kinetic_energy():.3g} vmax {np.abs(sim.state.velocities.numpy()).max():.3g}"
                f" ymean {x[:, 1].mean():.3f} cg {getattr(sim.integrator, 'last_cg_iterations', 0)}"
                f" t {time.perf_counter() - t0:.1f}")
        if args.count <= 4:
            line += " tori " + " ".join(f"{x[o:o + per_torus, 1].mean():.3f}" for o in scene.offsets)
        if args.check_every and frame % args.check_every == args.check_every - 1:
            crossings = edges_through_other_bodies(x, scene.bodies)
            line += (f" depth {deepest_vertex(x, scene.bodies) * 1e3:.2f}mm"
                     f" crossings {sum(n for *_, n in crossings)}")
        print(line, flush=True)


if __name__ == "__main__":
    main()
