"""Hair step rate: the ``hair`` scene's strands against the same particles as a plain mass-spring.

warpsim: the ``hair`` scene (sphere head turning and nodding, ``StrandForce``: stretch and
bending with transported frames, one thread per strand, no atomics; semi-implicit Euler; head,
kinematic roots, floor; air drag). Reference, in the same process: the same particles, masses
and pins stepped by the generic ``ws.Simulator`` with ``ws.Springs`` (a stretch spring per segment
and a distance spring across two segments per vertex, one thread per spring with atomic adds),
gravity, the head (static) and the floor. Both step at the scene's measured stable step. Prints
steps per second of each, their ratio, and the one-time costs (build, stable-step measurement,
sag-free solve).

    python benchmarks/bench_hair.py --device cpu --strands 200 --segments 16 --steps 50
    python benchmarks/bench_hair.py --device cuda:0 --strands 100000 --segments 32
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import warp as wp

wp.config.quiet = True
wp.config.log_level = getattr(wp, "LOG_WARNING", wp.config.log_level)

from timing import time_per_call

import warpsim as ws


def reference_simulator(scene, device):
    """The scene's particles as plain springs (stretch + across two segments) in ws.Simulator."""
    model = scene.model
    hair = scene.hair
    b = ws.ModelBuilder()
    q = model.particle_q.numpy()
    b.particle_q.extend(map(tuple, q.tolist()))
    b.particle_qd.extend([(0.0, 0.0, 0.0)] * len(q))
    b.particle_mass.extend(model.particle_mass.numpy().tolist())
    b.particle_radius.extend(model.particle_radius.numpy().tolist())
    idx = hair.particles()
    pairs, ks = [], []
    for gap, k in ((1, hair.stretch_stiffness), (2, hair.bend_stiffness)):
        a = idx[:, 1:-gap].reshape(-1)
        pairs.append(np.stack([a, a + gap], axis=1))
        ks.append(np.repeat(k, idx.shape[1] - 1 - gap))
    pairs, ks = np.concatenate(pairs), np.concatenate(ks)
    rest = np.linalg.norm(q[pairs[:, 0]] - q[pairs[:, 1]], axis=1)
    b.spring_indices.extend(map(tuple, pairs.tolist()))
    b.spring_rest_length.extend(rest.tolist())
    b.spring_stiffness.extend(ks.tolist())
    b.spring_damping.extend([float(hair.stretch_damping[0])] * len(pairs))
    head = ws.Sphere(tuple(scene.head.center), scene.head.radius, restitution=0.0, friction=0.3, mode="project")
    floor = ws.Plane(restitution=0.0, friction=0.3, mode="project")
    return ws.Simulator(b.finalize(device), forces=[ws.Gravity()], colliders=[head, floor],
                        check_every=scene.sim.check_every)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default=None)
    parser.add_argument("--strands", type=int, default=100_000)
    parser.add_argument("--segments", type=int, default=32)
    parser.add_argument("--steps", type=int, default=200, help="timed steps per run")
    parser.add_argument("--no-reference", action="store_true", help="skip the plain mass-spring reference")
    args = parser.parse_args()
    device = wp.get_device(args.device)
    from warpsim.scenes import get_scene

    t0 = time.perf_counter()
    scene = get_scene("hair")({"strands": args.strands, "segments": args.segments, "still": 0.0,
                               "motion": "turn_nod", "sag_free": False}, device=device)
    build = time.perf_counter() - t0
    t0 = time.perf_counter()
    report = ws.sag_free(scene.sim)
    wp.synchronize_device(device)
    solve = time.perf_counter() - t0
    h = (1.0 / 60.0) / scene.strand_steps(1.0 / 60.0)
    particles = scene.model.particle_count
    print(f"hair: {args.strands} strands x {args.segments} segments = {particles} particles on {device}; "
          f"step {h * 1e6:.1f} us ({scene.strand_steps(1 / 60)} steps per 1/60 s frame, stable step "
          f"{scene.stable_dt * 1e6:.1f} us measured)")
    print(f"  build (groom, add_strands, finalize, stable-step measurement): {build:.2f} s")
    print(f"  sag_free: {solve:.2f} s, {report.rounds} rounds, {report.iterations} CGLS iterations, "
          f"residual {100 * report.residual_relative:.3g} % of the largest load")
    scene.sim.step(h)  # compile
    per_step = time_per_call(lambda: scene.sim.step(h), args.steps, device)
    print(f"  warpsim strands: {1.0 / per_step:10.1f} steps/s  ({per_step * 1e3:.3f} ms/step, "
          f"{particles / per_step / 1e6:.1f} M particle-steps/s, "
          f"{1.0 / (per_step * scene.strand_steps(1 / 60)):.2f} frames/s at 60 fps)")
    if not args.no_reference:
        ref = reference_simulator(scene, device)
        ref.step(h)
        per_ref = time_per_call(lambda: ref.step(h), args.steps, device)
        print(f"  plain springs:   {1.0 / per_ref:10.1f} steps/s  ({per_ref * 1e3:.3f} ms/step, "
              f"{ref.model.spring_count} springs)")
        print(f"  ratio (strands / plain springs steps/s): {per_ref / per_step:.2f}")


if __name__ == "__main__":
    main()
