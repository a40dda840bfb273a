"""``warpsim info`` on a long chunked cache: the chunk index vs reading every chunk, same run.

    python benchmarks/bench_cache_info.py [--frames 50000] [--chunk 24] [--device cpu] [--keep DIR]

Makes the cache with the tiny ``bounce`` scene (``warpsim run bounce --frames N --chunk K`` on
``--device``; reused from ``--keep DIR`` when it is already there), then times, in this process
and on the same files:

* index: ``cache_info(path)`` — root layer + ``<stem>.chunks.jsonl``; chunk sizes always and
  CRC-32s (below 256 MiB of chunks) compared, no chunk opened in USD;
* every chunk: ``cache_info(Usd.Stage)`` — the previous way (every frame's points and extent
  read through the value clips, so every chunk file is opened);

and the whole command ``warpsim info PATH`` in a subprocess (wall and CPU seconds of the child:
interpreter start, imports and the summary). Both summaries must agree (frames, counts, bounds).
Also reports what the index cost the writer: seconds spent in ``chunk_index.record`` and
``append_record`` (size, CRC-32 and one synced line per chunk) as a share of the run.
"""

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time

import numpy as np

from warpsim.cli_common import DefaultsHelpFormatter, run_script


def make_cache(path, frames, chunk, device):
    import warpsim.cli as cli
    from warpsim.usd import chunk_index

    spent = [0.0]

    def timed(fn):
        def wrapper(*a, **k):
            t = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                spent[0] += time.perf_counter() - t

        return wrapper

    chunk_index.record, chunk_index.append_record = (
        timed(chunk_index.record),
        timed(chunk_index.append_record),
    )
    t0 = time.perf_counter()
    code = cli.main(
        [
            "run",
            "bounce",
            "--frames",
            str(frames),
            "--chunk",
            str(chunk),
            "--no-progress",
            "--device",
            device,
            "--out",
            path,
        ]
    )
    assert code == 0, code
    return time.perf_counter() - t0, spent[0]


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=DefaultsHelpFormatter)
    ap.add_argument("--frames", type=int, default=50000)
    ap.add_argument("--chunk", type=int, default=24)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--keep", default=None, help="folder for the cache (reused when present)")
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args()
    folder = a.keep or tempfile.mkdtemp(prefix="bench_cache_info_")
    path = os.path.join(folder, f"bounce_{a.frames}.usda")
    if not os.path.exists(path):
        seconds, index_seconds = make_cache(path, a.frames, a.chunk, a.device)
        print(
            f"made {path}: {a.frames + 1} frames in {seconds:.1f} s; "
            f"chunk index upkeep {index_seconds:.2f} s "
            f"({100 * index_seconds / seconds:.1f} % of the run)"
        )
    from pxr import Usd

    from warpsim.usd.validate import cache_info

    chunks = len([f for f in os.listdir(folder) if ".chunk0" in f and f.startswith(f"bounce_{a.frames}.")])

    def best(fn):
        times = []
        for _ in range(a.repeat):
            t = time.perf_counter()
            out = fn()
            times.append(time.perf_counter() - t)
        return min(times), out

    cache_info(path)  # warm-up: pxr's plugins load on first use
    t_index, fast = best(lambda: cache_info(path))
    t_size, _ = best(lambda: cache_info(path, verify=False))
    t_all, slow = best(lambda: cache_info(Usd.Stage.Open(path)))
    assert (fast["start"], fast["end"], fast["frames"]) == (slow["start"], slow["end"], slow["frames"])
    for p, q in zip(fast["prims"], slow["prims"]):
        assert p["path"] == q["path"] and p.get("count") == q.get("count"), (p, q)
        np.testing.assert_allclose(p["bounds"], q["bounds"], rtol=1e-6, atol=1e-9)
    cmd = []
    for _ in range(a.repeat):
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        t = time.perf_counter()
        subprocess.run([sys.executable, "-m", "warpsim", "info", path], check=True, capture_output=True)
        wall = time.perf_counter() - t
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        cmd.append((wall, after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime))
    wall, cpu = min(cmd)
    print(f"{a.frames + 1} frames in {chunks} chunk files")
    print(
        f"cache_info, index (size + CRC-32): {t_index:.3f} s   index (size only): {t_size:.3f} s   "
        f"every chunk: {t_all:.3f} s   ratio every chunk / index: {t_all / t_index:.0f}x"
    )
    print(
        f"'warpsim info' command: {wall:.2f} s wall, {cpu:.2f} s CPU (interpreter start and imports included)"
    )


if __name__ == "__main__":
    sys.exit(run_script(main))
