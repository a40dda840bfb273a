"""The dam-break surge front by two methods, PBF particles and an Eulerian FLIP liquid, against
Martin and Moyce (1952): resolution, wall condition and FLIP settings, with run times.

Runs the dam break of tests/test_dam_break_crosscheck.py (column a x 2a, a = 0.1 m, box 5a x 2.5a,
frames of dT = 0.05 up to T = 3.1; the run functions are imported from there) and prints

1. the front Z(T) of every run at Martin and Moyce's samples, next to the experiment;
2. per run: the lead Z / Z_exp - 1 over 1.0 < T < 1.9, the range of Z / Z_ref - 1 over every frame
   with 0.8 <= T <= 3 against the reference run (default: PBF at a / spacing = 20, free-slip walls,
   the FLIP grid's wall condition), steps and wall-clock seconds.

    python benchmarks/dam_break_methods.py                      # the default set (~1 min on 2 CPU cores)
    python benchmarks/dam_break_methods.py --flip-res 10 14 20 40 --seeds 4 5 6 7 --variants  # ~2 min
"""

import argparse
import sys
from pathlib import Path

import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from test_dam_break_crosscheck import EARLY, MM_T, MM_Z, at_mm, run_flip_dam_break, run_pbf_dam_break

from warpsim.cli_common import DefaultsHelpFormatter, run_script
from warpsim.verbosity import set_warp_verbosity


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=DefaultsHelpFormatter)
    ap.add_argument("--flip-res", type=int, nargs="+", default=[10, 20, 40], help="FLIP cells per a")
    ap.add_argument("--pbf-res", type=int, nargs="+", default=[10, 20], help="PBF particles per a")
    ap.add_argument("--main-res", type=int, default=20, help="FLIP cells per a of the seed and variant runs")
    ap.add_argument("--seeds", type=int, nargs="+", default=[3], help="FLIP seeds besides the default 3 (at --main-res)")
    ap.add_argument("--variants", action="store_true",
                    help="also FLIP with cfl 0.5, pure PIC, and without the density correction")
    args = ap.parse_args()
    set_warp_verbosity()  # quiet unless $WARPSIM_VERBOSE=1 (Warp 1.19 ignores config.quiet)
    wp.init()

    runs = {}
    for res in args.pbf_res:
        runs[f"PBF a/{res} no-slip"] = run_pbf_dam_break(res=res)
        runs[f"PBF a/{res} slip"] = run_pbf_dam_break(res=res, wall_friction=0.0)
    for res in args.flip_res:
        runs[f"FLIP a/{res}"] = run_flip_dam_break(res=res)
    main_res = args.main_res
    for seed in args.seeds:
        if seed != 3 or main_res not in args.flip_res:
            runs[f"FLIP a/{main_res} seed {seed}"] = run_flip_dam_break(res=main_res, seed=seed)
    if args.variants:
        runs[f"FLIP a/{main_res} cfl 0.5"] = run_flip_dam_break(res=main_res, cfl=0.5)
        runs[f"FLIP a/{main_res} PIC"] = run_flip_dam_break(res=main_res, flip_ratio=0.0)
        runs[f"FLIP a/{main_res} no density corr."] = run_flip_dam_break(res=main_res, density_correction=0.0)

    names = list(runs)
    print("\nfront Z = x_front / a at Martin and Moyce's T (Z_sim / Z_exp - 1 in brackets)")
    print("   T    M&M  " + "".join(f"{n[:22]:>24}" for n in names))
    for i, (t, z) in enumerate(zip(MM_T, MM_Z)):
        cells = "".join(f"{at_mm(runs[n])[i]:>15.3f} ({at_mm(runs[n])[i] / z - 1:+.3f})" for n in names)
        print(f"  {t:.2f}  {z:.2f}{cells}")

    ref_name = f"PBF a/{max(args.pbf_res)} slip"
    ref = runs[ref_name]
    window = (ref["T"] >= 0.8) & (ref["T"] <= 3.0 + 1e-6)
    print(f"\nrun                           lead over 1.0 < T < 1.9     Z / Z({ref_name}) - 1, 0.8 <= T <= 3"
          "    steps   particles   seconds")
    for n in names:
        r = runs[n]
        lead = at_mm(r)[EARLY] / MM_Z[EARLY] - 1.0
        rel = r["Z"][window] / ref["Z"][window] - 1.0
        extra = f"  area {r['area']:.3f}" if "area" in r else ""
        print(f"{n:28s}  {lead.min():+.3f} .. {lead.max():+.3f}            {rel.min():+.3f} .. {rel.max():+.3f}"
              f"          {r['steps']:6d}   {r['particles']:8d}   {r['seconds']:7.1f}{extra}")


if __name__ == "__main__":
    sys.exit(run_script(main))
