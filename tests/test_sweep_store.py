"""Issue 50: every world's frame data at once (the scene's frame_arrays) equals the per-world
frame_data() on a swapped-in state, sample for sample; the sweep's --store modes."""
import os

import numpy as np
import pytest

from warpsim.scenes import get_scene
from warpsim.sweeps.sweep import make_batch
from warpsim.usd.frame_arrays import described, world_samples
from warpsim.sweeps.usd import BatchLayerWriter

# every scene a WorldBatch steps (small sizes), with a key that varies between its worlds
SWEEPABLE = [
    ("bounce", {}, "restitution", [0.3, 0.8]),
    ("springs", {}, "stiffness", [50.0, 200.0]),
    ("teapot", {"resolution": 6}, "stiffness", [20.0, 60.0]),
    ("teapot", {"resolution": 6, "obstacle": "paddle"}, "stiffness", [20.0, 60.0]),
    ("hair", {"strands": 8, "segments": 4}, "mass", [0.001, 0.002]),
    ("donuts", {"count": 2}, "stiffness", [1000.0, 2000.0]),
    ("cloth", {"resolution": 6, "integrator": "semi_implicit_euler"}, "structural", [500.0, 900.0]),
    ("wall", {}, "ball_speed", [3.0, 5.0]),
]


@pytest.mark.parametrize("name,fixed,key,values", SWEEPABLE, ids=[f"{s[0]}-{i}" for i, s in enumerate(SWEEPABLE)])
def test_batch_frame_data_equals_each_worlds_frame_data(tmp_path, name, fixed, key, values):
    cls = get_scene(name)
    params = [{**fixed, key: v} for v in values]
    batch = make_batch(cls, params, device="cpu")
    writer = BatchLayerWriter(tmp_path / f"{name}.usdc", batch.scene, 0, batch.world_count, 25.0)  # declares
    for _ in range(2):  # frame 0 and a stepped frame (the worlds differ by then)
        x, v = batch.world_slices()
        batched = batch.batch_frame_data(x, v)
        if name == "wall":  # its springs are each world's unbroken ones: asked world by world
            assert batched is None and described(batch.scene) is None
            break
        assert batched is not None
        per = [batch.world_frame_data(x[w], v[w], w) for w in range(batch.world_count)]
        for prim, decl in writer.dynamic.items():
            every = world_samples(decl, batched[prim], 3, batch.world_count)
            for w, data in enumerate(per):
                one = decl.frame_samples(data[prim], 3)
                assert list(one) == list(every), prim  # the order samples are authored in
                for attr, value in one.items():
                    got = np.asarray(every[attr][w])
                    assert got.dtype == np.asarray(value).dtype and got.tobytes() == np.asarray(value).tobytes(), \
                        (prim, attr, w)
        if any(not np.array_equal(x[0], x[w]) for w in range(1, batch.world_count)):
            assert not all(np.array_equal(batched[p]["points"][0], batched[p]["points"][1])
                           for p in batched if "points" in batched[p])
        batch.advance(1.0 / 25.0, 2)


@pytest.mark.parametrize("name,fixed,key,values", [SWEEPABLE[0], SWEEPABLE[2], SWEEPABLE[4]],
                         ids=["bounce", "teapot", "hair"])
def test_batch_writing_gives_the_per_world_writers_bytes(tmp_path, name, fixed, key, values):
    """write_batch authors attribute by attribute over all worlds, write_worlds world by world:
    the chunk files (two chunks of 3 frames, 3 worlds) and their index are the same bytes."""
    import glob

    cls = get_scene(name)
    params = [{**fixed, key: v} for v in values + values[:1]]
    batch = make_batch(cls, params, device="cpu")
    for how in ("batch", "worlds"):
        os.makedirs(tmp_path / how)
    writers = {how: BatchLayerWriter(tmp_path / how / f"{name}.usdc", batch.scene, 0, batch.world_count, 25.0,
                                     chunk_size=3) for how in ("batch", "worlds")}
    for frame in range(5):
        x, v = batch.world_slices()
        writers["batch"].write_batch(frame, batch.batch_frame_data(x, v))
        writers["worlds"].write_worlds(frame, [batch.world_frame_data(x[w], v[w], w) for w in range(batch.world_count)])
        batch.advance(1.0 / 25.0, 2)
    for writer in writers.values():
        writer.close(name)
    files = {how: sorted(glob.glob(str(tmp_path / how / f"{name}.*chunk0*.usdc"))) for how in writers}
    assert len(files["batch"]) == len(files["worlds"]) == 2
    for a, b in zip(files["batch"], files["worlds"]):
        assert open(a, "rb").read() == open(b, "rb").read(), os.path.basename(a)


