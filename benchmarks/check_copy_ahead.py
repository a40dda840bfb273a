"""A sweep's batch layer is the same bytes however it reaches the disk (issue 50), on a GPU.

Runs ``run_batch`` on one device four ways: frames copied to the host after each frame or while
the next one steps (pinned, double-buffered, :class:`warpsim.worlds.host_copies.HostCopies`), and
chunks authored by the stepping process or by worker processes; compares every file of the four
layers byte for byte and the tables. (The CPU takes the first way only: the tests check the
workers there, ``tests/test_chunk_workers.py``.)

    python benchmarks/check_copy_ahead.py --device cuda:0 --scene teapot --worlds 64 --frames 30
"""
from __future__ import annotations

import argparse
import filecmp
import os
import shutil
import sys
import tempfile
import time
import types


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--device", default="cuda:0")
    p.add_argument("--scene", default="teapot")
    p.add_argument("--worlds", type=int, default=64)
    p.add_argument("--frames", type=int, default=30)
    p.add_argument("--vary", action="append", default=["stiffness=20:60"])
    p.add_argument("--chunk", type=int, default=8)
    args = p.parse_args(argv)
    import warp as wp

    import warpsim.usd.writer as writer_module
    from warpsim.sweeps.sweep import run_batch, sample_worlds
    from warpsim.worlds.batch import WorldBatch

    wp.init()
    writer_module.secrets = types.SimpleNamespace(token_hex=lambda n: "fixed0run0id")  # one run id for all four
    params = sample_worlds(args.scene, {}, args.vary, args.worlds)
    root = tempfile.mkdtemp(prefix="copy_ahead_")
    original = WorldBatch.can_copy_ahead
    results = {}
    try:
        for ahead in (False, True):
            for workers in (0, 2):
                WorldBatch.can_copy_ahead = original if ahead else (lambda self: False)
                folder = os.path.join(root, f"ahead{int(ahead)}_w{workers}")
                t0 = time.perf_counter()
                rows = run_batch(args.scene, params, frames=args.frames, device=args.device, chunk_size=args.chunk,
                                 layer_path=os.path.join(folder, "s.batch_0000.usdc"), write_workers=workers)
                results[(ahead, workers)] = (folder, rows, time.perf_counter() - t0)
                print(f"copy ahead {ahead!s:5}  workers {workers}: {results[(ahead, workers)][2]:.2f} s "
                      f"({len(os.listdir(folder))} files)")
    finally:
        WorldBatch.can_copy_ahead = original
    base_folder, base_rows, _ = results[(False, 0)]
    names = sorted(os.listdir(base_folder))
    bad = []
    for key, (folder, rows, _) in results.items():
        if sorted(os.listdir(folder)) != names:
            bad.append(f"{key}: files {sorted(os.listdir(folder))}")
            continue
        bad += [f"{key}: {n} differs" for n in names
                if not filecmp.cmp(os.path.join(base_folder, n), os.path.join(folder, n), shallow=False)]
        if rows != base_rows:
            bad.append(f"{key}: table rows differ")
    shutil.rmtree(root, ignore_errors=True)
    print("identical: every file of the four layers and the tables" if not bad else "DIFFERENT:\n  " + "\n  ".join(bad))
    return 0 if not bad else 1


if __name__ == "__main__":
    sys.exit(main())
