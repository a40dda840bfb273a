"""Dam break with position-based fluids: a water column collapses in a box.

A column a wide and 2a tall (Martin and Moyce's n^2 = 2) stands in the -x corner of a box. Each
frame the script advances the fluid in CFL-limited sub-steps, prints the surge front z/a against
the dimensionless time T = t sqrt(2 g / a) beside Martin and Moyce's (1952) measurements, and
streams the particles (UsdGeom.Points with ids) and the marching-cubes liquid surface (a Mesh
whose topology changes every frame) into a USD cache.

    python examples/dam_break.py --frames 30 --out usd_out/dam_break.usda
    python examples/dam_break.py --spacing 0.01 --depth 0.1      # finer, a thicker slab

The surge front against Martin and Moyce is drawn to ``--figure`` (matplotlib, the ``plot``
extra; ``--figure ''`` skips it).
"""

import argparse
import math
import sys

import numpy as np

from warpsim.cli_common import DefaultsHelpFormatter, device_arg, run_script
from warpsim.particle_fluids.pbf import ParticleFluid, fluid_block
from warpsim.particle_fluids.surface import FluidSurface
from warpsim.usd.writer import UsdCacheWriter
from warpsim.verbosity import set_warp_verbosity

G = 9.81
# Martin and Moyce (1952), Phil. Trans. R. Soc. A 244, 312-324, Table 2 (n^2 = 2, a = 2.25 in)
MM_T = np.array([0.41, 0.84, 1.19, 1.43, 1.63, 1.83, 1.98, 2.20, 2.32, 2.51, 2.65, 2.83, 2.98, 3.11, 3.33])
MM_Z = np.array([1.11, 1.22, 1.44, 1.67, 1.89, 2.11, 2.33, 2.56, 2.78, 3.00, 3.22, 3.44, 3.67, 3.89, 4.11])


class Example:
    """The column [0, a] x [0, 2a] x [0, depth] in the box [0, 5a] x [0, 2.5a] x [0, depth]."""

    def __init__(self, a=0.2, spacing=0.02, depth=0.06, iterations=40, surface=True, device=None):
        self.a = a
        self.fluid = ParticleFluid(fluid_block((0, 0, 0), (a, 2 * a, depth), spacing), spacing=spacing,
                                   domain=((0, 0, 0), (5 * a, 2.5 * a, depth)), iterations=iterations,
                                   viscosity=0.01, device=device)
        self.surface = FluidSurface(self.fluid, cell=0.5 * spacing) if surface else None

    def step(self, frame_dt):
        """One frame; returns the number of CFL sub-steps it took."""
        return self.fluid.advance(frame_dt)

    def front(self):
        """Surge front z/a (the furthest particle's edge)."""
        x = self.fluid.positions.numpy()
        return (x[:, 0].max() + 0.5 * self.fluid.spacing) / self.a

    def frame_data(self):
        f = self.fluid
        data = {"particles": {"points": f.positions, "velocities": f.velocities, "ids": f.ids}}
        if self.surface is not None:
            data["surface"] = self.surface.mesh().usd_frame()
        return data

    def declare(self, writer):
        writer.add_points("particles", count_changes=True, radius=0.5 * self.fluid.spacing, color=(0.15, 0.45, 0.9))
        if self.surface is not None:
            writer.add_mesh("surface", topology_changes=True, velocities=False, color=(0.15, 0.45, 0.9))
        writer.add_plane("floor", offset=0.0, size=float(2 * self.fluid.domain[1][0]))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=DefaultsHelpFormatter)
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--fps", type=float, default=60.0)
    parser.add_argument("--a", type=float, default=0.2, help="column width a [m] (height 2a)")
    parser.add_argument("--spacing", type=float, default=0.02, help="particle spacing [m]")
    parser.add_argument("--depth", type=float, default=0.06, help="slab thickness in z [m]")
    parser.add_argument("--iterations", type=int, default=40, help="most PBF iterations per step (stops earlier at 0.2 %% mean compression)")
    parser.add_argument("--no-surface", action="store_true", help="skip the marching-cubes surface")
    parser.add_argument("--device", default=None)
    parser.add_argument("--out", default="usd_out/dam_break.usda")
    parser.add_argument("--figure", default="usd_out/dam_break_front.png", help="surge-front figure ('' for none)")
    parser.add_argument("--verbose", action="store_true", help="show Warp's banner and module-load lines")
    args = parser.parse_args(argv)
    set_warp_verbosity(args.verbose)
    args.device = device_arg(args.device)  # one line naming the devices there are
    for flag, value in (("--a", args.a), ("--spacing", args.spacing), ("--depth", args.depth)):
        if not value > 0.0:
            raise ValueError(f"{flag} {value:g} must be a positive length [m]")
    if args.depth < 2.0 * args.spacing or 2.5 * args.a < 2.0 * args.spacing:
        raise ValueError(f"--spacing {args.spacing:g} m is too coarse for --depth {args.depth:g} m and --a {args.a:g} m: "
                         f"the box needs at least 2 particle spacings on every axis; use --spacing "
                         f"{min(args.depth, 2.5 * args.a) / 2.0:g} or less, or a deeper --depth")
    if args.figure:  # matplotlib is the optional "plot" extra: say so before simulating
        from warpsim.extras import MissingExtraError, require_extra

        try:
            require_extra("plot", "--figure")
        except MissingExtraError as exc:
            parser.error(f"{exc} (or --figure '' for no figure)")
    example = Example(args.a, args.spacing, args.depth, args.iterations, not args.no_surface, args.device)
    scale = math.sqrt(2.0 * G / args.a)
    print(f"{example.fluid.active_count} particles; Martin & Moyce (1952) n^2 = 2")
    print(f"{'frame':>5} {'T':>6} {'z/a':>6} {'M&M z/a':>8} {'substeps':>8} {'compression':>11}")
    times, fronts = [], []
    with UsdCacheWriter(args.out, fps=args.fps) as writer:
        example.declare(writer)
        writer.write_frame(0, example.frame_data())
        for frame in range(1, args.frames + 1):
            substeps = example.step(1.0 / args.fps)
            writer.write_frame(frame, example.frame_data())
            T = example.fluid.time * scale
            measured = np.interp(T, MM_T, MM_Z, left=np.nan, right=np.nan)
            times.append(T)
            fronts.append(example.front())
            print(f"{frame:5d} {T:6.2f} {example.front():6.2f} {measured:8.2f} {substeps:8d} "
                  f"{example.fluid.density_error()[0]:11.2e}")
    print(f"wrote {writer.output_path}")
    if args.figure:
        front_figure(times, fronts, args, args.figure)
        print(f"wrote {args.figure}")


def front_figure(times, fronts, args, path):
    """Surge front z/a against T = t sqrt(2 g / a): this run and Martin and Moyce's table."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from warpsim.render.plot import save_figure

    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot(times, fronts, "-", label=f"PBF, spacing {args.spacing} m")
    ax.plot(MM_T, MM_Z, "o", label="Martin & Moyce (1952), n^2 = 2")
    ax.set_xlabel("T = t sqrt(2 g / a)")
    ax.set_ylabel("front z / a")
    ax.set_title("dam break: surge front")
    save_figure(fig, path)


if __name__ == "__main__":
    sys.exit(run_script(main))