def test_lone_frame_data_derives_from_the_description(tmp_path):
    """A lone run's frame_data() is the description applied to its own state (the teapot's
    surface rows of the positions; the bounce's arrays passed through as the simulator holds them)."""
    teapot = get_scene("teapot")(get_scene("teapot").resolve_params({"resolution": 6}), device="cpu")
    data = teapot.frame_data()
    x = teapot.sim.state.positions.numpy()
    n = teapot.body.surface_count
    assert np.array_equal(data["teapot"]["points"], x[:n]) and np.array_equal(data["springs"]["points"], x)
    bounce = get_scene("bounce")(get_scene("bounce").resolve_params({}), device="cpu")
    BatchLayerWriter(tmp_path / "b.usdc", bounce, 0, 1, 25.0)  # declares its prims, writes nothing
    assert bounce.frame_data()["ball"]["points"] is bounce.sim.state.positions


def test_a_subclass_overriding_frame_data_alone_is_asked_per_world():
    """A scene subclass that overrides frame_data() without describing it keeps the per-world path."""
    cls = get_scene("bounce")

    class Odd(cls):
        def frame_data(self):
            data = super().frame_data()
            return {k: {"points": np.asarray(v["points"].numpy()) * 2.0, "velocities": v["velocities"]}
                    for k, v in data.items()}

    scene = Odd(cls.resolve_params({}), device="cpu")
    assert described(scene) is None
    assert described(cls(cls.resolve_params({}), device="cpu")) is not None


def _sweep(tmp_path, name, *extra):
    from warpsim.cli import main

    root = tmp_path / name / "s.usda"
    device = [] if "--devices" in extra else ["--device", "cpu"]
    code = main(["sweep", "bounce", "--worlds", "4", "--frames", "9", *device, "--vary",
                 "restitution=0.2:0.9", "--out", str(root), "--no-progress", *extra])
    assert code == 0
    return root


def _chunk_bytes(folder):
    return {f: open(os.path.join(folder, f), "rb").read() for f in sorted(os.listdir(folder)) if ".chunk0" in f}


def test_store_modes_keep_the_table_and_record_and_pick_re_runs_a_none_sweep(tmp_path, capsys):
    """--store none writes no batch layer but the same table, record and thumbnails; preview keeps
    every 4th frame and the last; a world picked (or re-run) from a none sweep equals the same world
    re-run from an all sweep, chunk for chunk, and its samples equal the all sweep's world."""
    from pxr import Sdf

    from warpsim.browse.pick import UnstoredWorldError, pick_world
    from warpsim.sweeps.rerun import first_difference, pick_or_rerun, rerun_world

    roots = {m: _sweep(tmp_path, m, "--store", m) for m in ("all", "preview", "none")}
    said = capsys.readouterr().out
    assert "store: none, no frames" in said and "store: preview, every 4th frame and the last" in said
    folder = {m: os.path.dirname(r) for m, r in roots.items()}
    assert not [f for f in os.listdir(folder["none"]) if ".batch_" in f]
    for m in ("preview", "none"):
        for f in ("s.csv", "s.occupancy.npz"):
            assert open(os.path.join(folder[m], f), "rb").read() == open(os.path.join(folder["all"], f), "rb").read()
        for f in os.listdir(os.path.join(folder["all"], "s.thumbs")):
            assert open(os.path.join(folder[m], "s.thumbs", f), "rb").read() == \
                open(os.path.join(folder["all"], "s.thumbs", f), "rb").read()
    preview = Sdf.Layer.FindOrOpen(os.path.join(folder["preview"], "s.batch_0000.usdc"))
    assert list(preview.customLayerData["warpsim"]["chunkEnds"]) == [9]
    chunk = Sdf.Layer.FindOrOpen(os.path.join(folder["preview"], [f for f in os.listdir(folder["preview"])
                                                                 if ".chunk0" in f][0]))
    assert list(chunk.ListTimeSamplesForPath("/Worlds/world_000001/ball.points")) == [0.0, 4.0, 8.0, 9.0]
    with pytest.raises(UnstoredWorldError, match="--store none"):  # nothing stored to pick from
        pick_world(roots["none"], 2, tmp_path / "pick_none" / "w.usda")
    picked = pick_or_rerun(roots["none"], 2, tmp_path / "pick_none" / "w.usda")
    again = rerun_world(roots["all"], 2, out=tmp_path / "rerun_all" / "w.usda")
    assert _chunk_bytes(os.path.dirname(picked)) == _chunk_bytes(os.path.dirname(again)) != {}
    assert first_difference(roots["all"], 2, picked) is None
    with pytest.raises(ValueError, match="out of range"):
        pick_or_rerun(roots["none"], 4, tmp_path / "x.usda")


