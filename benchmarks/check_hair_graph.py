"""On a CUDA device, the hair scene's frames replayed from one captured CUDA graph equal eager
frames bit for bit (the head turning and nodding, so its poses change every step). CUDA graphs
need a GPU, so this check lives here rather than in the CPU test suite; the CPU suite checks what
a graph needs (tests/test_hair_frame.py: device poses equal launch-parameter poses bit for bit, a
frame allocates nothing).

    python benchmarks/check_hair_graph.py --device cuda:0 --frames 12

Exit status 0 when the runs are identical, 1 otherwise.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from warpsim.cli_common import DefaultsHelpFormatter, run_script
from warpsim.verbosity import set_warp_verbosity

set_warp_verbosity()  # quiet unless $WARPSIM_VERBOSE=1

PARAMS = {"strands": 6, "segments": 8, "still": 0.0, "motion": "turn_nod", "sag_free": False}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=DefaultsHelpFormatter)
    parser.add_argument("--device", default="cuda:0", help="a CUDA device")
    parser.add_argument("--frames", type=int, default=12, help="frames of 1/60 s to compare")
    args = parser.parse_args(argv)
    import warp as wp

    from warpsim.scenes import get_scene

    if not wp.get_device(args.device).is_cuda:
        raise ValueError(f"--device {args.device!r} is not a CUDA device: CUDA graphs need one (e.g. cuda:0)")

    graphed = get_scene("hair")(PARAMS, device=args.device)
    eager = get_scene("hair")({**PARAMS, "graph": False}, device=args.device)
    for _ in range(args.frames):
        graphed.advance(1.0 / 60.0, 1)
        eager.advance(1.0 / 60.0, 1)
    captured = graphed.frame.use_graph and not eager.frame.use_graph
    same = all(np.array_equal(getattr(graphed.sim.state, name).numpy(), getattr(eager.sim.state, name).numpy())
               for name in ("positions", "velocities"))
    print(f"hair on {args.device}, {args.frames} frames: graph frames {'captured' if captured else 'NOT captured'}, "
          f"{'identical' if same else 'DIFFERENT'} to eager frames")
    return 0 if (captured and same) else 1


if __name__ == "__main__":
    sys.exit(run_script(main))
