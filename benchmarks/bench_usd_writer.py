"""Streaming USD writer vs bare usd-core writes of the same arrays, in the same run.

    python benchmarks/bench_usd_writer.py [POINTS] [FRAMES] [CHUNK]     (default 1000000 120 24)

Each frame has ``points`` and ``velocities`` (POINTS x 3 float32, different every frame).
* bare: ``Usd.Stage.CreateNew(x.usdc)``, ``UsdGeom.Points`` attributes ``Set`` per time sample,
  one ``Save()`` at the end (all samples held in memory; a kill before the save loses everything);
* writer: ``warpsim.usd.writer.UsdCacheWriter`` (crash-safe chunks of CHUNK frames, fsync'd, plus
  ``extent`` per frame), closed at the end.
Each runs in its own subprocess so its peak resident memory (``ru_maxrss``) is its own; times
exclude interpreter start-up. Prints both, the time ratio writer / bare and the memory figures.
"""
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time

import numpy as np


def frames(n, count):
    """Deterministic frame data: (points, velocities) float32 (n, 3), new arrays every frame."""
    base = np.random.default_rng(0).random((n, 3), dtype=np.float32)
    for f in range(count):
        shift = np.float32(0.001 * f)
        yield f, base + shift, base * shift


def run_bare(path, n, count):
    from pxr import Usd, UsdGeom, Vt

    stage = Usd.Stage.CreateNew(path)
    pts = UsdGeom.Points.Define(stage, "/World/particles")
    pa, va = pts.GetPointsAttr(), pts.GetVelocitiesAttr()
    for f, p, v in frames(n, count):
        pa.Set(Vt.Vec3fArray.FromNumpy(p), f)
        va.Set(Vt.Vec3fArray.FromNumpy(v), f)
    stage.Save()


def run_writer(path, n, count, chunk):
    from warpsim.usd.writer import UsdCacheWriter

    with UsdCacheWriter(path, fps=60, chunk_size=chunk) as w:
        w.add_points("particles", radius=0.001)
        for f, p, v in frames(n, count):
            w.write_frame(f, {"particles": {"points": p, "velocities": v}})


def child(mode, path, n, count, chunk):
    import pxr.Usd  # noqa: F401  (imports stay outside the timing)

    import warpsim.usd.writer  # noqa: F401

    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.perf_counter()
    if mode == "bare":
        run_bare(path, n, count)
    else:
        run_writer(path, n, count, chunk)
    seconds = time.perf_counter() - t0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    print(json.dumps({"seconds": seconds, "peak_mib": peak / 1024, "startup_mib": rss0 / 1024}))


def main():
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        _, _, mode, path, n, count, chunk = sys.argv
        child(mode, path, int(n), int(count), int(chunk))
        return
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 1_000_000
    count = int(sys.argv[2]) if len(sys.argv) > 2 else 120
    chunk = int(sys.argv[3]) if len(sys.argv) > 3 else 24
    frame_mib = 2 * n * 12 / 2**20
    print(f"{n} points x {count} frames (points + velocities: {frame_mib:.1f} MiB per frame, "
          f"{frame_mib * count / 1024:.2f} GiB in all), writer chunks of {chunk} frames")
    tmp = tempfile.mkdtemp(prefix="bench_usd_")
    results = {}
    try:
        for mode in ("bare", "writer"):
            path = os.path.join(tmp, f"{mode}.usdc")
            out = subprocess.run([sys.executable, __file__, "--child", mode, path, str(n), str(count), str(chunk)],
                                 check=True, capture_output=True, text=True).stdout
            results[mode] = json.loads(out.strip().splitlines()[-1])
            size = sum(os.path.getsize(os.path.join(tmp, f)) for f in os.listdir(tmp) if f.startswith(mode))
            r = results[mode]
            print(f"  {mode:6s}: {r['seconds']:8.2f} s  ({count / r['seconds']:7.1f} frames/s)  peak RSS "
                  f"{r['peak_mib']:8.0f} MiB (after imports {r['startup_mib']:.0f} MiB)  files {size / 2**30:.2f} GiB")
            for f in os.listdir(tmp):
                os.remove(os.path.join(tmp, f))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    b, w = results["bare"], results["writer"]
    print(f"time ratio writer / bare usd-core: {w['seconds'] / b['seconds']:.2f}")
    print(f"peak memory: writer {w['peak_mib']:.0f} MiB vs bare {b['peak_mib']:.0f} MiB "
          f"(writer holds ~one frame; bare holds every frame until Save)")


if __name__ == "__main__":
    main()
