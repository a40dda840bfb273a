"""Dam break with a particle liquid (PBF or divergence-free SPH): a water column collapses in a box.

A column a wide and 2a tall (Martin and Moyce's n^2 = 2) stands in the -x corner of a box. Each
frame the script advances the fluid in CFL-limited sub-steps, prints the surge front z/a (the
leading edge of the water on the floor, as the experiment measured it) against the dimensionless
time T = t sqrt(2 g / a) beside Martin and Moyce's (1952) measurements, and streams the particles
(UsdGeom.Points with ids) and the marching-cubes liquid surface (a Mesh whose topology changes
every frame) into a USD cache. At the end it prints the worst deviation from the table over
0.8 <= T <= 3, as run and with the experiment's release delay (``martin_moyce.RELEASE_DELAY``),
and the throughput in particle-steps per second.

    python examples/dam_break.py --out usd_out/dam_break.usda              # PBF, up to T = 3.1
    python examples/dam_break.py --method dfsph --spacing 0.01             # divergence-free SPH, finer
    python examples/dam_break.py --method dfsph --spacing 0.002 --depth 0.1 --device cuda:0 --no-surface --out ''

The surge front against Martin and Moyce is drawn to ``--figure`` (matplotlib, the ``plot``
extra; ``--figure ''`` skips it).
"""

import argparse
import contextlib
import math
import sys
import time

import numpy as np

from warpsim.cli_common import DefaultsHelpFormatter, device_arg, run_script
from warpsim.particle_fluids import martin_moyce as MM
from warpsim.particle_fluids.pbf import METHODS, ParticleFluid, fluid_block
from warpsim.particle_fluids.surface import FluidSurface
from warpsim.usd.writer import UsdCacheWriter
from warpsim.verbosity import set_warp_verbosity

G = MM.G
T_END = 3.1  # the last frame reaches this T: every tabulated point of the window 0.8 <= T <= 3 is covered


class Example:
    """The column [0, a] x [0, 2a] x [0, depth] in the box [0, 5a] x [0, 2.5a] x [0, depth]."""

    def __init__(self, a=0.2, spacing=0.02, depth=0.06, iterations=40, surface=True, method="pbf",
                 device=None, floor_viscosity=0.0):
        self.a = a
        self.layers = max(1, int(round(depth / spacing)))
        # DFSPH: a no-slip floor (boundary viscosity on the floor's particles only), other walls free slip
        floor = {"boundary_viscosity": floor_viscosity, "no_slip": "floor"} if floor_viscosity > 0.0 else {}
        self.fluid = ParticleFluid(fluid_block((0, 0, 0), (a, 2 * a, depth), spacing), spacing=spacing,
                                   domain=((0, 0, 0), (5 * a, 2.5 * a, depth)), iterations=iterations,
                                   viscosity=0.01, method=method, device=device, **floor)
        self.surface = FluidSurface(self.fluid, cell=0.5 * spacing) if surface else None

    def step(self, frame_dt):
        """One frame; returns the number of CFL sub-steps it took."""
        return self.fluid.advance(frame_dt)

    def fronts(self):
        """Surge fronts z/a from one read of the positions: the far edge of the water on the floor
        (:func:`martin_moyce.floor_front`) and of the water at least ``martin_moyce.FILM_DEPTH`` a deep
        (:func:`martin_moyce.depth_front`: a film on the floor thinner than that, whose thickness shrinks with
        the spacing, does not move it)."""
        x = self.fluid.positions.numpy()
        s = self.fluid.spacing
        return (MM.floor_front(x, s, layers=self.layers) / self.a,
                MM.depth_front(x, s, MM.FILM_DEPTH * self.a, layers=self.layers) / self.a)

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
    parser.add_argument("--frames", type=int, default=None, help=f"frames to run (default: up to T = {T_END})")
    parser.add_argument("--fps", type=float, default=60.0)
    parser.add_argument("--a", type=float, default=0.2, help="column width a [m] (height 2a)")
    parser.add_argument("--spacing", type=float, default=0.02, help="particle spacing [m]")
    parser.add_argument("--depth", type=float, default=0.06, help="slab thickness in z [m]")
    parser.add_argument("--method", default="pbf", choices=METHODS,
                        help="pbf: position-based fluids; dfsph: divergence-free SPH with boundary particles")
    parser.add_argument("--iterations", type=int, default=40, help="most pressure iterations per step (each solve)")
    parser.add_argument("--floor-viscosity", type=float, default=0.0,
                        help="DFSPH: nu_b [m^2/s] of a no-slip floor (side and slab walls stay free slip; "
                             "0: free slip)")
    parser.add_argument("--no-surface", action="store_true", help="skip the marching-cubes surface")
    parser.add_argument("--device", default=None)
    parser.add_argument("--out", default="usd_out/dam_break.usda", help="USD cache ('' for none)")
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
    if not args.floor_viscosity >= 0.0:
        raise ValueError(f"--floor-viscosity {args.floor_viscosity:g} must be >= 0 [m^2/s]")
    if args.frames is not None and args.frames < 1:
        raise ValueError(f"--frames {args.frames} must be >= 1")
    if args.figure:  # matplotlib is the optional "plot" extra: say so before simulating
        from warpsim.extras import MissingExtraError, require_extra

        try:
            require_extra("plot", "--figure")
        except MissingExtraError as exc:
            parser.error(f"{exc} (or --figure '' for no figure)")
    example = Example(args.a, args.spacing, args.depth, args.iterations, not args.no_surface, args.method,
                      args.device, args.floor_viscosity)
    scale = MM.time_scale(args.a, 2.0 * args.a)
    frames = args.frames or math.ceil(T_END / scale * args.fps - 1e-9)
    f = example.fluid
    print(f"{f.active_count} particles, method {args.method}; Martin & Moyce (1952) n^2 = 2")
    print(f"{'frame':>5} {'T':>6} {'z/a':>6} {'M&M z/a':>8} {'substeps':>8} {'compression':>11}")
    floor, deep_now = example.fronts()
    times, fronts, deep = [0.0], [floor], [deep_now]
    work, seconds = 0, 0.0
    with (UsdCacheWriter(args.out, fps=args.fps) if args.out else contextlib.nullcontext()) as writer:
        if writer is not None:
            example.declare(writer)
            writer.write_frame(0, example.frame_data())
        for frame in range(1, frames + 1):
            start = time.perf_counter()
            substeps = example.step(1.0 / args.fps)
            if frame > 1:  # the first frame compiles the kernels
                seconds += time.perf_counter() - start
                work += substeps * f.active_count
            if writer is not None:
                writer.write_frame(frame, example.frame_data())
            T = f.time * scale
            measured = np.interp(T, MM.N2_2_T, MM.N2_2_Z, left=np.nan, right=np.nan)
            times.append(T)
            floor, deep_now = example.fronts()
            fronts.append(floor)
            deep.append(deep_now)
            print(f"{frame:5d} {T:6.2f} {fronts[-1]:6.2f} {measured:8.2f} {substeps:8d} {f.density_error()[0]:11.2e}")
    if writer is not None:
        print(f"wrote {writer.output_path}")
    report(times, fronts)
    report(times, deep, f"the water at least {MM.FILM_DEPTH:g} a deep (a thinner film on the floor not counted)")
    if seconds > 0.0:
        print(f"throughput: {work / seconds:.4g} particle-steps/s ({f.step_count} steps, "
              f"{f.total_iterations / f.step_count:.1f} pressure iterations per step; first frame not timed)")
    if args.figure:
        front_figure(times, fronts, args, args.figure)
        print(f"wrote {args.figure}")


