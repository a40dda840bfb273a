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


@pytest.mark.parametrize("block_per_world", [False, True])
def test_cells_marked_at_each_worlds_own_last_sub_step(block_per_world):
    """The occupancy record marked inside the step (at each world's own last sub-step of a frame)
    equals the separate pass over the positions after the frame, with worlds of different counts."""
    from warpsim.browse.occupancy import OccupancyRecorder

    cls, worlds = sweep_worlds("springs")
    timing = sweep_timing(cls, worlds)
    records = []
    for in_step in (True, False):
        batch = WorldBatch(cls, worlds, device="cpu", block_per_world=block_per_world)
        batch.use_timing(timing)
        counts = batch.world_steps(timing.frame_dt, timing.steps)
        assert len(set(counts.tolist())) == 3 and (counts % 2 == 1).any(), counts  # an odd count ends in the spare
        recorder = OccupancyRecorder(batch, 6, resolution=16, exact_max=0, in_step=in_step)
        assert recorder.in_step == in_step
        recorder.update()
        recorder.after_frame()
        for _ in range(6):
            batch.advance(timing.frame_dt, timing.steps)
            recorder.update()
            recorder.after_frame()
        records.append(recorder.finish())
    step, apart = records
    assert len(np.unique(step.pair_bits[:, 0])) > 3  # cells change over the frames
    for key in ("world_start", "pair_cell", "pair_bits"):
        assert getattr(step, key).tobytes() == getattr(apart, key).tobytes(), key


def test_a_fixed_substeps_sweep_steps_every_world_alike(tmp_path):
    """--substeps N: every world takes N steps (the former shared count), and world N still equals its
    plain run with --substeps N."""
    from warpsim.sweeps.rerun import first_difference

    cls, worlds = sweep_worlds("springs")
    timing = sweep_timing(cls, worlds, substeps=12)
    batch = WorldBatch(cls, worlds, device="cpu")
    batch.use_timing(timing)
    assert batch.world_steps(timing.frame_dt, timing.steps).tolist() == [12, 12, 12]
    fixed, key, values, _ = SWEEPS["springs"]
    sets = [a for k, v in fixed.items() for a in ("--set", f"{k}={v}")]
    root = tmp_path / "sweep.usda"
    code, _, err = cli("sweep", "springs", *sets, "--vary", f"{key}={','.join(map(str, values))}", "--worlds", 3,
                       "--frames", FRAMES, "--device", "cpu", "--out", root, "--no-progress", "--substeps", 12)
    assert code == 0, err
    cache = tmp_path / "alone.usda"
    code, _, err = cli("run", "springs", *sets, "--set", f"{key}={values[0]}", "--frames", FRAMES, "--device", "cpu",
                       "--out", cache, "--no-progress", "--substeps", 12)
    assert code == 0, err
    assert first_difference(root, 0, cache) is None


def test_a_rerun_needs_no_count_from_the_manifest(tmp_path):
    """A re-run of a sweep whose worlds take different counts equals its samples with the manifest's
    frame_steps removed (null) as with it kept."""
    import json

    from warpsim.sweeps.rerun import first_difference, manifest_path, rerun_world

    fixed, key, values, extra = SWEEPS["cloth"]
    sets = [a for k, v in fixed.items() for a in ("--set", f"{k}={v}")]
    root = tmp_path / "sweep.usda"
    code, _, err = cli("sweep", "cloth", *sets, "--vary", f"{key}={','.join(map(str, values))}", "--worlds", 3,
                       "--frames", FRAMES, "--device", "cpu", "--out", root, "--no-progress", *extra)
    assert code == 0, err
    path = manifest_path(root)
    with open(path) as f:
        manifest = json.load(f)
    assert manifest["frame_steps"] is not None
    manifest["frame_steps"] = None
    with open(path, "w") as f:
        json.dump(manifest, f)
    for world in (0, 2):  # the fewest and the most steps a frame
        assert first_difference(root, world, rerun_world(root, world, out=tmp_path / f"w{world}.usda")) is None


def test_a_height_sweep_world_equals_its_plain_run_bit_for_bit():
    """A parameter that shifts positions (the teapot's drop height): each world starts where its own
    scene starts (the builder's float64 positions shifted in float64 and cast once, as the scene casts
    them; a float32 sum of world 0's positions and the shift was up to 1.2e-7 m off), so world N
    equals its plain run (built and stepped as ``warpsim run`` does) bit for bit."""
    from warpsim.scenes.timing import resolve_timing

    cls = get_scene("teapot")
    worlds = [{"resolution": "3", "height": h} for h in (0.6, 0.45, 0.8, 0.7123)]
    timing = sweep_timing(cls, worlds)
    batch = WorldBatch(cls, worlds, device="cpu")
    assert batch.shared  # the fused shared path (its initial state is the batch's, not the scene's)
    batch.use_timing(timing)
    start = batch.world_slices()[0]
    scenes = []
    for w, p in enumerate(worlds):
        scene = cls(p, device="cpu")
        scene.use_timing(resolve_timing(cls, scene.params, given=tuple(p)))
        assert scene.timing.steps == timing.steps and scene.timing.frame_dt == timing.frame_dt
        assert start[w].tobytes() == scene.sim.state.positions.numpy().tobytes(), w
        scenes.append(scene)
    assert len({s.tobytes() for s in start}) == len(worlds)
    for _ in range(FRAMES):
        batch.advance(timing.frame_dt, timing.steps)
        for scene in scenes:
            scene.advance(scene.timing.frame_dt, scene.timing.steps)
    end = batch.world_slices()[0]
    for w, scene in enumerate(scenes):
        assert end[w].tobytes() == scene.sim.state.positions.numpy().tobytes(), w
