"""Cost of particle-pair collisions in a batched wall sweep: their share of a frame.

``collide_particle_pairs`` sums each particle's contacts in ascending partner index (one grid
query per contact, plus one) so that identical worlds give identical bits wherever their copy of
space sits in the neighbour grid (issue 28). This measures, in one process on one device, a
frame of N wall worlds (ball, bricks, breakable mortar) with the scene's colliders against the
same frame with the particle-pair stage removed, and the pair stage alone (count + collide
launches through ``ParticleCollisions.apply``): the ratio says what the ordered sum costs per
frame, with the contacts the scene really makes.

    python benchmarks/bench_particle_pairs.py --device cuda:0 --worlds 256
    python benchmarks/bench_particle_pairs.py --device cpu --worlds 4 --frames 3   # check
"""

import argparse
import sys
import time

import numpy as np
import warp as wp

from warpsim.cli_common import DefaultsHelpFormatter, run_script
from warpsim.verbosity import set_warp_verbosity


def _frame_time(batch, frame_dt, substeps, frames, device):
    wp.synchronize_device(device)
    t0 = time.perf_counter()
    for _ in range(frames):
        batch.advance(frame_dt, substeps)
    wp.synchronize_device(device)
    return (time.perf_counter() - t0) / frames


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=DefaultsHelpFormatter)
    p.add_argument("--device", default="cuda:0")
    p.add_argument("--worlds", type=int, default=256)
    p.add_argument("--frames", type=int, default=20, help="timed frames (after 6 warm-up frames: the ball hits)")
    args = p.parse_args()
    set_warp_verbosity()  # quiet unless $WARPSIM_VERBOSE=1 (Warp 1.19 ignores config.quiet)
    from warpsim.bodies.colliders import ParticleCollisions
    from warpsim.scenes import get_scene
    from warpsim.sweeps.sweep import frame_timing, make_batch

    cls = get_scene("wall")
    params = cls.resolve_params({"ball_speed": 20.0})
    worlds = [dict(params) for _ in range(args.worlds)]
    _, substeps, frame_dt = frame_timing(cls, params)
    results = {}
    for label in ("with pairs", "without pairs"):
        batch = make_batch(cls, worlds, device=args.device)
        if label == "without pairs":
            batch.sim.colliders = [c for c in batch.sim.colliders if not isinstance(c, ParticleCollisions)]
        steps = batch.batch_scene.frame_steps(frame_dt, substeps)
        for _ in range(6):  # warm-up, modules loaded, the ball reaches the wall
            batch.advance(frame_dt, substeps)
        results[label] = _frame_time(batch, frame_dt, substeps, args.frames, args.device)
        if label == "with pairs":
            x, _ = batch.world_slices()
            same = all(np.array_equal(x[0], x[w]) for w in range(1, batch.world_count))
            pairs = next(c for c in batch.sim.colliders if isinstance(c, ParticleCollisions))
            st = batch.sim.state
            wp.synchronize_device(args.device)
            t0 = time.perf_counter()
            for _ in range(args.frames * steps):
                pairs.apply(batch.model, st, st.positions, frame_dt / steps)
            wp.synchronize_device(args.device)
            results["pair stage per frame"] = (time.perf_counter() - t0) / args.frames
    print(f"wall x {args.worlds} worlds on {args.device}, {steps} steps per frame, {args.frames} frames timed")
    for label, seconds in results.items():
        print(f"  {label:<22} {seconds * 1e3:9.3f} ms/frame")
    print(f"  pairs' share of a frame: {results['pair stage per frame'] / results['with pairs']:.2f}; frame with / "
          f"without pairs: {results['with pairs'] / results['without pairs']:.2f}")
    print(f"  identical worlds identical after {6 + args.frames} frames: {same}")


if __name__ == "__main__":
    sys.exit(run_script(main))
