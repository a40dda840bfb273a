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

``--profile-every N`` (CUDA) times every kernel of one frame in N (``wp.timing_begin``) and prints, at the end, the
share of the GPU's activity in those frames spent in the contact search (the kernels of ``kernels.vbd_contact`` and
``kernels.soft_contact``, and the BVH's refits and rebuilds; the contact energies inside VBD's colour sweeps count as
the solve) and the frames of 1/60 s a wall second over the frames not checked or profiled; ``--print-every N``
prints one frame's line in N (checked frames always). ``--oracle warp`` (the default) counts the crossings on the
heap's device (``heap_oracles.py``: the NumPy oracle's count in seconds) and computes the depth with the NumPy
oracle only where an edge crossed (two closed surfaces of tori that no edge of either crosses cannot hold a vertex
of one inside the other); ``--oracle numpy`` runs the tests' oracles:

    python benchmarks/check_heap.py --device cuda:0 --count 100 --segments 50 --sides 40 --integrator vbd \
        --dt 1/240 --frames 600 --check-every 100 --profile-every 25 --print-every 25
"""

import argparse
import os
import sys
import time
from fractions import Fraction

import numpy as np
import warp as wp
from bench_donuts import add_heap_arguments
from heap_oracles import edges_through_other_bodies_count
from timing import activity_name
from vbd_heap import heap_state

from warpsim.kernels import soft_contact, vbd, vbd_contact
from warpsim.scenes import get_scene

CONTACT_KERNELS = {k.key for module in (soft_contact, vbd_contact) for k in vars(module).values()
                   if isinstance(k, wp.Kernel)} | {vbd.list_contact_particles.key}
"""Names of the contact search's kernels (``--profile-every``), and VBD's listing of the particles a search leaves
within reach of a contact (split sweeps)."""


def is_contact(result) -> bool:
    """Whether a timed activity of ``wp.timing_end`` belongs to the contact search: its kernels, and Warp's built-in
    kernels (in these steps only the BVHs' refits and builds: ``bvh_refit_kernel``, ``build_hierarchy``, ...)."""
    return activity_name(result) in CONTACT_KERNELS or (result.name or "").startswith("builtin kernel")

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
    parser.add_argument("--profile-every", type=int, default=0, help="CUDA: time the kernels of one frame in N and "
                        "print the contact search's share of the GPU's activity at the end (0: never)")
    parser.add_argument("--print-every", type=int, default=1, help="print one frame's line in N (checked frames "
                        "always)")
    parser.add_argument("--oracle", default="warp", choices=["warp", "numpy"], help="the crossing check: warp "
                        "(heap_oracles.py on the heap's device, the NumPy oracle's count; the depth then only where "
                        "an edge crossed) or numpy (the tests' oracles, minutes a check at 100 tori)")
    parser.add_argument("--state", action="store_true", help="vbd: on each printed frame also the heap's state "
                        "(vbd_heap.heap_state: fastest particles and the tori holding them, bounds, smallest gaps)")
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
    device = scene.sim.model.device
    profiled = []  # (contact ms, all ms) of each profiled frame
    plain = [0, 0.0]  # frames neither checked nor profiled, their wall seconds
    vbd = getattr(scene, "vbd_contact", None) if args.integrator == "vbd" else None
    searches = vbd.searches_run if vbd is not None else 0
    t0 = time.perf_counter()
    for frame in range(args.frames):
        profile = bool(args.profile_every and device.is_cuda and frame % args.profile_every == 0)
        checked = bool(args.check_every and frame % args.check_every == args.check_every - 1)
        if profile:
            wp.timing_begin(cuda_filter=wp.TIMING_ALL)
        wp.synchronize_device(device)
        start = time.perf_counter()
        scene.advance(1.0 / 60.0, steps)
        if profile:
            results = wp.timing_end()
            profiled.append((sum(r.elapsed for r in results if is_contact(r)),
                             sum(r.elapsed for r in results)))
            print(f"{frame} profiled: contact search {profiled[-1][0]:.2f} of {profiled[-1][1]:.2f} ms of GPU activity "
                  f"({profiled[-1][0] / max(profiled[-1][1], 1e-9):.1%})", flush=True)
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
        if vbd is not None:  # the contact searches that ran (those at rest are skipped)
            line += f" searches/step {(vbd.searches_run - searches) / steps:.2f}"
            searches = vbd.searches_run
        if args.count <= 4:
            line += " tori " + " ".join(f"{x[o:o + per_torus, 1].mean():.3f}" for o in scene.offsets)
        if not profile and not checked:
            plain[0] += 1
            plain[1] += time.perf_counter() - start  # the frame and its energy check and read-backs
        if checked and args.oracle == "numpy":
            crossings = edges_through_other_bodies(x, scene.bodies)
            line += (f" depth {deepest_vertex(x, scene.bodies) * 1e3:.2f}mm"
                     f" crossings {sum(n for *_, n in crossings)}")
        elif checked:
            crossed = edges_through_other_bodies_count(x, scene.bodies, device)
            depth = f"{deepest_vertex(x, scene.bodies) * 1e3:.2f}mm" if crossed else "- (no edge crossed)"
            line += f" depth {depth} crossings {crossed}"
        if checked or frame % max(args.print_every, 1) == 0 or frame == args.frames - 1:
            print(line, flush=True)
            if args.state and vbd is not None:
                print(f"{frame} {heap_state(scene, sim.integrator.renew_fraction)}", flush=True)
    if profiled:
        contact_ms, all_ms = (sum(column) for column in zip(*profiled))
        print(f"contact search over {len(profiled)} profiled frames (one in {args.profile_every}): "
              f"{contact_ms / len(profiled):.2f} of {all_ms / len(profiled):.2f} ms of GPU activity a frame, "
              f"{contact_ms / all_ms:.1%} (per profiled frame: "
              f"{', '.join(f'{c / a:.0%}' for c, a in profiled)})")
    if plain[0]:
        print(f"{plain[0]} frames neither checked nor profiled: {plain[0] / plain[1]:.2f} frames of 1/60 s a wall "
              f"second (each with its energy check and read-backs)")


if __name__ == "__main__":
    main()
