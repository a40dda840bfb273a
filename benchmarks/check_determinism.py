"""Run every scene twice, in separate processes (as a user would), and compare the two USD caches
sample by sample: prints, per scene, ``identical`` or the first differing sample (prim, attribute,
frame, element index and both values).

    python benchmarks/check_determinism.py --device cuda:0 --frames 30
    python benchmarks/check_determinism.py --device cpu --frames 5 --scenes bounce flip_splash

A scene is identical when every attribute of every prim has the same time samples with the same
bits (NaNs included). The line also says whether the cache files are byte-identical. Exit status:
0 when every scene is identical, 1 otherwise (2 when a run fails).
"""

from __future__ import annotations

import argparse
import filecmp
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from warpsim.cli_common import DefaultsHelpFormatter, run_script

ROOT = Path(__file__).resolve().parents[1]


def scene_names() -> list[str]:
    """The scenes ``warpsim list`` knows, in its order."""
    sys.path.insert(0, str(ROOT))
    from warpsim.scenes import scenes

    return list(scenes())


def run_scene(scene: str, out: Path, device: str, frames: int, extra: list[str]) -> float:
    """``warpsim run`` in a fresh process; returns its wall time [s]. Raises on failure."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    cmd = [sys.executable, "-m", "warpsim", "run", scene, "--frames", str(frames), "--out", str(out),
           "--no-progress", *extra]
    if device:
        cmd += ["--device", device]
    start = time.perf_counter()
    done = subprocess.run(cmd, env=env, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} exited {done.returncode}: {done.stderr.strip()[-800:]}")
    return time.perf_counter() - start


def _as_array(value) -> np.ndarray:
    if value is None:
        return np.zeros(0)
    try:
        return np.asarray(value)
    except Exception:  # noqa: BLE001  (a USD value numpy cannot take: compare its text)
        return np.asarray(str(value))


def _first_difference(a: np.ndarray, b: np.ndarray):
    """None when a and b hold the same bits, else (element index, value a, value b)."""
    if a.shape == b.shape and a.dtype == b.dtype and a.tobytes() == b.tobytes():
        return None
    if a.shape != b.shape or a.dtype != b.dtype or a.dtype.kind not in "fiub":
        return "shape", f"{a.dtype}{a.shape}", f"{b.dtype}{b.shape}"
    rows_a = a.reshape(a.shape[0], -1) if a.ndim > 0 else a.reshape(1, 1)
    rows_b = b.reshape(rows_a.shape)
    for index in range(rows_a.shape[0]):
        if rows_a[index].tobytes() != rows_b[index].tobytes():
            return index, rows_a[index].tolist(), rows_b[index].tolist()
    return None


def compare_caches(path_a: Path, path_b: Path):
    """None when the composed stages hold the same samples, else the earliest difference as
    (frame, prim, attribute, index, value a, value b)."""
    from pxr import Usd

    stage_a, stage_b = Usd.Stage.Open(str(path_a)), Usd.Stage.Open(str(path_b))
    prims_a = {p.GetPath(): p for p in stage_a.Traverse()}
    prims_b = {p.GetPath(): p for p in stage_b.Traverse()}
    if prims_a.keys() != prims_b.keys():
        only = sorted(str(p) for p in prims_a.keys() ^ prims_b.keys())
        return None, only[0], "(prim present in one cache only)", "", "", ""
    earliest = None
    for path, prim_a in prims_a.items():
        prim_b = prims_b[path]
        for attr_a in prim_a.GetAttributes():
            name = attr_a.GetName()
            attr_b = prim_b.GetAttribute(name)
            times_a, times_b = attr_a.GetTimeSamples(), attr_b.GetTimeSamples() if attr_b else []
            if list(times_a) != list(times_b):
                frame = min(set(times_a) ^ set(times_b), default=None)
                diff = (frame, str(path), name, "time samples", list(times_a)[:5], list(times_b)[:5])
                if earliest is None or (frame is not None and earliest[0] is not None and frame < earliest[0]):
                    earliest = diff
                continue
            for frame in [None, *times_a]:  # None: the default (unsampled) value
                if earliest is not None and frame is not None and earliest[0] is not None and frame >= earliest[0]:
                    break
                t = Usd.TimeCode.Default() if frame is None else Usd.TimeCode(frame)
                found = _first_difference(_as_array(attr_a.Get(t)), _as_array(attr_b.Get(t)))
                if found is not None:
                    earliest = (frame, str(path), name, *found)
                    if frame is None:  # a default value differs: nothing comes earlier
                        return earliest
                    break
    return earliest


def files_identical(dir_a: Path, dir_b: Path) -> bool:
    names_a = sorted(p.relative_to(dir_a) for p in dir_a.rglob("*") if p.is_file())
    names_b = sorted(p.relative_to(dir_b) for p in dir_b.rglob("*") if p.is_file())
    if names_a != names_b:
        return False
    return all(filecmp.cmp(dir_a / n, dir_b / n, shallow=False) for n in names_a)


def _short(values):
    text = str(values)
    return text if len(text) < 120 else text[:117] + "..."


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=DefaultsHelpFormatter)
    parser.add_argument("--device", default="", help="Warp device, e.g. cpu or cuda:0 (default: warpsim's default)")
    parser.add_argument("--frames", type=int, default=30, help="frames per run (default 30)")
    parser.add_argument("--scenes", nargs="*", default=None, help="scene names (default: every scene)")
    parser.add_argument("--keep", default=None,
                        help="folder to keep the caches in (default: a temporary folder, removed at the end)")
    parser.add_argument("--set", action="append", default=[], metavar="SCENE:KEY=VALUE",
                        help="a scene parameter for one scene (repeatable)")
    args = parser.parse_args(argv)
    if args.frames < 1:
        parser.error(f"--frames {args.frames}: it must be >= 1")
    known = scene_names()
    chosen = args.scenes or known
    unknown = [s for s in chosen if s not in known]
    if unknown:
        parser.error(f"unknown scene(s) {unknown}; known: {' '.join(known)}")
    settings: dict[str, list[str]] = {}
    for item in args.set:
        scene, _, kv = item.partition(":")
        if not kv or "=" not in kv:
            parser.error(f"--set {item!r}: write SCENE:KEY=VALUE")
        settings.setdefault(scene, []).extend(["--set", kv])

    work = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="warpsim-determinism-"))
    print(f"device {args.device or '(default)'}, {args.frames} frames, caches in {work}")
    failures = 0
    for scene in chosen:
        dirs = [work / scene / f"run{k}" for k in (1, 2)]
        try:
            seconds = [run_scene(scene, d / f"{scene}.usda", args.device, args.frames, settings.get(scene, []))
                       for d in dirs]
        except RuntimeError as exc:
            print(f"{scene:12s} run failed: {exc}")
            print(f"caches kept in {work}")
            return 2
        diff = compare_caches(dirs[0] / f"{scene}.usda", dirs[1] / f"{scene}.usda")
        same_bytes = files_identical(*dirs)
        timing = f"({seconds[0]:.1f} s, {seconds[1]:.1f} s)"
        if diff is None:
            print(f"{scene:12s} identical{' (byte-identical files)' if same_bytes else ' (same samples; file bytes differ)'}"
                  f" {timing}")
        else:
            failures += 1
            frame, prim, attr, index, a, b = diff
            where = "default value" if frame is None else f"frame {frame:g}"
            print(f"{scene:12s} DIFFERS at {where}, {prim}.{attr}, index {index}: {_short(a)} vs {_short(b)} {timing}")
    print(f"{len(chosen) - failures} of {len(chosen)} scenes identical")
    if not args.keep:
        shutil.rmtree(work, ignore_errors=True)
    return 0 if failures == 0 else 1


if __name__ == "__main__":
    sys.exit(run_script(main))
