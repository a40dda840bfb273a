"""The dam-break surge front against Martin and Moyce (1952), n^2 = 2, by method and resolution:
PBF and DFSPH particles (warpsim.particle_fluids, a slab 3 particles thick, a = 0.2 m) and the FLIP
grid liquid (warpsim.grid_fluids.flip, 2D, a = 0.1 m; the runner of tests/test_dam_break_crosscheck.py).

For every run, over the tabulated points 0.8 <= T <= 3 (martin_moyce.WINDOW), with the front of
the water on the floor (martin_moyce.floor_front): the worst deviation Z_sim / Z_exp - 1 as run,
the worst with the experiment's release delay (T + martin_moyce.RELEASE_DELAY), the time shift that
fits best and its worst deviation; the surge's speed dZ/dT over 1.4 <= T <= 3 against the table's
(a start delay leaves it unchanged); steps, pressure iterations per step, particles, seconds. With
``--causes``, one switch at a time against each particle method's default at a / spacing = 20
(wall friction, boundary treatment, no-slip walls (all or the floor only), viscosity, solve
tolerance, step size, kernel, slab depth, front measure). Prints Markdown tables (benchmarks/RESULTS.md).

    python benchmarks/dam_break_convergence.py                        # 10, 20, 40 per method (~7 min, 2 cores)
    python benchmarks/dam_break_convergence.py --causes --res 20 --methods pbf dfsph
    python benchmarks/dam_break_convergence.py --gate-speeds 0.5 1 2 4 --res 20   # a gate lifted off the column
    python benchmarks/dam_break_convergence.py --causes --res 20 --methods dfsph --only "floor only"
    python benchmarks/dam_break_convergence.py --methods pbf dfsph --front depth   # film < 0.1 a uncounted
"""

import argparse
import sys
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from warpsim.cli_common import DefaultsHelpFormatter, run_script
from warpsim.particle_fluids import martin_moyce as MM
from warpsim.verbosity import set_warp_verbosity

CAUSES = {
    "pbf": [("default (wall friction 5 /s)", {}), ("free-slip walls (friction 0)", {"wall_friction": 0.0}),
            ("wall friction 20 /s", {"wall_friction": 20.0}), ("XSPH 0", {"viscosity": 0.0}),
            ("XSPH 0.1", {"viscosity": 0.1}), ("converged solve (0.02 %, 200 it.)",
                                                {"density_tolerance": 0.0002, "iterations": 200}),
            ("cfl 0.1", {"cfl": 0.1}), ("Wendland kernel", {"kernel": "wendland"}), ("slab 6 layers", {"layers": 6})],
    "dfsph": [("default (boundary particles, free slip)", {}), ("signed-distance walls", {"boundary": "volume"}),
              ("wall friction 5 /s", {"wall_friction": 5.0}), ("no-slip boundary particles (nu_b 0.01)",
                                                                {"boundary_viscosity": 0.01}),
              *[(f"no-slip floor only (nu_b {nu:g})", {"boundary_viscosity": nu, "no_slip": "floor"})
                for nu in (1e-5, 1e-4, 1e-3, 1e-2)],
              ("SPH viscosity nu 0.001", {"kinematic_viscosity": 0.001}),
              ("SPH viscosity nu 0.01", {"kinematic_viscosity": 0.01}), ("XSPH 0", {"viscosity": 0.0}),
              ("converged solve (0.01 %)", {"density_tolerance": 0.0001}), ("cfl 0.1", {"cfl": 0.1}),
              ("SPlisHSPlasH's mass (0.8 of the lattice's: starts at 0.8 rho0)", {"mass_fraction": 0.8}),
              ("SPlisHSPlasH's block (one spacing inside, one layer fewer)", {"inset": True}),
              ("SPlisHSPlasH's mass and block", {"mass_fraction": 0.8, "inset": True}),
              ("SPlisHSPlasH's mass, SPH viscosity nu 0.01", {"mass_fraction": 0.8, "kinematic_viscosity": 0.01})],
}


