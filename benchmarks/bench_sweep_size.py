"""A teapot sweep's batch layer: springs written as their particles' points (as sweeps write them)
against the former form, both ends of every spring as curves, in the same process.

    python benchmarks/bench_sweep_size.py [--worlds W] [--frames F] [--repeats R]

Writes F frames of W teapot worlds (518 mesh points with velocities, 538 particles, 5,238 springs
each) through ``warpsim.sweeps.usd.BatchLayerWriter`` twice per repeat, alternating the two forms
(``curves``: the declaration the scene makes, as every layer was written before; ``joined``: what
sweeps write now). Frame data is seeded noise, new every world and frame (USD's crate format stores
identical arrays once, so repeated data would flatter both). Prints, per form, the best time per
world and frame for authoring and saving, the bytes written, and the estimate
``estimate_sweep_bytes`` gives before a sweep against the bytes the joined layer holds.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time

import numpy as np


def _args(argv):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--worlds", type=int, default=64, help="teapot worlds in the layer")
    p.add_argument("--frames", type=int, default=24, help="frames written (one chunk at the default chunk size)")
    p.add_argument("--repeats", type=int, default=2, help="runs of each form (the best is reported)")
    args = p.parse_args(argv)
    for name in ("worlds", "frames", "repeats"):
        if getattr(args, name) < 1:
            p.error(f"--{name} {getattr(args, name)}: it must be >= 1")
    return args


def _write(form, folder, scene, worlds, frames, seed=0):
    """Seconds to write ``frames`` frames of ``worlds`` worlds in ``form``; bytes written."""
    import warpsim.sweeps.usd as layers

    data0 = scene.frame_data()
    n, p = len(data0["teapot"]["points"]), len(data0["springs"]["points"])
    rng = np.random.default_rng(seed)
    saved = layers.joined_form
    if form == "curves":
        layers.joined_form = lambda decl: decl  # the scene's own declaration: springs as curves
    try:
        path = os.path.join(folder, f"{form}.usdc")
        writer = layers.BatchLayerWriter(path, scene, 0, worlds, 60.0, durable=False)
        writer.begin()
        seconds = 0.0
        for f in range(frames):
            datas = []
            for _ in range(worlds):
                x = (data0["springs"]["points"] + rng.normal(scale=1e-3, size=(p, 3))).astype(np.float32)
                datas.append({"teapot": {"points": x[:n], "velocities": rng.normal(size=(n, 3)).astype(np.float32)},
                              "springs": {"points": x}})
            t0 = time.perf_counter()
            writer.write_worlds(f, datas)
            seconds += time.perf_counter() - t0
        t0 = time.perf_counter()
        writer.close("teapot")
        seconds += time.perf_counter() - t0
    finally:
        layers.joined_form = saved
    size = sum(os.path.getsize(os.path.join(folder, name)) for name in os.listdir(folder) if name.startswith(form))
    for name in os.listdir(folder):
        if name.startswith(form):
            os.remove(os.path.join(folder, name))
    return seconds, size


def main(argv=None):
    args = _args(argv)
    from warpsim.scenes import get_scene
    from warpsim.sweeps.usd import estimate_sweep_bytes

    cls = get_scene("teapot")
    scene = cls(cls.resolve_params({}), device="cpu")
    best = {}
    with tempfile.TemporaryDirectory(prefix="bench_sweep_size_") as folder:
        for r in range(args.repeats):
            for form in ("curves", "joined"):
                seconds, size = _write(form, folder, scene, args.worlds, args.frames, seed=r)
                old = best.get(form, (np.inf, 0))
                best[form] = (min(old[0], seconds), size)
        estimate = estimate_sweep_bytes(scene, os.path.join(folder, "e.usdc"), args.worlds, args.frames)
    wf = args.worlds * args.frames
    print(f"teapot batch layer, {args.worlds} worlds x {args.frames} frames, best of {args.repeats}")
    print("form     ms per world-frame   bytes          bytes per world-frame")
    for form in ("curves", "joined"):
        s, b = best[form]
        print(f"{form:8s} {1e3 * s / wf:18.3f}   {b:13,d}  {b / wf:12,.0f}")
    (sc, bc), (sj, bj) = best["curves"], best["joined"]
    print(f"joined / curves: time {sj / sc:.3f}x, bytes {bj / bc:.3f}x")
    print(f"estimate before the sweep: {estimate['bytes']:,d} B for the joined layer's {bj:,d} B "
          f"({100 * (estimate['bytes'] / bj - 1):+.1f} %)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
