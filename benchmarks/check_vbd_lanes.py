"""VBD's colour solve with several lanes a particle on a device, as ``tests/test_vbd.py`` checks it on the CPU (where a
block's lanes run as Warp's fibers): the test's two tori dropped on each other with self contact, 12 frames of 4
steps, with each count of lanes (``ws.VBD``'s ``lanes``), every run's positions and velocities against a thread a
particle's (within rounding: 1e-5 m, 1e-4 m/s, as the test) and each run twice (the same bits).

    python benchmarks/check_vbd_lanes.py --device cuda:0
"""

import argparse
import os
import sys

import numpy as np
import warp as wp

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests"))
import test_vbd  # noqa: E402 (the tests' scene)

LANES = (1, 4, 32, 64)


def run(lanes):
    sim, _, _ = test_vbd.two_tori(gap=0.004)
    sim.integrator.lanes = lanes
    for _ in range(12):
        sim.frame(1.0 / 60.0, 4)
    return sim.state.positions.numpy(), sim.state.velocities.numpy()


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cuda:0")
    args = parser.parse_args()
    wp.config.quiet = True
    test_vbd.DEVICE = args.device
    x1, v1 = run(1)
    failed = 0
    for lanes in LANES[1:]:
        (x, v), (xb, vb) = run(lanes), run(lanes)
        dx, dv = np.abs(x - x1).max(), np.abs(v - v1).max()
        repeat = np.array_equal(x, xb) and np.array_equal(v, vb)
        ok = repeat and dx < 1.0e-5 and dv < 1.0e-4
        failed += not ok
        print(f"lanes {lanes:3d}: max |dx| {dx:.3g} m, max |dv| {dv:.3g} m/s against a thread a particle; "
              f"a second run {'the same bits' if repeat else 'DIFFERS'}: {'ok' if ok else 'FAIL'}")
    sys.exit(1 if failed else 0)


if __name__ == "__main__":
    main()
