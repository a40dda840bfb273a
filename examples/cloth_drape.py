"""A square sheet drapes over a sphere and settles on the floor, written to a USD cache.

Shows the cloth API end to end: ``add_cloth_grid`` (structural, shear and bend springs, mass from
an area density), colliders with friction and a thickness offset (a sphere and the floor), the
``ClothSimulator`` with implicit Euler (one Baraff-Witkin step per frame, each frame replayed
as a captured graph) and the cloth as a USD mesh with fixed topology and per-frame points and
velocities. It prints, every 10 frames, the lowest point, the closest approach to the sphere
surface (never below the thickness) and the CG iterations.

    python examples/cloth_drape.py --frames 120 --resolution 40 --out usd_out/cloth_drape.usdc
"""

import argparse
import sys

import numpy as np

import warpsim as ws
from warpsim.bodies.colliders import Sphere
from warpsim.cli_common import DefaultsHelpFormatter, device_arg, run_script
from warpsim.cloth.builder import add_cloth_grid
from warpsim.cloth.solver import ClothImplicitEuler, ClothSimulator
from warpsim.usd.writer import UsdCacheWriter
from warpsim.verbosity import set_warp_verbosity


class Example:
    def __init__(self, resolution=32, size=1.6, radius=0.35, thickness=0.01, friction=0.4, device=None):
        builder = ws.ModelBuilder()
        self.cloth = add_cloth_grid(builder, resolution, size, (0.0, 1.0, 0.0), centered=True, density=0.3,
                                    structural=(400.0, 0.02), shear=(100.0, 0.02), bend=(20.0, 0.005))
        self.center, self.radius, self.thickness = np.array([0.0, radius, 0.0]), radius, thickness
        colliders = [Sphere(tuple(self.center), radius, restitution=0.0, friction=friction, thickness=thickness),
                     ws.Plane((0.0, 1.0, 0.0), 0.0, restitution=0.0, friction=friction, mode="project")]
        self.sim = ClothSimulator(builder.finalize(device), ClothImplicitEuler(cg_tol=1.0e-4), colliders=colliders)

    def declare(self, writer):
        writer.add_mesh("cloth", self.cloth.face_vertex_counts, self.cloth.face_vertex_indices, double_sided=True,
                        color=(0.8, 0.3, 0.2))
        writer.add_sphere("sphere", tuple(self.center), self.radius)
        writer.add_plane("floor", size=3.0)

    def frame_data(self):
        st = self.sim.state
        return {"cloth": {"points": st.positions, "velocities": st.velocities}}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=DefaultsHelpFormatter)
    parser.add_argument("--frames", type=int, default=120)
    parser.add_argument("--resolution", type=int, default=32, help="cells per side")
    parser.add_argument("--friction", type=float, default=0.4)
    parser.add_argument("--device", default=None)
    parser.add_argument("--out", default="usd_out/cloth_drape.usdc")
    parser.add_argument("--verbose", action="store_true", help="show Warp's banner and module-load lines")
    args = parser.parse_args(argv)
    set_warp_verbosity(args.verbose)
    args.device = device_arg(args.device)  # one line naming the devices there are
    example = Example(args.resolution, friction=args.friction, device=args.device)
    writer = UsdCacheWriter(args.out, fps=60.0)
    example.declare(writer)
    writer.write_frame(0, example.frame_data())
    print(f"{'frame':>5} {'lowest y [m]':>12} {'to sphere [m]':>13} {'CG its':>6}")
    for frame in range(1, args.frames + 1):
        example.sim.frame(1.0 / 60.0, 1)
        writer.write_frame(frame, example.frame_data())
        if frame % 10 == 0 or frame == args.frames:
            x = example.sim.state.positions.numpy()
            gap = (np.linalg.norm(x - example.center, axis=1) - example.radius).min()
            print(f"{frame:5d} {x[:, 1].min():12.4f} {gap:13.4f} {example.sim.integrator.last_cg_iterations:6d}")
    writer.close()
    print(f"wrote {args.out}")


if __name__ == "__main__":
    sys.exit(run_script(main))
