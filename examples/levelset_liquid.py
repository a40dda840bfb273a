"""Level-set liquid: water sloshing in a tank, its surface tracked by a particle level set.

Shows the liquid API: a ``MacGrid`` tank, a ``LevelSetLiquid`` (signed distance advected by the
velocity and re-distanced, marker particles correcting it, gravity, ghost-fluid pressure
projection with ``warp.optim.linear.cg``), the surface meshed every frame with marching cubes and
streamed to USD, and the liquid volume printed per frame (it should stay put).

    python examples/levelset_liquid.py --frames 60 --resolution 32 --out usd_out/levelset_liquid.usda
"""

import argparse
import math
import sys

import warp as wp

from warpsim.cli_common import DefaultsHelpFormatter, device_arg, run_script
from warpsim.grid_fluids.levelset_liquid import LevelSetLiquid
from warpsim.grid_fluids.mac_grid import MacGrid
from warpsim.meshing.marching_cubes import MarchingCubes
from warpsim.usd.writer import UsdCacheWriter
from warpsim.verbosity import set_warp_verbosity


class Example:
    def __init__(self, resolution=24, particle_level_set=True, device=None):
        n = resolution
        dx = 1.0 / n
        self.grid = MacGrid((n, max(4, round(0.6 / dx)), max(4, round(0.4 / dx))), dx, device=device)
        self.liquid = LevelSetLiquid(self.grid, lambda x: x[..., 1] - (0.3 + 0.3 * (x[..., 0] - 0.5)),
                                     particle_level_set=particle_level_set)
        g = self.grid
        self.mesher = MarchingCubes(g.shape, g.dx, tuple(o + 0.5 * g.dx for o in g.origin), device=g.device,
                                    close_boundary=True)
        self.volume0 = self.liquid.volume()

    def step(self, frame_dt, cfl=1.0):
        """One frame in as many sub-steps as the CFL number asks."""
        n = max(1, math.ceil(self.liquid.max_speed() * frame_dt / (cfl * self.grid.dx)))
        for _ in range(n):
            self.liquid.step(frame_dt / n)
        return n

    def declare(self, writer):
        writer.add_mesh("surface", topology_changes=True, velocities=False, color=(0.15, 0.45, 0.9))
        writer.add_box("tank_floor", (0.0, -0.02, 0.0), (1.0, 0.0, self.grid.upper[2]))

    def write(self, writer, frame):
        writer.write_frame(frame, {"surface": self.mesher.mesh(self.liquid.phi).usd_frame()})


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=DefaultsHelpFormatter)
    parser.add_argument("--device", default=None)
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--fps", type=float, default=30.0)
    parser.add_argument("--resolution", type=int, default=24, help="cells along the 1 m tank")
    parser.add_argument("--no-particles", action="store_true", help="plain level set (no marker particles)")
    parser.add_argument("--out", default="usd_out/levelset_liquid.usda")
    parser.add_argument("--verbose", action="store_true", help="show Warp's banner and module-load lines")
    args = parser.parse_args(argv)
    set_warp_verbosity(args.verbose)
    args.device = device_arg(args.device)  # one line naming the devices there are
    with wp.ScopedDevice(args.device):
        example = Example(args.resolution, particle_level_set=not args.no_particles)
        with UsdCacheWriter(args.out, fps=args.fps) as writer:
            example.declare(writer)
            example.write(writer, 0)
            for frame in range(1, args.frames + 1):
                substeps = example.step(1.0 / args.fps)
                example.write(writer, frame)
                change = example.liquid.volume() / example.volume0 - 1.0
                print(f"frame {frame:4d}  substeps {substeps:2d}  volume change {100 * change:+6.2f} %  "
                      f"CG iterations {example.liquid.pressure.last_iterations}")
    print(f"open: {args.out}")


if __name__ == "__main__":
    sys.exit(run_script(main))
