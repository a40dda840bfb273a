"""A sweep's size on disk (issue 42): topology stored once, springs kept as their particles' points
(curves drawn from them), the size said before the first step and a refusal when the disk is short.

The budget is the issue's: 40 MB for 16 teapots x 60 frames (61 frames written, 0..60), i.e.
40e6 / (16 x 61) = 40,984 bytes a world a frame. The test runs the README's teapot sweep with 4
worlds over 10 frames (11 written) and holds every file it writes (batch layer, chunks, manifest,
chunk index, table, record, manifest of the sweep, root) to that budget scaled by the world-frames
written: 40e6 x (4 x 11) / (16 x 61) = 1.80 MB (the files that do not grow with worlds and frames
count in full, so the scaled budget is the stricter one).
"""
from __future__ import annotations

import io
import os
import re

import numpy as np
import pytest

pytest.importorskip("pxr")

from warpsim.cli import main

BUDGET_16x60 = 40e6  # [bytes] 16 teapots x 60 frames (frames 0..60)
FRAMES = 10
WORLDS = 4
SWEEP = ["sweep", "teapot", "--worlds", str(WORLDS), "--vary", "stiffness=20:60", "--vary", "restitution=0.2,0.5,0.8",
         "--sample", "lhs", "--seed", "1", "--frames", str(FRAMES), "--device", "cpu", "--no-progress",
         "--no-thumbnails"]
UNITS = {"bytes": 1, "KiB": 1 << 10, "MiB": 1 << 20, "GiB": 1 << 30}


def run(*argv):
    out, err = io.StringIO(), io.StringIO()
    code = main([str(a) for a in argv], out=out, err=err)
    return code, out.getvalue(), err.getvalue()


@pytest.fixture(scope="module")
def sweep(tmp_path_factory):
    from warpsim.sweeps import preflight

    folder = tmp_path_factory.mktemp("size")
    large = preflight.LARGE_OUTPUT_BYTES
    preflight.LARGE_OUTPUT_BYTES = 0  # 4 x 11 frames write ~0.8 MB: below the line a large sweep prints
    try:
        code, out, err = run(*SWEEP, "--out", folder / "t.usda")
    finally:
        preflight.LARGE_OUTPUT_BYTES = large
    assert code == 0, err
    written = sum(os.path.getsize(os.path.join(d, f)) for d, _, files in os.walk(folder) for f in files)
    return {"root": folder / "t.usda", "layer": folder / "t.batch_0000.usdc", "out": out, "err": err,
            "written": written}


def test_a_teapot_sweep_fits_the_budget(sweep):
    budget = BUDGET_16x60 * WORLDS * (FRAMES + 1) / (16 * 61)
    assert sweep["written"] <= budget, f"{sweep['written']:,} bytes written, budget {budget:,.0f}"


def test_the_sweep_says_its_size_before_it_starts(sweep):
    said = re.search(r"writing about ([\d.]+) (bytes|KiB|MiB|GiB) to .*4 worlds x 11 frames", sweep["err"])
    assert said, sweep["err"]
    assert sweep["err"].index(said.group(0)) == 0  # before anything else the sweep says
    estimate = float(said.group(1)) * UNITS[said.group(2)]
    assert abs(estimate - sweep["written"]) <= 0.25 * sweep["written"], (estimate, sweep["written"])


def test_topology_is_stored_once_and_every_world_inherits_it(sweep):
    from pxr import Sdf, Usd, UsdGeom

    from warpsim.scenes import get_scene
    from warpsim.sweeps.usd import SHARED

    layer = Sdf.Layer.FindOrOpen(str(sweep["layer"]))
    valued = []  # (prim path, attribute) of every attribute spec holding a value in the batch layer

    def visit(path):
        spec = layer.GetObjectAtPath(path)
        if isinstance(spec, Sdf.AttributeSpec) and spec.HasDefaultValue():
            valued.append((str(path.GetPrimPath()), spec.name))

    layer.Traverse(Sdf.Path.absoluteRootPath, visit)
    assert ("/WorldShared/teapot", "faceVertexIndices") in valued
    assert ("/WorldShared/springs", "warpsim:segments") in valued
    assert all(p.startswith(SHARED + "/") for p, _ in valued), [v for v in valued if not v[0].startswith(SHARED)]
    assert len(set(valued)) == len(valued)  # each value once in the layer
    cls = get_scene("teapot")
    scene = cls(cls.resolve_params({}), device="cpu")
    faces = (scene.body.faces - scene.body.particle_start).reshape(-1)
    springs = scene.model.spring_indices.numpy().reshape(-1, 2)
    stage = Usd.Stage.Open(str(sweep["layer"]))
    for w in range(WORLDS):
        world = f"/Worlds/world_{w:06d}"
        mesh = UsdGeom.Mesh(stage.GetPrimAtPath(f"{world}/teapot"))
        assert np.array_equal(np.asarray(mesh.GetFaceVertexIndicesAttr().Get()), faces)
        assert len(mesh.GetPointsAttr().GetTimeSamples()) == FRAMES + 1  # points as time samples (Blender)
        points = stage.GetPrimAtPath(f"{world}/springs")
        assert points.GetTypeName() == "Points"
        assert np.array_equal(np.asarray(points.GetAttribute("warpsim:segments").Get()).reshape(-1, 2), springs)
        x = np.asarray(points.GetAttribute("points").Get(FRAMES))
        assert x.shape == (scene.model.particle_count, 3)  # one point a particle, not two a spring
        assert np.array_equal(x[: scene.body.surface_count], np.asarray(mesh.GetPointsAttr().Get(FRAMES)))


