"""Occupancy records and spacetime queries (``--inside`` / ``--outside``, ``warpsim query``).

The analytic check: balls dropped from heights on a grid fall freely (restitution 0, dt = 1 ms),
y(t) = h - g t^2 / 2, so which worlds have their ball inside a box during a window is known in
closed form; the sweep's answer (exact record: one particle per world) must match it, the
cell-only answer must match it up to one cell at the border, and ``warpsim query`` after the run
must print the same worlds as the sweep did."""
from __future__ import annotations

import io

import numpy as np
import pytest
import warp as wp

pytest.importorskip("pxr")

from warpsim.cli import main
from warpsim.kernels import occupancy as KO
from warpsim.browse.occupancy import OccupancyGrid, OccupancyRecord, occupancy_path
from warpsim.browse.query import answer_region, parse_region

G = 9.81
FPS, FRAMES = 50, 40  # 0.8 s, frame every 0.02 s
HEIGHTS = np.linspace(0.2, 1.6, 15)
BOX = "-0.5,0.4,-0.5,0.5,0.6,0.5"
WINDOW = (0.2, 0.5)


def run(*argv):
    out, err = io.StringIO(), io.StringIO()
    code = main([str(a) for a in argv], out=out, err=err)
    return code, out.getvalue(), err.getvalue()


def picked_worlds(out):
    return [int(line.split()[0]) for line in out.splitlines() if line.startswith("  ") and line.split()[0].isdigit()]


@pytest.fixture(scope="module")
def sweep(tmp_path_factory):
    root = tmp_path_factory.mktemp("occupancy") / "drop.usda"
    code, out, err = run("sweep", "bounce", "--worlds", len(HEIGHTS), "--vary", f"height={HEIGHTS[0]}:{HEIGHTS[-1]}",
                         "--set", "restitution=0", "--fps", FPS, "--substeps", 20, "--frames", FRAMES,
                         "--no-progress", "--out", root, "--device", "cpu",
                         "--inside", f"{BOX}@{WINDOW[0]}:{WINDOW[1]}", "--rank", "inside1_entry")
    assert code == 0, err
    return root, out


def free_fall(h, t):
    return np.maximum(h - 0.5 * G * t ** 2, 0.0)


def predicted(lo_y, hi_y, margin):
    """(surely in, surely out) world sets: the analytic height at the window's frames is inside
    [lo_y, hi_y] at some frame by more than ``margin`` / outside at every frame by more."""
    t = np.arange(round(WINDOW[0] * FPS), round(WINDOW[1] * FPS) + 1) / FPS
    y = free_fall(HEIGHTS[:, None], t[None, :])
    depth = np.minimum(y - lo_y, hi_y - y)  # > 0 inside
    return set(np.flatnonzero(depth.max(1) > margin)), set(np.flatnonzero(depth.max(1) < -margin))


