"""The donut heap: step time of the ``donuts`` scene (soft tori piling up, ws.SoftContact) and the
share of each step spent in soft-body contact.

The scene is built with ``--count`` tori of ``--segments`` x ``--sides`` surface vertices
(default 12 tori of 50 x 40 = 2,000 vertices, plus each torus's interior lattice), dropped for
``--settle`` steps of ``--dt`` so that they touch (blow-up checks on), then three things are timed in this process on the same
heap: the full step (semi-implicit Euler, springs, box walls, SoftContact), the SoftContact stage
alone (refit of the BVH over all triangles, contact search, pushes and impulses), and the step
without SoftContact. Printed: ms per step, the contact stage's share of a step, the ratio of a
step with contact to one without, and the number of vertex contacts. On CUDA the full step is
also timed as a captured graph.

    python benchmarks/bench_donuts.py --device cpu --steps 20
    python benchmarks/bench_donuts.py --device cpu --count 3 --segments 16 --sides 8 --settle 200  # quick
    python benchmarks/bench_donuts.py --device cuda:0 --settle 3000 --steps 500
"""

import argparse
import time

import warp as wp
from timing import time_per_call, time_per_graph_launch

from warpsim.scenes import get_scene


def build(args, device):
    cls = get_scene("donuts")
    params = cls.resolve_params({"count": args.count, "segments": args.segments, "sides": args.sides,
                                 "lattice_cells": args.lattice_cells, "dt": args.dt})
    return cls(params, device=device)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default=None, help="Warp device (cpu, cuda:0); default: Warp's preferred")
    parser.add_argument("--count", type=int, default=12, help="number of tori")
    parser.add_argument("--segments", type=int, default=50, help="torus segments around its axis")
    parser.add_argument("--sides", type=int, default=40, help="torus segments around its tube")
    parser.add_argument("--lattice-cells", type=int, default=10, help="interior lattice cells across a torus")
    parser.add_argument("--dt", type=float, default=1.0 / 2400.0,
                        help="time step [s] (the scene's 1/1200 s blows up at 2,000 vertices a torus)")
    parser.add_argument("--settle", type=int, default=1000, help="steps simulated before timing (tori touching)")
    parser.add_argument("--steps", type=int, default=50, help="timed steps")
    args = parser.parse_args()
    device = wp.get_device(args.device)
    wp.config.quiet = True

    t0 = time.perf_counter()
    scene = build(args, device)
    sim, contact = scene.sim, scene.contact
    dt = scene.params["dt"]
    model = sim.model
    print(f"device {device}; {args.count} tori x {args.segments * args.sides} surface vertices; "
          f"{model.particle_count} particles, {model.spring_count} springs, {contact.triangle_count} contact "
          f"triangles; built in {time.perf_counter() - t0:.1f} s")
    t0 = time.perf_counter()
    for _ in range(args.settle):
        sim.step(dt)
    wp.synchronize_device(device)
    sim.check_every = 0  # blow-ups were checked every settling step; no host read-back while timing
    print(f"settled {args.settle} steps ({args.settle * dt:.3f} s simulated) in {time.perf_counter() - t0:.1f} s; "
          f"{contact.contact_count} vertex contacts, kinetic energy {scene.kinetic_energy():.3g} J")

    full = time_per_call(lambda: sim.step(dt), args.steps, device)
    st = sim.state
    stage = time_per_call(lambda: contact.apply(model, st, sim._q_prev, dt), args.steps, device)
    contacts = contact.contact_count
    colliders = sim.colliders
    sim.colliders = [c for c in colliders if c is not contact]
    without = time_per_call(lambda: sim.step(dt), args.steps, device)
    sim.colliders = colliders
    print(f"step with contact     {full * 1e3:9.3f} ms")
    print(f"SoftContact stage     {stage * 1e3:9.3f} ms   share of a step: {stage / full:.1%}  "
          f"({contacts} vertex contacts)")
    print(f"step without contact  {without * 1e3:9.3f} ms   with / without: {full / without:.2f}x")
    if device.is_cuda:
        try:
            graph = time_per_graph_launch(lambda: sim.step(dt), args.steps, device)
            print(f"step as a CUDA graph  {graph * 1e3:9.3f} ms   eager / graph: {full / graph:.2f}x")
        except Exception as exc:  # noqa: BLE001 (report and go on: the eager figures stand)
            print(f"CUDA graph capture failed: {exc}")


if __name__ == "__main__":
    main()