def test_readers_draw_the_springs_a_full_cache_holds(sweep, tmp_path):
    """World 2 re-run alone writes its full cache (springs as curves, bit for bit the sweep's
    world); the viewer and the exporter draw the sweep's springs from its points exactly as they
    draw the full cache's curves; the picked world opens with pxr with the expected prims, its
    springs written as the full cache's curves."""
    from pxr import Usd

    from warpsim.browse.pick import pick_world
    from warpsim.render.export import read_frame
    from warpsim.sweeps.rerun import first_difference, rerun_world
    from warpsim.viewer.playback import CacheReader

    full = rerun_world(sweep["root"], 2, out=tmp_path / "w2.usda", device="cpu")
    assert first_difference(sweep["root"], 2, full) is None
    picked = pick_world(sweep["root"], 2, tmp_path / "w2.usdc", flatten=True)
    stage = Usd.Stage.Open(picked)
    assert {p.GetName(): p.GetTypeName() for p in stage.GetPrimAtPath("/World").GetChildren()} == \
        {"teapot": "Mesh", "springs": "BasisCurves", "walls": "Mesh", "floor": "Mesh"}  # one world: the full form
    cached = Usd.Stage.Open(str(full))
    assert cached.GetPrimAtPath("/World/springs").GetTypeName() == "BasisCurves"
    frame = FRAMES // 2
    a, b = CacheReader(picked).items(frame)["springs"], CacheReader(str(full)).items(frame)["springs"]
    assert a.kind == b.kind == "segments" and np.array_equal(a.points, b.points) and a.radius == b.radius
    ends = []
    for path in (picked, full):
        part = {p.name: p for p in read_frame(path, frame)[1]}["springs"]
        assert part.kind == "curves"
        ends.append(part.vertices[part.segments])
    assert np.array_equal(ends[0], ends[1])


def test_the_query_refines_from_the_particles_true_positions(sweep):
    """The occupancy record's source prim is the springs' points; read back they are the
    particles' positions (the curves' gathered ends were read as particles before)."""
    from pxr import Usd

    from warpsim.browse.occupancy import OccupancyRecord, occupancy_path
    from warpsim.browse.query import cached_positions

    record = OccupancyRecord.load(occupancy_path(sweep["root"]))
    assert record.source_prim == "springs"
    got = cached_positions(sweep["root"], record)(3, 8, 10)  # (3 frames, 538, 3)
    stage = Usd.Stage.Open(str(sweep["layer"]))
    mesh = stage.GetPrimAtPath("/Worlds/world_000003/teapot").GetAttribute("points")
    for k, f in enumerate(range(8, 11)):
        surface = np.asarray(mesh.Get(record.first_frame + f))
        assert np.array_equal(got[k, : len(surface)], surface)


def test_a_sweep_larger_than_the_free_disk_is_refused_before_it_runs(tmp_path, monkeypatch):
    from warpsim.sweeps import preflight

    monkeypatch.setattr(preflight, "free_disk_bytes", lambda path: 100 << 10)  # the sweep writes ~0.8 MB
    code, _, err = run(*SWEEP, "--out", tmp_path / "big" / "t.usda", "--store", "all")  # asked for: refused
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1, err
    assert "writes about" in lines[0] and "100 KiB free" in lines[0] and "--worlds" in lines[0], lines[0]
    assert not os.path.exists(tmp_path / "big" / "t.batch_0000.usdc")
    code, out, err = run(*SWEEP, "--out", tmp_path / "fits" / "t.usda", "--no-thumbnails")  # issue 50: by default
    assert code == 0 and "store: none" in out and "half the free disk" in out, out + err  # it keeps what fits
    assert not [f for f in os.listdir(tmp_path / "fits") if ".batch_" in f]
    assert preflight.check_disk(tmp_path / "t.usda", 5 << 20, free=6 << 20) is None  # small: nothing to say
    line = preflight.check_disk(tmp_path / "t.usda", 50 << 20, free=60 << 20)
    assert line.startswith("writing about 50 MiB to ") and "60 MiB free" in line


def test_a_layer_of_the_former_form_is_not_resumed_into(tmp_path):
    """A batch layer written before the worlds inherited ``/WorldShared`` (its chunks hold the
    curves' segment ends) is refused by a resume, which would mix the two forms in one layer."""
    from pxr import Sdf

    from warpsim.sweeps.sweep import run_batch
    from warpsim.sweeps.usd import SHARED

    worlds = [{"stiffness": 50.0}, {"stiffness": 400.0}]
    part = tmp_path / "part.usdc"
    run_batch("springs", worlds, frames=7, device="cpu", layer_path=part, chunk_size=4)
    layer = Sdf.Layer.FindOrOpen(str(part))
    edit = Sdf.BatchNamespaceEdit()
    edit.Add(SHARED, Sdf.Path.emptyPath)  # the former form: no class (prims declared per world)
    assert layer.Apply(edit) and layer.Save()
    with pytest.raises(ValueError, match="earlier warpsim"):
        run_batch("springs", worlds, frames=12, device="cpu", layer_path=part, chunk_size=4, resume_frame=8)
