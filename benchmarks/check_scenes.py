"""Every scene at full length, as a user runs it: no false alarm anywhere, every real blow-up flagged.

Runs the corpus of :mod:`warpsim.commands.corpus` (the same cases and runner as
``tests/test_full_length.py``) and prints one row per case: scene, case, device, frames run of
frames asked, exit (ok / alarm at frame N / error), the largest energy gain (empty: the scene has no
energy balance), expected (clean / flagged), PASS or FAIL; then the failures' commands and messages,
and a summary line counting false alarms, missed blow-ups and errors. Exit status 1 when there is
any, else 0.

    python benchmarks/check_scenes.py --device cuda:0                        # everything, full size
    python benchmarks/check_scenes.py --device cpu --small                   # the CPU: resolution lowered
    python benchmarks/check_scenes.py --device cuda:0 --only cloth drape     # some scenes
    python benchmarks/check_scenes.py --device cpu --small --kinds blowup    # some kinds of case
    python benchmarks/check_scenes.py --device cuda:0 --case "springs/damping=0"   # one case (repeatable)
    python benchmarks/check_scenes.py --list                                 # the cases, as commands

The cases (``--kinds``): ``default`` (every scene of ``warpsim list`` at its defaults for its
default length, ``warpsim run``'s 120 frames), ``long`` (the same for ``--slider-frames``, 600),
``slider`` (each end of the physical sliders the viewer gives a scene: damping 0, restitution 1, the
largest stiffness and wind, the smallest mass, and the other ends, for ``--slider-frames`` frames),
``readme`` (every ``warpsim run`` of README.md at its README length) and ``blowup`` (each explicit
integrator at 1.2x its stability limit in springs, teapot, cloth and hair: flagged, within two frames
of the growth of an unchecked twin over the same scene stepped inside its limit). Each runs through
``warpsim run``'s own parsing, timing and checks in this process (the cache is not written).
``--small`` lowers only resolution-type parameters (cells, spacing, counts), never frames.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from warpsim.cli_common import DefaultsHelpFormatter, run_script  # noqa: E402

KINDS = ("default", "long", "slider", "readme", "blowup")


def parse(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=DefaultsHelpFormatter)
    p.add_argument("--device", default=None, help="Warp device (default: cuda:0 when present, else cpu)")
    p.add_argument("--small", action="store_true", help="lower resolution-type parameters (never frames)")
    p.add_argument("--only", nargs="+", default=None, metavar="SCENE", help="only these scenes")
    p.add_argument("--kinds", nargs="+", default=list(KINDS), choices=KINDS, help="only these kinds of case")
    p.add_argument("--case", action="append", default=[], metavar="SCENE/CASE",
                   help="only this case (its name as listed; repeatable)")
    p.add_argument("--slider-frames", type=int, default=None,
                   help="frames of each slider end (default: the corpus's 600)")
    p.add_argument("--seconds", type=float, default=None,
                   help="stop a case after the frame that passes this wall time (INCOMPLETE, counted apart)")
    p.add_argument("--list", action="store_true", help="list the cases as warpsim commands and exit")
    p.add_argument("--quiet", action="store_true", help="no row while running, only the table at the end")
    return p.parse_args(argv)


def main(argv=None):
    args = parse(argv)
    import warp as wp

    wp.config.quiet = True
    from warpsim.cli_common import UsageError, device_arg
    from warpsim.commands import corpus

    slider_frames = corpus.SLIDER_FRAMES if args.slider_frames is None else args.slider_frames
    todo = corpus.cases(args.only, tuple(args.kinds), slider_frames=slider_frames)
    if args.case:
        todo = [c for c in todo if c.name in args.case]
        if not todo:
            raise UsageError(f"--case {args.case}: no such case; see --list")
    if args.list:
        for case in todo:
            print(f"{case.name:45s} {case.expect:8s} {case.sized(args.small).shell()}")
        return 0
    device = device_arg(args.device)
    wp.init()
    print(f"check_scenes: {len(todo)} cases on {device}{' (small)' if args.small else ''}; "
          f"{corpus.environment_note()}", flush=True)
    results, t0 = [], time.perf_counter()
    for case in todo:
        result = corpus.run_case(case, device, small=args.small, seconds=args.seconds)
        results.append(result)
        if not args.quiet:
            print(corpus.format_table([result]).splitlines()[1], flush=True)
    print()
    print(corpus.format_table(results))
    stopped = [r for r in results if r.stopped]
    failed = [r for r in results if not r.passed and not r.stopped]
    if failed:
        print("\nfailures:")
        for r in failed:
            print(r.summary())
    false_alarms = sum(r.case.expect == "clean" and r.alarm_frame is not None for r in failed)
    missed = sum(r.case.expect == "flagged" and not r.exit.startswith("error") for r in failed)
    errors = sum(r.exit.startswith("error") or r.refused for r in failed)
    refused = [r for r in results if r.refused and r.passed]
    if refused:
        print("\nslider ends the scene refuses before any frame (no alarm; the viewer's slider reaches "
              "them):")
        for r in refused:
            print(f"  {r.case.name}: {r.message}")
    passed = len(results) - len(failed) - len(refused) - len(stopped)
    print(f"\nsummary: {len(results)} cases on {device} in {time.perf_counter() - t0:.0f} s: "
          f"{passed} passed, {false_alarms} false alarms, {missed} missed blow-ups, {errors} errors, "
          f"{len(refused)} slider ends refused, {len(stopped)} stopped at the time budget (--seconds)")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(run_script(main))
