"""Energy drift of the five integrators on the angle-form pendulum q'' = -(g/l) sin q.

The same pendulum (l = 1 m, released at rest from q0) is stepped by explicit Euler, semi-implicit
Euler, implicit Euler, RK2 (midpoint) and RK4 at one time step. The table shows total energy
relative to the start: explicit Euler gains energy, implicit Euler loses it, semi-implicit Euler
oscillates around the true value (bounded), RK2 drifts slowly and RK4 holds it closely.

    python examples/pendulum_integrators.py --steps 1000 --dt 0.01 --angle 1.0

The figure (E/E0 against time, one line per integrator) goes to ``--figure`` (matplotlib, the
``plot`` extra; ``--figure ''`` skips it).
"""

import argparse
import sys

import warpsim as ws
from warpsim.cli_common import DefaultsHelpFormatter, device_arg, run_script
from warpsim.verbosity import set_warp_verbosity


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=DefaultsHelpFormatter)
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--dt", type=float, default=0.01)
    parser.add_argument("--angle", type=float, default=1.0, help="release angle [rad]")
    parser.add_argument("--rows", type=int, default=10, help="table rows to print")
    parser.add_argument("--device", default=None)
    parser.add_argument("--figure", default="usd_out/pendulum_integrators.png", help="energy drift figure ('' for none)")
    parser.add_argument("--verbose", action="store_true", help="show Warp's banner and module-load lines")
    args = parser.parse_args(argv)
    set_warp_verbosity(args.verbose)
    args.device = device_arg(args.device)  # one line naming the devices there are
    if args.figure:  # matplotlib is the optional "plot" extra: say so before simulating
        from warpsim.extras import MissingExtraError, require_extra

        try:
            require_extra("plot", "--figure")
        except MissingExtraError as exc:
            parser.error(f"{exc} (or --figure '' for no figure)")
    names = list(ws.INTEGRATORS)
    runs = {n: ws.Pendulum(args.angle, integrator=n, device=args.device).run(args.steps, args.dt) for n in names}
    e0 = runs[names[0]]["total"][0, 0]
    print(f"E(t) / E(0) for q0 = {args.angle} rad, dt = {args.dt} s   "
          f"(exact period {ws.exact_period(args.angle):.4f} s)")
    print(f"{'t [s]':>8} " + " ".join(f"{n:>20}" for n in names))
    stride = max(1, args.steps // args.rows)
    for k in range(0, args.steps + 1, stride):
        t = runs[names[0]]["time"][k]
        print(f"{t:8.3f} " + " ".join(f"{runs[n]['total'][k, 0] / e0:20.6f}" for n in names))
    if args.figure:
        energy_figure(runs, args, args.figure)
        print(f"wrote {args.figure}")


def energy_figure(runs, args, path):
    """E(t)/E(0) of every integrator on one axes (log scale when the drift spans decades)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from warpsim.render.plot import save_figure

    fig, ax = plt.subplots(figsize=(7, 4))
    for name, run in runs.items():
        ax.plot(run["time"], run["total"][:, 0] / run["total"][0, 0], label=name)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("E(t) / E(0)")
    ax.set_title(f"pendulum energy drift, q0 = {args.angle} rad, dt = {args.dt} s")
    save_figure(fig, path)


if __name__ == "__main__":
    sys.exit(run_script(main))