def test_record_kernel_matches_numpy_cells(device):
    grid = OccupancyGrid.over([-1.0, 0.0, -0.5], [1.0, 1.0, 0.5], resolution=8)
    rng = np.random.default_rng(3)
    x = rng.uniform(-1.6, 1.6, size=(3, 50, 3)).astype(np.float32)  # 3 worlds, some points beyond the grid
    x[1, 7] = np.nan
    n, P = x.shape[:2]
    block = wp.zeros(n * grid.cell_count, dtype=wp.uint32, device=device)
    hit = wp.zeros(n * grid.cell_count, dtype=wp.uint8, device=device)
    samples = wp.zeros(n * 2 * P, dtype=wp.vec3, device=device)
    frame = wp.array([1], dtype=int, device=device)
    wp.launch(KO.record_cells, (n, P), inputs=[wp.array(x.reshape(-1, 3), dtype=wp.vec3, device=device), P,
                                               wp.array(np.arange(P, dtype=np.int32), dtype=int, device=device),
                                               wp.vec3(*grid.lo.astype(np.float32)),
                                               float(np.float32(1 / grid.cell_size)),
                                               wp.vec3i(*map(int, grid.dims)), frame, 2, hit, samples],
              device=device)
    wp.launch(KO.fold_cell_hits, hit.shape[0], inputs=[hit, frame, block], device=device)
    assert not hit.numpy().any()  # the marks are cleared for the next frame
    got = block.numpy().reshape(n, -1)
    want = np.zeros_like(got)
    for w in range(n):
        ok = np.isfinite(x[w]).all(1)
        want[w, grid.cells_of(x[w][ok])] = 1 << 1  # frame 1 -> bit 1
    assert np.array_equal(got, want)
    assert np.array_equal(samples.numpy().reshape(n, 2, P, 3)[:, 1], x, equal_nan=True)
    # beyond the grid: the outside layers (coordinate 0 and dims - 1) catch every point
    c = np.unravel_index(grid.cells_of(x[0]), tuple(grid.dims))
    beyond = (x[0] < grid.lo) | (x[0] >= grid.hi)
    for a in range(3):
        assert ((c[a] == 0) | (c[a] == grid.dims[a] - 1))[beyond[:, a]].all()


def test_inside_matches_free_fall_and_query_repeats_it(sweep):
    root, out = sweep
    record = OccupancyRecord.load(occupancy_path(root))
    assert record.exact and record.world_count == len(HEIGHTS) and record.frame_count == FRAMES + 1
    surely_in, surely_out = predicted(0.4, 0.6, 0.005)  # dt = 1 ms: the discrete fall is within 3 mm
    worlds = set(picked_worlds(out))
    assert surely_in <= worlds and not (worlds & surely_out)
    assert len(surely_in) + len(surely_out) >= len(HEIGHTS) - 2  # the test decides nearly every world
    # ranked by first entry into the box: analytic entry times are non-decreasing in the list
    entries = {}
    for line in out.splitlines():
        parts = line.split()
        if parts and parts[0].isdigit():
            entries[int(parts[0])] = float(parts[3])
    listed = picked_worlds(out)
    assert [entries[w] for w in listed] == sorted(entries[w] for w in listed)
    code, again, err = run("query", root, "--inside", f"{BOX}@{WINDOW[0]}:{WINDOW[1]}", "--rank", "inside1_entry")
    assert code == 0, err
    assert picked_worlds(again) == listed
    assert [ln for ln in again.splitlines() if ln.startswith("  ")] == \
        [ln for ln in out.splitlines() if ln.startswith("  ")]


def test_outside_is_the_complement_and_cells_are_conservative(sweep):
    root, _ = sweep
    code, out, err = run("query", root, "--outside", f"{BOX}@{WINDOW[0]}:{WINDOW[1]}")
    assert code == 0, err
    surely_in, surely_out = predicted(0.4, 0.6, 0.005)
    kept = set(picked_worlds(out))
    assert surely_out <= kept and not (kept & surely_in)
    # cells only (exact positions dropped): IN keeps a superset, within one cell of the box
    record = OccupancyRecord.load(occupancy_path(root))
    exact = answer_region(record, parse_region(f"{BOX}@{WINDOW[0]}:{WINDOW[1]}"))
    record.samples = None
    cells = answer_region(record, parse_region(f"{BOX}@{WINDOW[0]}:{WINDOW[1]}"))
    h = record.grid.cell_size
    near_in, _ = predicted(0.4 - h, 0.6 + h, 0.005)
    assert set(np.flatnonzero(exact.match)) <= set(np.flatnonzero(cells.match)) <= near_in | surely_in
    not_in = answer_region(record, parse_region(f"{BOX}@{WINDOW[0]}:{WINDOW[1]}", inside=False))
    assert np.array_equal(not_in.match, ~cells.match)


