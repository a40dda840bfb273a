"""``warpsim pick``: one world of a sweep as a file any USD tool opens, with the sweep's stage
settings and the world's parameters; grid roots name their prims in world order and carry each
world's parameters; bad input exits 2 with one line."""
from __future__ import annotations

import csv
import io

import numpy as np
import pytest

pytest.importorskip("pxr")
from pxr import Sdf, Usd, UsdGeom

from warpsim.cli import main

FRAMES, FPS = 12, 50


def run(*argv):
    out, err = io.StringIO(), io.StringIO()
    code = main([str(a) for a in argv], out=out, err=err)
    return code, out.getvalue(), err.getvalue()


@pytest.fixture(scope="module", params=["variants", "grid"])
def sweep(request, tmp_path_factory):
    root = tmp_path_factory.mktemp("pick") / "drop.usda"
    code, _, err = run("sweep", "bounce", "--worlds", 4, "--vary", "height=0.2:0.8", "--vary", "restitution=0.3,0.9",
                       "--fps", FPS, "--frames", FRAMES, "--no-progress", "--device", "cpu", "--out", root,
                       "--layout", request.param)
    assert code == 0, err
    with open(root.with_suffix(".csv")) as f:
        return root, request.param, list(csv.DictReader(f))


@pytest.mark.parametrize("flatten", [False, True])
def test_pick_shows_one_world_with_the_stage_settings(sweep, tmp_path, flatten):
    root, layout, rows = sweep
    batch = Usd.Stage.Open(str(root.parent / "drop.batch_0000.usdc"))
    for world in (0, 3):
        out = tmp_path / f"w{world}.usdc"
        code, text, err = run("pick", root, "--world", world, "--out", out, *(["--flatten"] if flatten else []))
        assert code == 0, err
        stage = Usd.Stage.Open(str(out))
        assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0 and UsdGeom.GetStageUpAxis(stage) == "Y"
        assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (0, FRAMES)
        assert stage.GetTimeCodesPerSecond() == FPS and stage.GetFramesPerSecond() == FPS
        assert stage.GetDefaultPrim().GetPath() == "/World"
        assert [p.GetName() for p in stage.GetDefaultPrim().GetChildren()] == ["ball", "floor"]  # one world only
        own = UsdGeom.Points(batch.GetPrimAtPath(f"/Worlds/world_{world:06d}/ball")).GetPointsAttr()
        got = UsdGeom.Points(stage.GetPrimAtPath("/World/ball")).GetPointsAttr()
        assert got.GetTimeSamples() == own.GetTimeSamples() == [float(f) for f in range(FRAMES + 1)]
        for f in range(FRAMES + 1):
            assert np.array_equal(np.array(got.Get(f)), np.array(own.Get(f)))
        params = stage.GetPrimAtPath("/World").GetCustomDataByKey("warpsim")["params"]
        assert params["height"] == pytest.approx(float(rows[world]["height"]), rel=1e-9)
        assert params["restitution"] == pytest.approx(float(rows[world]["restitution"]), rel=1e-9)
        if flatten:  # self-contained: no reference to the batch layer
            assert not Sdf.Layer.FindOrOpen(str(out)).GetCompositionAssetDependencies()


def test_roots_name_worlds_in_order_and_carry_their_parameters(sweep):
    root, layout, rows = sweep
    stage = Usd.Stage.Open(str(root))
    top = stage.GetPrimAtPath("/World")
    if layout == "grid":
        prims = top.GetChildren()
        assert [p.GetName() for p in prims] == [f"world_{g:06d}" for g in range(4)]
    else:
        prims = []
        vset = top.GetVariantSets().GetVariantSet("world")
        assert vset.GetVariantNames() == [f"world_{g:06d}" for g in range(4)]
    for g, row in enumerate(rows):
        if layout != "grid":
            vset.SetVariantSelection(f"world_{g:06d}")
        data = (prims[g] if prims else top).GetCustomDataByKey("warpsim")
        assert data["world"] == g and data["params"]["height"] == pytest.approx(float(row["height"]), rel=1e-9)


@pytest.mark.parametrize("args, words", [
    (["--world", "4"], ["--world 4 is out of range", "worlds 0..3"]),
    (["--world", "-1"], ["--world -1 is out of range"]),
    (["--world", "1", "--out", "x.txt"], ["must end in .usd, .usda or .usdc"]),
])
def test_bad_picks_exit_2_with_one_line(sweep, tmp_path, args, words):
    root, _, _ = sweep
    argv = ["pick", root, *args] + ([] if "--out" in args else ["--out", tmp_path / "w.usda"])
    code, out, err = run(*argv)
    assert code == 2, (out, err)
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("warpsim: error:"), err
    for word in words:
        assert word in lines[0]
    code, _, err = run("pick", tmp_path / "none.usda", "--world", 0, "--out", tmp_path / "w.usda")
    assert code == 2 and "no sweep root" in err and len(err.strip().splitlines()) == 1
