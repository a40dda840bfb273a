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


def authored(stage):
    """{prim name: (type, {attribute: time-sample count})} of the default prim's children: the
    authored attributes a USD tool reads (``warpsim:segments`` only where it holds a value)."""
    return {p.GetName(): (p.GetTypeName(), {a.GetName(): a.GetNumTimeSamples() for a in p.GetAttributes()
                                            if a.HasAuthoredValue()})
            for p in stage.GetDefaultPrim().GetChildren()}


@pytest.mark.parametrize("scene", ["teapot", "springs"])
def test_a_picked_world_holds_the_curves_a_lone_run_writes(scene, tmp_path):
    """Blender reads no ``warpsim:segments`` (a sweep's compact springs): both kinds of pick file
    hold the world as its lone run writes it, springs as BasisCurves (the same prims, types,
    attributes, curve count and samples, bit for bit), and ``pick`` lists what the file holds."""
    from warpsim.sweeps.rerun import rerun_world
    from warpsim.usd.prims import SEGMENTS_ATTR

    root = tmp_path / "s.usda"
    code, _, err = run("sweep", scene, "--worlds", 2, "--vary", "stiffness=30:60", "--frames", 3, "--no-progress",
                       "--no-thumbnails", "--device", "cpu", "--out", root)
    assert code == 0, err
    sweep = Usd.Stage.Open(str(root))
    sweep_springs = sweep.GetPrimAtPath("/World/springs")
    assert sweep_springs.GetTypeName() == "Points" and sweep_springs.GetAttribute(SEGMENTS_ATTR).HasValue()
    lone = Usd.Stage.Open(str(rerun_world(root, 1, out=tmp_path / "lone.usda", device="cpu")))
    curves = lone.GetPrimAtPath("/World/springs")
    count = len(curves.GetAttribute("curveVertexCounts").Get())
    assert curves.GetTypeName() == "BasisCurves" and count > 0
    for flatten in (False, True):
        out = tmp_path / f"w1{'_flat' if flatten else ''}.usdc"
        code, text, err = run("pick", root, "--world", 1, "--out", out, *(["--flatten"] if flatten else []))
        assert code == 0, err
        stage = Usd.Stage.Open(str(out))
        assert authored(stage) == authored(lone)
        springs = stage.GetPrimAtPath("/World/springs")
        assert len(springs.GetAttribute("curveVertexCounts").Get()) == count
        assert not springs.GetAttribute(SEGMENTS_ATTR).HasValue()
        for name in ("points", "extent", "widths", "curveVertexCounts", "type", "primvars:displayColor"):
            ours, theirs = springs.GetAttribute(name), curves.GetAttribute(name)
            for t in [Usd.TimeCode.Default()] + [Usd.TimeCode(t) for t in theirs.GetTimeSamples()]:
                assert np.asarray(ours.Get(t)).tobytes() == np.asarray(theirs.Get(t)).tobytes(), (name, t)
        listed = {line.split()[0]: line.split(None, 2)[1:] for line in text.splitlines()[2:]}
        assert listed["springs"][0] == "BasisCurves" and f"{count:,} curves" in listed["springs"][1], text
        assert set(listed) == {p.GetName() for p in stage.GetDefaultPrim().GetChildren()}
        if flatten:
            assert SEGMENTS_ATTR not in springs.GetPropertyNames()


def test_a_damaged_sweeps_picked_springs_keep_the_readable_frames(tmp_path):
    """``--allow-damaged``: the springs of a sweep whose middle chunk file is truncated are written
    as curves at the frames that remain (0..23 and 48..60), the lost chunk's frames left out."""
    root = tmp_path / "s.usda"
    code, _, err = run("sweep", "springs", "--worlds", 2, "--vary", "stiffness=30:60", "--frames", 60, "--chunk", 24,
                       "--no-progress", "--no-thumbnails", "--device", "cpu", "--out", root)
    assert code == 0, err
    chunk = next(p for p in tmp_path.iterdir() if p.name.startswith("s.batch_0000.run") and
                 p.name.endswith("chunk000024.usdc"))
    chunk.write_bytes(chunk.read_bytes()[:100])
    code, text, err = run("pick", root, "--world", 1, "--out", tmp_path / "w1.usdc", "--allow-damaged")
    assert code == 0, err
    stage = Usd.Stage.Open(str(tmp_path / "w1.usdc"))
    springs = stage.GetPrimAtPath("/World/springs")
    assert springs.GetTypeName() == "BasisCurves"
    assert springs.GetAttribute("points").GetTimeSamples() == [float(f) for f in (*range(24), *range(48, 61))]
