"""Each world of a batch takes its own step count (issue 41, part 4): world N of a sweep equals
``warpsim run SCENE --set ...`` with its parameters, bit for bit on the same device, with no
manifest, for worlds that need different automatic counts (teapot, springs, cloth, bounce); with
one count shared by the batch (the largest, as before) it would not."""

import io

import numpy as np
import pytest

from warpsim.cli import main
from warpsim.scenes import get_scene
from warpsim.sweeps.sweep import sweep_timing
from warpsim.worlds.batch import WorldBatch

pytest.importorskip("pxr")

FRAMES = 3
SWEEPS = {  # (--set, the varied key and its values, extra options): three worlds needing different counts
    "teapot": ({"resolution": "2"}, "stiffness", (40.0, 160.0, 640.0), ()),
    "springs": ({"count": "5"}, "stiffness", (400.0, 10000.0, 40000.0), ()),
    "cloth": ({"integrator": "semi_implicit_euler", "resolution": "4", "explicit_substeps": "1"}, "structural",
              (400.0, 1600.0, 6400.0), ()),
    "bounce": ({"collision": "seed"}, "height", (0.2, 0.04, 0.01), ("--substeps", "auto")),
}


def cli(*argv):
    out, err = io.StringIO(), io.StringIO()
    code = main([str(a) for a in argv], out=out, err=err)
    return code, out.getvalue(), err.getvalue()


def sweep_worlds(name):
    fixed, key, values, _ = SWEEPS[name]
    cls = get_scene(name)
    return cls, [{**fixed, key: v} for v in values]  # as the sweep command gives them


@pytest.mark.parametrize("name", sorted(SWEEPS))
def test_a_sweep_world_equals_its_plain_run_bit_for_bit(tmp_path, name):
    from warpsim.sweeps.rerun import first_difference

    fixed, key, values, extra = SWEEPS[name]
    sets = [a for k, v in fixed.items() for a in ("--set", f"{k}={v}")]
    root = tmp_path / "sweep.usda"
    code, _, err = cli("sweep", name, *sets, "--vary", f"{key}={','.join(map(str, values))}", "--worlds", 3,
                         "--frames", FRAMES, "--device", "cpu", "--out", root, "--no-progress", *extra)
    assert code == 0, err
    # the worlds need different automatic counts: each takes its own
    cls, worlds = sweep_worlds(name)
    batch = WorldBatch(cls, worlds, device="cpu")
    timing = sweep_timing(cls, worlds, substeps=extra[1] if extra else None)  # the sweep's request
    batch.use_timing(timing)
    counts = batch.world_steps(timing.frame_dt, timing.steps)
    assert len(set(counts.tolist())) == 3, counts
    w = int(np.argmin(counts))  # the world furthest from the batch's largest count
    cache = tmp_path / "alone.usda"
    code, _, err = cli("run", name, *sets, "--set", f"{key}={values[w]}", "--frames", FRAMES, "--device", "cpu",
                         "--out", cache, "--no-progress", *extra)
    assert code == 0, err
    assert first_difference(root, w, cache) is None
    assert first_difference(root, (w + 1) % 3, cache) is not None  # the comparison sees another world's samples
    # with the batch's largest count for every world (the former rule) world w would differ
    shared = WorldBatch(cls, worlds, device="cpu")
    fixed = sweep_timing(cls, worlds, substeps=int(counts.max()))  # --substeps N: N for every world
    shared.use_timing(fixed)
    assert fixed.frame_dt == timing.frame_dt and (shared.world_steps(fixed.frame_dt, fixed.steps) == counts.max()).all()
    for _ in range(FRAMES):
        batch.advance(timing.frame_dt, timing.steps)
        shared.advance(fixed.frame_dt, fixed.steps)
    assert batch.world_slices()[0][w].tobytes() != shared.world_slices()[0][w].tobytes()