def scores(T, Z):
    """(raw worst, worst with the release delay, (best shift, its worst)) over the window."""
    return MM.worst(T, Z)[1], MM.worst(np.asarray(T) + MM.RELEASE_DELAY, Z)[1], MM.best_shift(T, Z)


def row(name, T, Z, extra):
    raw, delayed, (shift, err) = scores(T, Z)
    speed, measured = MM.surge_speed(T, Z)
    return (f"| {name} | {100 * raw:+.1f} % | {100 * delayed:+.1f} % | {shift:.2f} / {100 * err:.1f} % | "
            f"{100 * (speed / measured - 1):+.1f} % | " + " | ".join(extra) + " |")


HEADER = ("| run | worst Z/Z_exp - 1, raw | with T + {d} | best shift dT / worst | surge speed dZ/dT, 1.4 <= T <= 3 | "
          "steps | iterations/step | particles | seconds |\n| --- | --- | --- | --- | --- | --- | --- | --- | --- |")


def particle_row(name, r, key="Z"):
    return row(name, r["T"], r[key], [str(r["steps"]), f"{r['iterations']:.1f}", str(r["particles"]),
                                      f"{r['seconds']:.1f}"])


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=DefaultsHelpFormatter)
    ap.add_argument("--methods", nargs="+", default=["pbf", "dfsph", "flip"], choices=["pbf", "dfsph", "flip"])
    ap.add_argument("--res", type=int, nargs="+", default=[10, 20, 40], help="particles (cells) per column width a")
    ap.add_argument("--causes", action="store_true", help="one switch at a time at the first --res")
    ap.add_argument("--only", default="", help="with --causes: only the switches whose label contains this")
    ap.add_argument("--gate-speeds", type=float, nargs="*", default=[],
                    help="DFSPH at the first --res released by a gate lifted at these speeds [m/s] instead")
    ap.add_argument("--device", default="cpu", help="particle methods' device (FLIP runs on the CPU)")
    ap.add_argument("--front", default="floor", choices=["floor", "depth"],
                    help="particle methods' front: the water on the floor (martin_moyce.floor_front) or the "
                         "water at least martin_moyce.FILM_DEPTH a deep (depth_front: a thinner film is not)")
    args = ap.parse_args()
    set_warp_verbosity()
    key = {"floor": "Z", "depth": "Z_depth"}[args.front]
    tag = "" if args.front == "floor" else f", front {MM.FILM_DEPTH:g} a deep"
    wp.init()
    print(HEADER.format(d=MM.RELEASE_DELAY))
    if args.gate_speeds:
        for speed in args.gate_speeds:
            r = MM.run_dam_break("dfsph", res=args.res[0], gate_speed=speed, device=args.device)
            label = f"DFSPH a/{args.res[0]}: gate lifted at {speed:g} m/s{tag}"
            print(particle_row(label, r, key), flush=True)
        return 0
    if args.causes:
        res = args.res[0]
        for method in [m for m in args.methods if m in CAUSES]:
            for label, settings in CAUSES[method]:
                if args.only not in label:
                    continue
                settings = dict(settings)
                layers = settings.pop("layers", 3)
                r = MM.run_dam_break(method, res=res, layers=layers, device=args.device, **settings)
                print(particle_row(f"{method.upper()} a/{res}: {label}{tag}", r, key), flush=True)
                if not settings and layers == 3 and not tag:
                    print(particle_row(f"{method.upper()} a/{res}: front = furthest particle + s/2", r, "Z_tip"),
                          flush=True)
        return 0
    for method in args.methods:
        for res in args.res:
            if method == "flip":
                from test_dam_break_crosscheck import run_flip_dam_break

                r = run_flip_dam_break(res=res)
                extra = [str(r["steps"]), "-", str(r["particles"]), f"{r['seconds']:.1f}"]
                print(row(f"FLIP a/dx = {res} (2D, floor front)", r["T"], r["Z_floor"], extra), flush=True)
                print(row(f"FLIP a/dx = {res} (furthest particle)", r["T"], r["Z"], extra), flush=True)
            else:
                r = MM.run_dam_break(method, res=res, device=args.device)
                print(particle_row(f"{method.upper()} a/spacing = {res}{tag}", r, key), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(run_script(main))