def test_store_estimate_covers_each_mode():
    from warpsim.sweeps.usd import estimate_sweep_bytes, stored_frames

    assert [stored_frames(10, k) for k in (1, 4, 0)] == [10, 4, 0]  # 0, 4, 8 and the last, 9
    assert stored_frames(9, 4) == 3  # 0, 4, 8 (the last)
    cls = get_scene("bounce")
    scene = cls(cls.resolve_params({}), device="cpu")
    sizes = [estimate_sweep_bytes(scene, "/tmp/never_written.usdc", 100, 121, 25.0, k)["bytes"] for k in (1, 4, 0)]
    assert sizes[0] > 3 * sizes[1] > 0 and sizes[2] == 0


def test_thumbnails_past_the_opt_in_count_are_off_unless_asked(tmp_path, capsys, monkeypatch):
    from warpsim.browse import panel

    monkeypatch.setattr(panel, "OPT_IN_WORLDS", 3)
    root = _sweep(tmp_path, "many", "--no-thumbnails")
    assert not os.path.exists(os.path.join(os.path.dirname(root), "s.thumbs"))
    root = _sweep(tmp_path, "many")
    said = capsys.readouterr().out
    assert "thumbnails: none (4 worlds, over 3" in said and "--thumbnails draws them" in said
    assert not os.path.exists(os.path.join(os.path.dirname(root), "s.thumbs"))
    root = _sweep(tmp_path, "many", "--thumbnails")
    assert len(os.listdir(os.path.join(os.path.dirname(root), "s.thumbs"))) == 4


def test_view_of_a_sweep_that_stored_nothing_re_runs_the_world_on_demand(tmp_path):
    from warpsim.cli_common import UsageError
    from warpsim.sweeps.rerun import first_difference
    from warpsim.viewer.command import on_demand_world

    none = _sweep(tmp_path, "none", "--store", "none", "--no-thumbnails")
    every = _sweep(tmp_path, "all", "--store", "all", "--no-thumbnails")
    assert on_demand_world(str(every), 1) is None  # stored frames: played as they are
    got = on_demand_world(str(none), 1)
    try:
        assert got.world == 1 and os.path.isfile(got.path)
        assert first_difference(every, 1, got.path) is None  # the sweep's world, bit for bit
    finally:
        got.folder.cleanup()
    with pytest.raises(UsageError, match="out of range"):
        on_demand_world(str(none), 9)


def test_an_unstored_sweeps_viewer_re_runs_any_world_on_demand(tmp_path):
    """``warpsim view`` of a --store none sweep: the page's "world" box and "re-run and play" re-run
    another world in the background and play it (the sweep's world, bit for bit); a world out of
    range or a re-run that fails is said in the page, and the server goes on serving."""
    import socket

    pytest.importorskip("viser")
    from warpsim.sweeps.rerun import first_difference, manifest_path, pick_or_rerun
    from warpsim.viewer.command import on_demand_world
    from warpsim.viewer.unstored import UnstoredSweepViewer

    none = _sweep(tmp_path, "none", "--store", "none", "--no-thumbnails")
    every = _sweep(tmp_path, "all", "--store", "all", "--no-thumbnails")
    got = on_demand_world(str(none), 0)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    viewer = UnstoredSweepViewer(str(none), 0, got.path, got.folder, 4, pick_or_rerun, port=port).start()
    try:
        first_folder = got.folder.name
        viewer.request(2).join(120)
        assert viewer.world == 2 and "re-ran exactly" in viewer.status.content
        assert first_difference(every, 2, viewer.reader.path) is None  # world 2 of the sweep, bit for bit
        assert not os.path.exists(first_folder)  # the world played before is removed
        assert viewer.request(7) is None and "out of range" in viewer.status.content
        os.rename(manifest_path(none), manifest_path(none) + ".away")  # the next re-run cannot read it
        viewer.request(1).join(60)
        assert "could not be re-run" in viewer.status.content and viewer.world == 2
        assert viewer.server is not None and viewer.reader.path.endswith("world_000002.usda")
    finally:
        viewer.stop()
        if viewer.rerun_folder is not None:
            viewer.rerun_folder.cleanup()