def report(times, fronts, front="the water on the floor"):
    """Print the worst deviation of ``front`` from Martin and Moyce over their window, raw and release-delayed."""
    lo, hi = MM.WINDOW
    if times[-1] < MM.N2_2_T[MM.N2_2_T <= hi].max():
        print(f"the run ends at T = {times[-1]:.2f}: run to T = {T_END} (the default --frames) for the deviation "
              f"over {lo} <= T <= {hi}")
        return
    t, dev = MM.worst(times, fronts)
    print(f"worst deviation from Martin & Moyce over {lo} <= T <= {hi}, {front}: {100 * dev:+.1f} % at T = {t:.2f}")
    t, dev = MM.worst(np.asarray(times) + MM.RELEASE_DELAY, fronts)
    print(f"  with the experiment's release delay (T + {MM.RELEASE_DELAY}): {100 * dev:+.1f} % at T = {t:.2f}")


def front_figure(times, fronts, args, path):
    """Surge front z/a against T = t sqrt(2 g / a): this run and Martin and Moyce's table."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from warpsim.render.plot import save_figure

    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot(times, fronts, "-", label=f"{args.method.upper()}, spacing {args.spacing} m")
    ax.plot(np.asarray(times) + MM.RELEASE_DELAY, fronts, ":", color="C0",
            label=f"the same, T + {MM.RELEASE_DELAY} (release delay)")
    ax.plot(MM.N2_2_T, MM.N2_2_Z, "o", color="C1", label="Martin & Moyce (1952), n^2 = 2")
    ax.axvspan(*MM.WINDOW, color="0.92", zorder=0)
    ax.set_xlabel("T = t sqrt(2 g / a)")
    ax.set_ylabel("front z / a")
    ax.set_title("dam break: surge front")
    ax.legend(loc="upper left", fontsize=8)
    save_figure(fig, path)


if __name__ == "__main__":
    sys.exit(run_script(main))
