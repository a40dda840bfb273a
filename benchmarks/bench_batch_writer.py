"""The sweep writer alone: CPU time a world-frame of ``BatchLayerWriter.write_batch`` (every world's
samples at once, as ``warpsim sweep`` writes them) against ``write_worlds`` (each world's
``frame_data()``, the reference) in the same process, and usd-core's own floor for the same samples
(``Sdf.Layer.SetTimeSample`` of ``Vt`` arrays made by ``FromNumpy``, nothing else).

    python benchmarks/bench_batch_writer.py --scene bounce --worlds 2000 --frames 30

The frames are stepped and gathered first; only the writers' calls are timed (process CPU time, so a
loaded machine slows them less than the wall clock says). The chunk files of both writers are
compared byte for byte.
"""
from __future__ import annotations

import argparse
import filecmp
import glob
import os
import tempfile
import time

import numpy as np


def _frames(batch, count):
    """``count`` frames of the batch: (batched arrays, per-world frame data), copied."""
    out = []
    for _ in range(count):
        x, v = batch.world_slices()
        batched = batch.batch_frame_data(x, v)
        batched = {p: {k: np.array(a, copy=True) for k, a in d.items()} for p, d in batched.items()}
        out.append((batched, [batch.world_frame_data(x[w], v[w], w) for w in range(batch.world_count)]))
        batch.advance(1.0 / 25.0, 2)
    return out


def _time_writer(batch, frames, folder, per_world):
    """CPU seconds of writing frames 1.. (frame 0 seals the layer, untimed) and the chunk files."""
    from warpsim.sweeps.usd import BatchLayerWriter

    os.makedirs(folder)
    writer = BatchLayerWriter(os.path.join(folder, "s.usdc"), batch.scene, 0, batch.world_count, 25.0)
    write = (lambda f, d: writer.write_worlds(f, d[1])) if per_world else (lambda f, d: writer.write_batch(f, d[0]))
    write(0, frames[0])
    t0 = time.process_time()
    for f in range(1, len(frames)):
        write(f, frames[f])
    writer.flush()
    seconds = time.process_time() - t0
    writer.close(batch.scene.name)
    return seconds, sorted(glob.glob(os.path.join(folder, "s.*chunk0*.usdc")))


def _usd_floor(writer_dynamic, frames, world_count):
    """CPU seconds of usd-core alone setting the samples the writer authors every frame (those of its
    attributes that change every frame, made by :func:`warpsim.usd.frame_arrays.world_samples`,
    untimed) on a layer with the same attribute paths; and how many attributes that is."""
    from pxr import Sdf

    from warpsim.usd.chunk_author import set_frame_samples
    from warpsim.usd.frame_arrays import world_samples
    from warpsim.usd.value_types import vt_maker

    layer = Sdf.Layer.CreateAnonymous(".usdc")
    per_frame, paths = [], {}
    for f in range(1, len(frames)):
        fields = []
        for prim, decl in writer_dynamic.items():
            for key, values in world_samples(decl, frames[f][0].get(prim), f, world_count).items():
                attr = decl.attrs[key]
                if attr.on_change or not isinstance(values, np.ndarray):
                    continue
                if (prim, key) not in paths:
                    made = paths[prim, key] = []
                    with Sdf.ChangeBlock():
                        for w in range(world_count):
                            spec = Sdf.CreatePrimInLayer(layer, f"/Worlds/world_{w:06d}/{prim}")
                            Sdf.AttributeSpec(spec, key, Sdf.ValueTypeNames.Find(attr.type_name))
                            made.append(spec.path.AppendProperty(key))
                fields.append((paths[prim, key], vt_maker(attr.type_name), values))
        per_frame.append(fields)
    t0 = time.process_time()
    with Sdf.ChangeBlock():
        for f, fields in enumerate(per_frame, start=1):
            for field_paths, make, values in fields:
                set_frame_samples(layer, field_paths, f, make, values)
    return time.process_time() - t0, len(paths)


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scene", default="bounce")
    p.add_argument("--worlds", type=int, default=2000)
    p.add_argument("--frames", type=int, default=30)
    p.add_argument("--repeats", type=int, default=3)
    args = p.parse_args()

    from warpsim.scenes import get_scene
    from warpsim.sweeps.sweep import make_batch
    from warpsim.sweeps.usd import BatchLayerWriter

    batch = make_batch(get_scene(args.scene), [{} for _ in range(args.worlds)], device="cpu")
    with tempfile.TemporaryDirectory() as tmp:
        declared = BatchLayerWriter(os.path.join(tmp, "declare.usdc"), batch.scene, 0, batch.world_count, 25.0)
        frames = _frames(batch, args.frames)
        wf = args.worlds * (args.frames - 1)
        for r in range(args.repeats):
            t_batch, a = _time_writer(batch, frames, os.path.join(tmp, f"batch{r}"), per_world=False)
            t_worlds, b = _time_writer(batch, frames, os.path.join(tmp, f"worlds{r}"), per_world=True)
            t_floor, fields = _usd_floor(declared.dynamic, frames, args.worlds)
            same = len(a) == len(b) and all(filecmp.cmp(x, y, shallow=False) for x, y in zip(a, b))
            print(f"{args.scene}, {args.worlds} worlds x {args.frames - 1} frames: write_batch {1e6 * t_batch / wf:.1f} us, "
                  f"write_worlds {1e6 * t_worlds / wf:.1f} us a world-frame (ratio {t_worlds / t_batch:.2f}); "
                  f"usd-core alone ({fields} attributes set every frame) {1e6 * t_floor / wf:.1f} us; chunks identical: {same}")


if __name__ == "__main__":
    main()
