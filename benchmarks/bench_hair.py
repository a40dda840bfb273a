"""Hair frame rate: the ``hair`` scene's implicit strand step against its explicit step, same run.

warpsim: the ``hair`` scene (sphere head turning and nodding; stretch and bending with
transported frames; head, kinematic roots, floor; air drag), stepped two ways in one process:
- implicit (the scene's default): ``StrandImplicitEuler``, backward Euler with one float64
  block-band direct solve per strand (one thread per strand), ``steps`` strand steps per 1/60 s
  frame, timed by whole frames (``scene.advance``: the head's poses uploaded, the steps, the
  blow-up test's read-back) with each frame captured as one CUDA graph (the scene's default on
  CUDA) and eagerly, launch by launch;
- explicit (``solver=explicit``, the reference): semi-implicit Euler at half the strands'
  measured stable step (``StrandForce``, one thread per strand).
Prints for each the steps per second, the steps per 1/60 s frame and the frames per second
(simulation only, no drawing or writing), their ratio, and the one-time costs (build, stable-step
measurement, sag-free solve). ``--style wavy`` / ``curly``: the curled grooms. ``--reference`` adds
the plain mass-spring stand-in of the earlier version of this script (``ws.Simulator`` with
``ws.Springs``).

    python benchmarks/bench_hair.py --device cpu --strands 2000 --segments 16 --steps 10
    python benchmarks/bench_hair.py --device cuda:0 --strands 15000 --segments 32
    python benchmarks/bench_hair.py --device cuda:0 --strands 100000 --segments 32
    python benchmarks/bench_hair.py --device cuda:0 --strands 15000 --segments 32 --style wavy --no-explicit
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np
import warp as wp

from warpsim.verbosity import set_warp_verbosity

set_warp_verbosity()  # quiet unless $WARPSIM_VERBOSE=1 (Warp 1.19 ignores config.quiet)
wp.config.log_level = getattr(wp, "LOG_WARNING", wp.config.log_level)

from timing import time_per_call

import warpsim as ws
from warpsim.cli_common import DefaultsHelpFormatter, device_arg, run_script


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


def build(args, device, solver):
    from warpsim.scenes import get_scene

    t0 = time.perf_counter()
    scene = get_scene("hair")({"strands": args.strands, "segments": args.segments, "still": 0.0, "motion": "turn_nod",
                               "sag_free": False, "solver": solver, "style": args.style}, device=device)
    wp.synchronize_device(device)
    return scene, time.perf_counter() - t0


def measure(scene, label, steps, device):
    """(seconds per strand step, steps per 1/60 s frame) of ``scene``; prints one line."""
    n = scene.strand_steps(1.0 / 60.0)
    h = (1.0 / 60.0) / n
    per_step = time_per_call(lambda: scene.sim.step(h), steps, device)
    particles = scene.model.particle_count
    print(f"  {label}: {1.0 / per_step:10.1f} steps/s ({per_step * 1e3:.3f} ms/step, "
          f"{particles / per_step / 1e6:.1f} M particle-steps/s; {n} steps per 1/60 s frame) = "
          f"{1.0 / (per_step * n):.2f} frames/s")
    return per_step, n


def measure_frames(scene, label, frames, device, graph):
    """Seconds per 1/60 s frame of ``scene.advance`` (``graph``: captured as a CUDA graph where
    the device is CUDA, else eager); prints one line."""
    scene.frame.use_graph = bool(graph)
    n = scene.frame_steps(1.0 / 60.0, 1)
    for _ in range(2):  # the eager first frame loads the modules, the second captures the graph
        scene.advance(1.0 / 60.0, 1)
    per_frame = time_per_call(lambda: scene.advance(1.0 / 60.0, 1), frames, device)
    particles = scene.model.particle_count
    print(f"  {label}: {1.0 / per_frame:.1f} frames/s ({n} steps per 1/60 s frame, {per_frame / n * 1e3:.3f} ms/step, "
          f"{particles * n / per_frame / 1e6:.1f} M particle-steps/s)")
    return per_frame, n


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=DefaultsHelpFormatter)
    parser.add_argument("--device", default=None)
    parser.add_argument("--strands", type=int, default=100_000)
    parser.add_argument("--segments", type=int, default=32)
    parser.add_argument("--steps", type=int, default=100, help="timed strand steps (implicit: steps / 4 frames)")
    parser.add_argument("--style", default="straight", choices=("straight", "wavy", "curly"), help="the groom")
    parser.add_argument("--explicit-steps", type=int, default=None, help="timed steps of the explicit step "
                                                                         "(default: --steps)")
    parser.add_argument("--no-explicit", action="store_true", help="skip the explicit step")
    parser.add_argument("--no-sag-free", action="store_true", help="skip the sag-free solve")
    parser.add_argument("--reference", action="store_true", help="also the plain mass-spring stand-in")
    args = parser.parse_args()
    device = wp.get_device(device_arg(args.device))

    scene, built = build(args, device, "implicit")
    particles = scene.model.particle_count
    stable = scene.stable_dt
    print(f"hair: {args.strands} strands x {args.segments} segments = {particles} particles on {device} "
          f"({wp.get_device(device).name})")
    print(f"  implicit build (groom, add_strands, finalize, implicit stable-step check: "
          f"{'unrestricted' if not np.isfinite(stable) else f'{stable * 1e6:.1f} us'}): {built:.2f} s")
    if not args.no_sag_free:
        t0 = time.perf_counter()
        report = ws.sag_free(scene.sim, rtol=scene.SAG_FREE_RTOL)  # as the scene solves it
        wp.synchronize_device(device)
        solve = time.perf_counter() - t0
        how = "the direct per-strand solve" if report.iterations == 0 else f"{report.iterations} CGLS iterations"
        print(f"  sag_free (rtol {scene.SAG_FREE_RTOL:g} for CGLS): {solve:.2f} s, {report.rounds} rounds, {how}, "
              f"residual {100 * report.residual_relative:.3g} % of the largest load")
    frames = max(1, args.steps // 4)
    graph = device.is_cuda
    eager, n_i = measure_frames(scene, "implicit, eager frames", frames, device, False)
    per_frame_i = eager
    if graph:
        per_frame_i, _ = measure_frames(scene, "implicit, one CUDA graph a frame", frames, device, True)
        print(f"  graph / eager frame time: {per_frame_i / eager:.3f}")
    per_i = per_frame_i / n_i
    print(f"  implicit: {1.0 / per_frame_i:.1f} frames/s ({n_i} steps per 1/60 s frame, {per_frame_i * 1e3:.2f} ms "
          "per frame)")
    if not args.no_explicit:
        del scene
        scene, built = build(args, device, "explicit")
        print(f"  explicit build (with the stable-step power iteration: {scene.stable_dt * 1e6:.1f} us): "
              f"{built:.2f} s")
        per_e, n_e = measure(scene, "explicit (semi-implicit Euler)", args.explicit_steps or args.steps, device)
        per_frame_e = per_e * n_e
        print(f"  explicit: {1.0 / per_frame_e:.2f} frames/s ({n_e} steps per 1/60 s frame)")
        print(f"  ratio (implicit / explicit frames/s): {per_frame_e / per_frame_i:.1f}; per step "
              f"{per_i / per_e:.1f}x the explicit step's time")
        if args.reference:
            h = (1.0 / 60.0) / n_e
            ref = reference_simulator(scene, device)
            ref.step(h)
            per_ref = time_per_call(lambda: ref.step(h), args.explicit_steps or args.steps, device)
            print(f"  plain springs:   {1.0 / per_ref:10.1f} steps/s  ({per_ref * 1e3:.3f} ms/step, "
                  f"{ref.model.spring_count} springs); explicit strands / plain springs time: {per_e / per_ref:.2f}")


if __name__ == "__main__":
    sys.exit(run_script(main))