def test_a_preview_layer_resumes_to_the_same_chunks(tmp_path):
    """--store preview with --resume: a layer resumed after its last completed chunk (frames 4..4
    of chunk 4: resumed at 5, as SweepStaging.resume_frame says; the frames before re-simulated
    without writing) holds the same chunk files as one run straight."""
    from warpsim.sweeps.sweep import run_batch

    worlds = [{"restitution": 0.3}, {"restitution": 0.8}]
    kw = dict(frames=13, device="cpu", chunk_size=4, store_every=4)
    run_batch("bounce", worlds, layer_path=tmp_path / "a" / "l.usdc", **kw)
    run_batch("bounce", worlds, layer_path=tmp_path / "b" / "l.usdc", **kw)
    run_batch("bounce", worlds, layer_path=tmp_path / "b" / "l.usdc", resume_frame=5, **kw)
    a, b = _chunk_bytes(tmp_path / "a"), _chunk_bytes(tmp_path / "b")
    assert a == b and sorted(a) == ["l.chunk000000.usdc", "l.chunk000004.usdc", "l.chunk000008.usdc",
                                    "l.chunk000012.usdc"]


def test_query_of_a_sweep_that_stored_nothing_answers_from_its_record(tmp_path, capsys):
    from warpsim.cli import main

    box = "--inside=-0.2,-0.1,-0.2,0.2,0.2,0.2@0:0.3"
    answers = {}
    for mode in ("all", "none"):
        root = _sweep(tmp_path, mode, "--store", mode, "--no-thumbnails")
        capsys.readouterr()
        assert main(["query", str(root), box]) == 0
        answers[mode] = capsys.readouterr().out
    assert "picked worlds: none written" in answers["none"] and "re-runs one" in answers["none"]
    assert answers["all"].split("picked worlds:")[0] == answers["none"].split("picked worlds:")[0]


@pytest.mark.parametrize("mode", ["none", "preview"])
def test_store_modes_over_two_devices_equal_one_device(tmp_path, mode):
    """--store none and preview over --devices cpu,cpu: the same table, occupancy record and
    thumbnails as on one device, and (preview) the same kept samples; a none sweep's scratch
    layers are gone afterwards and its worlds re-run from the root."""
    import glob
    import tempfile

    from warpsim.sweeps.rerun import pick_or_rerun

    before = set(glob.glob(os.path.join(tempfile.gettempdir(), "warpsim_sweep_last_*")))
    one = _sweep(tmp_path, "one", "--store", mode)
    two = _sweep(tmp_path, "two", "--store", mode, "--devices", "cpu,cpu")
    a, b = os.path.dirname(one), os.path.dirname(two)
    for f in ("s.csv", "s.occupancy.npz"):
        assert open(os.path.join(a, f), "rb").read() == open(os.path.join(b, f), "rb").read(), f
    pictures = sorted(os.listdir(os.path.join(a, "s.thumbs")))
    assert pictures == sorted(os.listdir(os.path.join(b, "s.thumbs"))) and len(pictures) == 4
    for f in pictures:
        assert open(os.path.join(a, "s.thumbs", f), "rb").read() == open(os.path.join(b, "s.thumbs", f), "rb").read()
    assert set(glob.glob(os.path.join(tempfile.gettempdir(), "warpsim_sweep_last_*"))) == before
    if mode == "none":
        assert not [f for f in os.listdir(b) if ".batch_" in f]
        picked = pick_or_rerun(two, 3, tmp_path / "w3two" / "w.usda")
        again = pick_or_rerun(one, 3, tmp_path / "w3one" / "w.usda")
        assert _chunk_bytes(os.path.dirname(picked)) == _chunk_bytes(os.path.dirname(again)) != {}
    else:
        assert _world_samples(a) == _world_samples(b) and len(_world_samples(a)) == 4


def _world_samples(folder):
    """{world: [(attribute, time, bytes)]} of every batch layer in ``folder``."""
    import glob

    from pxr import Usd

    out = {}
    for layer in sorted(glob.glob(os.path.join(folder, "s.batch_[0-9][0-9][0-9][0-9].usdc"))):
        stage = Usd.Stage.Open(layer)
        for world in stage.GetPrimAtPath("/Worlds").GetChildren():
            out[world.GetName()] = [(str(at.GetPath()).split("/", 3)[-1], t, np.asarray(at.Get(t)).tobytes())
                                    for prim in Usd.PrimRange(world) for at in prim.GetAttributes()
                                    for t in at.GetTimeSamples()]
    return out
