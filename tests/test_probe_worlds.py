"""Many worlds are correct for every stage (issue 28): for every scene ``warpsim sweep`` accepts,
two worlds with identical parameters give identical table rows and identical samples, and each
world equals the scene run alone (its own ``advance``, frame data as ``warpsim run`` writes it).
The stages covered: springs and walls (bounce, springs, teapot), breakable springs and particle
pairs (wall: the ball breaks the mortar), cloth springs (cloth with semi-implicit Euler), soft
contact between bodies (donuts: each world's own triangles) and flocks (flock, school)."""

import math

import numpy as np
import pytest

pytest.importorskip("pxr")
from pxr import Usd

from warpsim.scenes import get_scene
from warpsim.scenes.timing import resolve_timing
from warpsim.sweeps.sweep import run_batch
from warpsim.sweeps.usd import BatchLayerWriter

# scene -> (--set values that keep it small, frames); frames are enough for the stage to act
CASES = {
    "bounce": ({}, 12),
    "springs": ({}, 8),
    "teapot": ({"lattice_cells": 3}, 6),
    "wall": ({"bricks": "3,2", "ball_speed": 20.0}, 12),
    "cloth": ({"integrator": "semi_implicit_euler", "resolution": 8}, 4),
    "donuts": ({"count": 2, "segments": 8, "sides": 6, "lattice_cells": 2}, 30),
    "flock": ({"birds": 40, "geese": 6}, 6),
    "school": ({"fish": 40}, 6),
}
WHY = {"donuts": "per-world soft contact: world 1 must collide with its own tori's triangles, not world 0's",
       "wall": "per-world breakable springs and particle pairs"}


def _equal_rows(a, b):
    a = {k: v for k, v in a.items() if k != "world"}
    b = {k: v for k, v in b.items() if k != "world"}
    assert a.keys() == b.keys()
    for k in a:
        x, y = a[k], b[k]
        if isinstance(x, float) and math.isnan(x):
            assert isinstance(y, float) and math.isnan(y), k
        else:
            assert x == y, (k, x, y)


def _numpy(value):
    return np.asarray(value.numpy() if hasattr(value, "numpy") else value, dtype=np.float64)


@pytest.mark.parametrize("name", sorted(CASES))
def test_identical_worlds_give_identical_rows_and_each_equals_its_run_alone(tmp_path, name):
    cls = get_scene(name)
    sets, frames = CASES[name]
    params = cls.resolve_params(sets)
    timing = {}
    rows = run_batch(name, [dict(params), dict(params)], frames=frames, device="cpu",
                     layer_path=tmp_path / "b.usdc", timing=timing)
    why = WHY.get(name, "every stage per world")
    _equal_rows(rows[0], rows[1])
    assert not rows[0]["blown_up"], rows[0]
    stage = Usd.Stage.Open(str(tmp_path / "b.usdc"))
    alone = cls(params, device="cpu")
    decls = BatchLayerWriter(str(tmp_path / "alone.usdc"), alone, 0, 1, 60.0)  # the samples a batch layer holds
    alone.use_timing(alone.timing.with_steps(timing["frame_steps"]))  # the steps per frame the batch took (auto)
    timing = resolve_timing(cls, params)
    substeps, frame_dt = timing.steps, timing.frame_dt
    moved = 0.0
    for frame in range(frames + 1):
        if frame:
            alone.advance(frame_dt, substeps)
        data = alone.frame_data()
        for prim_name, values in data.items():
            if "points" not in values and "positions" not in values:
                continue
            key = "points" if "points" in values else "positions"
            mine = _numpy(decls.prims[prim_name].frame_samples(values, frame)[key]).reshape(-1, 3)
            got = [np.asarray(stage.GetPrimAtPath(f"/Worlds/world_{w:06d}/{prim_name}").GetAttribute(key)
                              .Get(float(frame)), np.float64).reshape(-1, 3) for w in (0, 1)]
            assert np.array_equal(got[0], got[1]), f"{name} frame {frame} {prim_name}: worlds 0 and 1 differ ({why})"
            assert got[1].shape == mine.shape and np.abs(got[1] - mine).max() <= 1e-5 * max(1.0, np.abs(mine).max()), \
                f"{name} frame {frame} {prim_name}: world 1 is {np.abs(got[1] - mine).max():.3g} m off its run alone " \
                f"({why})"
            if frame == frames:
                moved = max(moved, np.abs(got[1] - _numpy(stage.GetPrimAtPath(f"/Worlds/world_000001/{prim_name}")
                                                          .GetAttribute(key).Get(0.0)).reshape(-1, 3)).max())
    assert moved > 1e-3, f"{name}: nothing moved in {frames} frames; the test would not see a wrong world"
