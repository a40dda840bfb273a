"""Smoke plume: Eulerian smoke on a MAC grid rising around a sphere.

Shows the grid-fluid API step by step: a ``MacGrid`` with an open top and a solid sphere, a
``Smoke`` solver (MacCormack advection, buoyancy from density and temperature, vorticity
confinement, pressure projection with ``warp.optim.linear.cg``), and a USD cache holding the smoke
as points with a ``density`` primvar plus a marching-cubes iso-surface of the density.

    python examples/smoke.py --frames 48 --resolution 32 --out usd_out/smoke.usda
"""

import argparse
import math
import sys

import numpy as np
import warp as wp

from warpsim.cli_common import DefaultsHelpFormatter, device_arg, run_script
from warpsim.grid_fluids.mac_grid import MacGrid
from warpsim.grid_fluids.smoke import Smoke
from warpsim.meshing.marching_cubes import MarchingCubes
from warpsim.usd.writer import UsdCacheWriter
from warpsim.verbosity import set_warp_verbosity


class Example:
    def __init__(self, resolution=24, device=None):
        n = resolution
        self.grid = MacGrid((n, 3 * n // 2, n), 1.0 / n, origin=(-0.5, 0.0, -0.5), open_sides=("+y",), device=device)
        self.sphere = ((0.0, 0.6, 0.0), 0.15)
        self.grid.add_sphere(*self.sphere)
        self.smoke = Smoke(self.grid, temperature_buoyancy=4.0, density_buoyancy=0.5, vorticity=2.0)
        self.smoke.add_source((-0.12, 0.05, -0.12), (0.12, 0.05 + max(0.1, 1.5 / n), 0.12), density=1.0,
                              temperature=1.0)
        g = self.grid
        self.mesher = MarchingCubes(g.shape, g.dx, tuple(o + 0.5 * g.dx for o in g.origin), device=g.device,
                                    close_boundary=True, inside="above")
        self.centres = g.positions("center").reshape(-1, 3).astype(np.float32)

    def step(self, frame_dt, cfl=1.0):
        """One frame in as many sub-steps as the CFL number asks."""
        speed = max(float(np.abs(f.numpy()).max()) for f in self.grid.faces)
        n = max(1, math.ceil(speed * frame_dt / (cfl * self.grid.dx)))
        for _ in range(n):
            self.smoke.step(frame_dt / n)
        return n

    def declare(self, writer):
        writer.add_points("smoke", count_changes=True, radius=0.5 * self.grid.dx, velocities=False,
                          color=(0.75, 0.75, 0.8))
        writer.add_primvar("smoke", "density", "float[]", "vertex")
        writer.add_mesh("smoke_surface", topology_changes=True, velocities=False, color=(0.75, 0.75, 0.8))
        writer.add_sphere("obstacle", *self.sphere, color=(0.8, 0.4, 0.2))

    def write(self, writer, frame):
        rho = self.smoke.density.numpy().reshape(-1)
        keep = np.flatnonzero(rho > 0.02)
        writer.write_frame(frame, {
            "smoke": {"points": self.centres[keep], "ids": keep.astype(np.int32), "density": rho[keep]},
            "smoke_surface": self.mesher.mesh(self.smoke.density, 0.1).usd_frame(),
        })


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=DefaultsHelpFormatter)
    parser.add_argument("--device", default=None)
    parser.add_argument("--frames", type=int, default=48)
    parser.add_argument("--fps", type=float, default=24.0)
    parser.add_argument("--resolution", type=int, default=24, help="cells across the 1 m wide domain")
    parser.add_argument("--out", default="usd_out/smoke.usda")
    parser.add_argument("--verbose", action="store_true", help="show Warp's banner and module-load lines")
    args = parser.parse_args(argv)
    set_warp_verbosity(args.verbose)
    args.device = device_arg(args.device)  # one line naming the devices there are
    with wp.ScopedDevice(args.device):
        example = Example(args.resolution)
        with UsdCacheWriter(args.out, fps=args.fps) as writer:
            example.declare(writer)
            example.write(writer, 0)
            for frame in range(1, args.frames + 1):
                substeps = example.step(1.0 / args.fps)
                example.write(writer, frame)
                y = example.smoke.density_centroid()[1]
                print(f"frame {frame:4d}  substeps {substeps:2d}  smoke centroid height {y:6.3f} m  "
                      f"CG iterations {example.smoke.pressure.last_iterations}")
    print(f"open: {args.out}")


if __name__ == "__main__":
    sys.exit(run_script(main))