def _record_frames(batch, recorder, frames, frame_dt, substeps):
    """Steps and records as ``run_batch`` does; returns the recorder's record and the positions
    (frames + 1, N, 3) read back after each frame (after the batch froze its blown-up worlds)."""
    seen = [batch.sim.state.positions.numpy().copy()]
    recorder.update()
    recorder.after_frame()
    for _ in range(frames):
        batch.advance(frame_dt, substeps)
        recorder.update()
        recorder.after_frame()
        seen.append(batch.sim.state.positions.numpy().copy())
    return recorder.finish(), np.stack(seen)


@pytest.mark.parametrize("block_per_world", [False, True])
def test_cells_marked_inside_the_step_equal_the_separate_pass_and_numpy(device, block_per_world):
    """The shared-topology step marks the cells at each frame's last sub-step (both kernels); the
    record equals the separate pass over the positions bit for bit, and both equal the bits NumPy
    sets from the positions read back, over more than 32 frames (two flushes of the device's
    compaction) and with worlds flagged as blown up at different frames (frozen after the step)."""
    from warpsim.scenes import get_scene
    from warpsim.sweeps import sample_worlds
    from warpsim.worlds import WorldBatch
    from warpsim.browse.occupancy import OccupancyRecorder
    from warpsim.scenes.timing import resolve_timing

    cls = get_scene("springs")
    worlds = sample_worlds("springs", {"shape": "lattice", "count": 4}, ["stiffness=200:600", "gravity=3:12"], 6,
                           sample="lhs", seed=1)
    timing = resolve_timing(cls, cls.resolve_params(worlds[0]))
    substeps, frame_dt = timing.steps, timing.frame_dt
    frames = 40
    records = []
    for in_step in (True, False):
        batch = WorldBatch(cls, worlds, device=device, block_per_world=block_per_world)
        batch.max_speed = 2.0  # the worlds falling fastest are flagged (and frozen) first
        recorder = OccupancyRecorder(batch, frames, resolution=8, in_step=in_step)
        assert recorder.in_step == in_step
        record, seen = _record_frames(batch, recorder, frames, frame_dt, substeps)
        records.append(record)
        blown = batch.world_blown_frame.numpy()
    assert len(set(blown[blown >= 0])) >= 3 and (blown < 0).any()  # blown at different frames, one never
    step, apart = records
    for key in ("world_start", "pair_cell", "pair_bits"):
        assert getattr(step, key).tobytes() == getattr(apart, key).tobytes(), key
    n, P = len(worlds), step.world_particle_count
    want = np.zeros((n, step.grid.cell_count, 2), np.uint32)
    for f, x in enumerate(seen):
        for w in range(n):
            want[w, step.grid.cells_of(x[w * P:(w + 1) * P]), f // 32] |= np.uint32(1 << (f % 32))
    got = np.zeros_like(want)
    got[step.pair_world, step.pair_cell] = step.pair_bits
    assert np.array_equal(got, want)
    assert len(np.unique(step.pair_bits[:, 0])) > 3  # cells change over the frames


def test_two_runs_write_the_same_record(tmp_path):
    for name in ("a", "b"):
        code, _, err = run("sweep", "bounce", "--worlds", 3, "--vary", "height=0.1:0.3", "--frames", 40,
                           "--no-progress", "--device", "cpu", "--out", tmp_path / f"{name}.usda")
        assert code == 0, err
    a, b = (np.load(tmp_path / f"{n}.occupancy.npz") for n in "ab")
    for key in ("pair_cell", "pair_bits", "world_start", "samples", "lo", "dims"):
        assert np.array_equal(a[key], b[key]), key
    assert a["pair_bits"].shape[1] == 2  # 41 frames: two 32-frame words


@pytest.mark.parametrize("args, words", [
    (["--inside", "1,0,0,0,1,1@0:0.2"], ["x1 = 0 < x0 = 1", "lower corner first"]),
    (["--inside", "0,0,0,1,1,1@5:6"], ["outside the sweep's time", "0..0.8 s"]),
    (["--outside", "0,0,0,1,1@0:1"], ["six numbers"]),
    (["--inside", "0,0,0,1,1,1@0.5:0.1"], ["ends (0.1 s) before it starts"]),
    (["--inside", "0,0,0,1,1,1@0:1", "--rank", "inside2_time"], ["unknown metric"]),
])
def test_bad_regions_exit_2_with_one_line(sweep, args, words):
    root, _ = sweep
    for argv in (["query", root, *args],
                 ["sweep", "bounce", "--worlds", 2, "--vary", "height=0.1:0.2", "--fps", FPS, "--frames", FRAMES,
                  "--no-progress", "--out", root.parent / "never.usda", *args]):
        code, out, err = run(*argv)
        assert code == 2, (out, err)
        lines = err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("warpsim: error:"), err
        for word in words:
            assert word in lines[0]
    assert not (root.parent / "never.usda").exists()


def test_root_without_record_exits_2(sweep, tmp_path):
    root, _ = sweep
    import shutil

    for suffix in (".usda", ".csv", ".batch_0000.usdc"):
        shutil.copy(str(root)[:-5] + suffix, tmp_path / ("copy" + suffix))
    code, _, err = run("query", tmp_path / "copy.usda", "--inside", f"{BOX}@0:0.5")
    assert code == 2 and "no occupancy record" in err and len(err.strip().splitlines()) == 1, err
    code, _, err = run("query", tmp_path / "copy.csv", "--inside", f"{BOX}@0:0.5")
    assert code == 2 and err.startswith("warpsim: error:") and len(err.strip().splitlines()) == 1, err


def test_tracked_record_equals_the_cached_samples_and_their_cells(tmp_path):
    """--track records that particle only: its exact positions equal the USD samples bit for
    bit, and the packed cell bits decode to exactly the cells of those positions, frame by frame
    (41 frames: two 32-frame words)."""
    from pxr import Usd, UsdGeom

    root = tmp_path / "s.usda"
    code, _, err = run("sweep", "springs", "--worlds", 3, "--vary", "stiffness=100:400", "--set", "count=3",
                       "--frames", 40, "--no-progress", "--device", "cpu", "--out", root, "--track", "mid=1")
    assert code == 0, err
    record = OccupancyRecord.load(occupancy_path(root))
    assert record.track_names == ["mid"] and list(record.particles) == [1] and record.exact
    layer = Usd.Stage.Open(str(tmp_path / "s.batch_0000.usdc"))
    for w in range(3):
        attr = UsdGeom.Points(layer.GetPrimAtPath(f"/Worlds/world_{w:06d}/masses")).GetPointsAttr()
        cached = np.array([np.array(attr.Get(f))[1] for f in range(41)], np.float32)
        assert np.array_equal(record.samples[w, :, 0], cached)
        want = {(int(c), f) for f, c in enumerate(record.grid.cells_of(cached))}
        rows = slice(record.world_start[w], record.world_start[w + 1])
        bits = np.unpackbits(record.pair_bits[rows].view(np.uint8), axis=1, bitorder="little")
        got = {(int(c), int(f)) for c, row in zip(record.pair_cell[rows], bits) for f in np.flatnonzero(row)}
        assert got == want
        assert len({c for c, _ in want}) > 1  # the mass moves through several cells
    lo, hi = record.occupied_bounds()  # every recorded position lies in the occupied cells' bounds
    inner = record.samples.reshape(-1, 3)
    inner = inner[((inner >= record.grid.lo) & (inner < record.grid.hi)).all(1)]
    assert len(inner) and (inner >= lo - 1e-6).all() and (inner <= hi + 1e-6).all()


@pytest.mark.parametrize("args, words", [
    (["--occupancy-res", "0"], ["--occupancy-res 0", "1..256"]),
    (["--occupancy-bounds", "0,0,0,1,-1,1"], ["y1 = -1 < y0 = 0"]),
])
def test_bad_record_options_exit_2_before_running(tmp_path, args, words):
    code, out, err = run("sweep", "bounce", "--worlds", 2, "--vary", "height=0.1:0.2", "--frames", 5,
                         "--no-progress", "--out", tmp_path / "s.usda", *args)
    assert code == 2, (out, err)
    lines = err.strip().splitlines()
    assert len(lines) == 1 and all(w in lines[0] for w in words), err
    assert not (tmp_path / "s.usda").exists()


def test_answers_refined_from_the_cached_positions(tmp_path):
    """A chain of 10 masses keeps no exact positions in its record; the worlds the cells leave in
    doubt are read back from the USD cache, so the answer equals the brute-force one over every
    cached point; with no budget to read, the cells' answer is a superset within one cell."""
    from pxr import Usd, UsdGeom

    from warpsim.browse.query import cached_positions

    root = tmp_path / "c.usda"
    code, out, err = run("sweep", "springs", "--worlds", 6, "--vary", "stiffness=50:800:log", "--frames", 30,
                         "--no-progress", "--device", "cpu", "--out", root,
                         "--inside", "0.5,0.6,-0.1,1.2,0.95,0.1@0.2:0.5")
    assert code == 0, err
    record = OccupancyRecord.load(occupancy_path(root))
    assert not record.exact and record.source_prim in ("masses", "springs")
    assert "answers: exact (the cached positions)" in out
    layer = Usd.Stage.Open(str(tmp_path / "c.batch_0000.usdc"))
    f0, f1 = 0.2 * record.fps, 0.5 * record.fps
    lo, hi = np.array([0.5, 0.6, -0.1]), np.array([1.2, 0.95, 0.1])
    brute = []
    for w in range(6):
        attr = UsdGeom.Points(layer.GetPrimAtPath(f"/Worlds/world_{w:06d}/masses")).GetPointsAttr()
        pts = np.array([np.array(attr.Get(f)) for f in range(int(round(f0)), int(round(f1)) + 1)], np.float64)
        brute.append(bool(((pts >= lo) & (pts <= hi)).all(-1).any()))
    assert 0 < sum(brute) < 6  # the box separates the stiff chains from the soft ones
    assert picked_worlds(out) == [w for w in range(6) if brute[w]]
    region = parse_region("0.5,0.6,-0.1,1.2,0.95,0.1@0.2:0.5")
    refined = answer_region(record, region, cached_positions(root, record))
    cells = answer_region(record, region, cached_positions(root, record), budget=0)
    assert refined.exact and not cells.exact
    assert list(refined.match) == brute and (cells.match >= refined.match).all()


def test_flock_sweeps_keep_a_record(tmp_path):
    """Agent batches (flocks) record their agents too: the cells world w marks at frame 0 are
    exactly those of its cached agents."""
    root = tmp_path / "f.usda"
    code, out, err = run("sweep", "flock", "--vary", "seed=0,1", "--frames", 2, "--no-progress", "--device", "cpu",
                         "--out", root)
    assert code == 0, err
    record = OccupancyRecord.load(occupancy_path(root))
    assert record.world_count == 2 and record.frame_count == 3 and not record.exact
    from pxr import Usd, UsdGeom

    layer = Usd.Stage.Open(str(tmp_path / "f.batch_0000.usdc"))
    for w in range(2):
        rows = slice(record.world_start[w], record.world_start[w + 1])
        at0 = {int(c) for c, b in zip(record.pair_cell[rows], record.pair_bits[rows, 0]) if b & 1}
        agents = UsdGeom.PointInstancer(layer.GetPrimAtPath(f"/Worlds/world_{w:06d}/agents"))
        pts = np.array(agents.GetPositionsAttr().Get(0))
        assert len(pts) == record.world_particle_count and set(record.grid.cells_of(pts)) == at0
