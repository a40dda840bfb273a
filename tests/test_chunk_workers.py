"""Chunk files authored in worker processes (issue 50, writing off the critical path): the same
bytes as the stepping process writes itself, for a sweep's batch layer and a lone run's cache;
a worker's failure comes back as this process's error; workers die with their parent."""

import filecmp
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

pytest.importorskip("pxr")

from warpsim.process_pool import ProcessPool, RemoteError, SharedBlock, default_workers
from warpsim.sweeps.sweep import run_batch, sample_worlds
from warpsim.usd.writer import UsdCacheWriter


@pytest.fixture
def fixed_run_id(monkeypatch):
    """Both writers name their run alike (the run id is random otherwise)."""
    import types

    import warpsim.usd.writer as writer

    monkeypatch.setattr(writer, "secrets", types.SimpleNamespace(token_hex=lambda n: "abc123abc123"))


def files_equal(a, b):
    names = sorted(os.listdir(a))
    assert names == sorted(os.listdir(b))
    return {n: filecmp.cmp(os.path.join(a, n), os.path.join(b, n), shallow=False) for n in names}


def test_batch_layer_from_workers_is_byte_identical(tmp_path, fixed_run_id):
    """Six teapots x 12 frames in chunks of 5: every file (chunks, index, root, manifest) and every
    table row are the same written here (0 workers) or by 2 worker processes."""
    params = sample_worlds("teapot", {}, ["stiffness=20:60"], 6)
    rows = {}
    for workers in (0, 2):
        layer = tmp_path / f"w{workers}" / "s.batch_0000.usdc"
        rows[workers] = run_batch("teapot", params, frames=12, layer_path=str(layer), device="cpu", chunk_size=5,
                                  write_workers=workers)
    same = files_equal(tmp_path / "w0", tmp_path / "w2")
    assert len(same) == 6 and all(same.values()), same  # 3 chunks, index, manifest, root
    assert rows[0] == rows[2]


def test_workers_save_where_the_writer_saves(tmp_path, fixed_run_id):
    """Layers saved every few hundred bytes (crate saves append, so where a save falls shapes the
    file): five springs worlds x 9 frames in chunks of 4, the same files from 0 and 1 workers."""
    from warpsim.scenes import get_scene
    from warpsim.sweeps.sweep import make_batch
    from warpsim.sweeps.usd import BatchLayerWriter

    batch = make_batch(get_scene("springs"), [{"stiffness": 50.0 + 40.0 * w} for w in range(5)], device="cpu")
    frames = []
    for workers in (0, 1):
        os.makedirs(tmp_path / f"w{workers}")
        writer = BatchLayerWriter(tmp_path / f"w{workers}" / "s.usdc", batch.scene, 0, 5, 25.0, save_bytes=600,
                                  chunk_size=4, workers=workers)
        if not frames:
            for _ in range(9):
                x, v = batch.world_slices()
                frames.append({p: {k: np.array(a, copy=True) for k, a in d.items()}
                               for p, d in batch.batch_frame_data(x, v).items()})
                batch.advance(1.0 / 25.0, 2)
        for frame, data in enumerate(frames):
            writer.write_batch(frame, data)
        writer.close("springs")
    same = files_equal(tmp_path / "w0", tmp_path / "w1")
    assert len(same) == 6 and all(same.values()), same  # 3 chunks, index, manifest, root


def test_lone_cache_from_a_worker_is_byte_identical(tmp_path, fixed_run_id):
    """A lone run's cache with values whose length changes every frame (kept as copies, not in
    shared memory) and an attribute written only when it changes: the same bytes either way."""
    rng = np.random.default_rng(3)
    frames = [(rng.random((5 + f % 4, 3), dtype=np.float32), np.float32(f // 4)) for f in range(11)]
    for workers in (0, 1):
        w = UsdCacheWriter(tmp_path / f"w{workers}" / "c.usda", fps=30, chunk_size=4, run_id="fixed1",
                           workers=workers)
        w.add_points("blob", radius=0.01, count_changes=True)
        w.add_attribute("blob", "warpsim:level", "float")
        with w:
            for f, (x, level) in enumerate(frames):
                w.write_frame(f, {"blob": {"points": x, "velocities": 2 * x, "ids": np.arange(len(x)),
                                           "warpsim:level": level}})
    same = files_equal(tmp_path / "w0", tmp_path / "w1")
    assert len(same) == 6 and all(same.values()), same  # 3 chunks, index, manifest, root
    from pxr import Usd

    stage = Usd.Stage.Open(str(tmp_path / "w1" / "c.usda"))
    got = np.asarray(stage.GetPrimAtPath("/World/blob").GetAttribute("points").Get(7.0))
    assert np.array_equal(got, frames[7][0])


def test_a_workers_error_is_the_callers():
    with ProcessPool(1) as pool:
        with pytest.raises(RemoteError, match="invalid literal") as caught:
            pool.submit("builtins:int", "not a number").result()
        assert caught.value.kind == "ValueError"
        assert pool.submit("math:hypot", 3.0, 4.0).result() == 5.0  # the worker serves on
        with pytest.raises(RemoteError) as caught:
            pool.submit("os:listdir", "/no/such/folder").result()
        assert caught.value.kind == "FileNotFoundError" and caught.value.errno == 2


def test_shared_memory_reaches_the_worker():
    block = SharedBlock(4 * 6)
    try:
        block.array(0, (2, 3), np.float32)[...] = [[1, 2, 3], [4, 5, 6]]
        with ProcessPool(1) as pool:
            total = pool.submit("tests.test_chunk_workers:_sum_shared", block.ref(0, (2, 3), np.float32)).result()
        assert total == 21.0
    finally:
        block.release()


def _sum_shared(ref):
    from warpsim.process_pool import attach

    view, handle = attach(ref)
    total = float(view.sum())
    del view
    handle.close()
    return total


def test_workers_die_with_their_parent(tmp_path):
    """A parent killed with SIGKILL takes its workers with it (no orphan writes a killed run's
    temporaries)."""
    script = ("import sys, time; from warpsim.process_pool import ProcessPool; p = ProcessPool(2); "
              "print(' '.join(str(q.pid) for q in p._procs), flush=True); time.sleep(60)")
    parent = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True,
                              cwd=os.path.dirname(os.path.dirname(__file__)))
    pids = [int(p) for p in parent.stdout.readline().split()]
    assert len(pids) == 2
    parent.send_signal(signal.SIGKILL)
    parent.wait()
    deadline = time.time() + 20
    alive = pids
    while alive and time.time() < deadline:
        alive = [p for p in alive if os.path.exists(f"/proc/{p}") and "Z" not in _state(p)]
        time.sleep(0.05)
    assert not alive, f"workers {alive} outlived their parent"


def test_close_does_not_wait_for_a_worker_to_tear_down():
    """close() returns once the jobs are done and the workers told to exit (a worker whose exit
    takes 1.5 s, as a CUDA context's teardown can, does not hold the sweep up); join() reaps them."""
    pool = ProcessPool(1)
    assert pool.submit("atexit:register", time.sleep, 1.5).result(timeout=60) is time.sleep
    t0 = time.monotonic()
    pool.close()
    assert time.monotonic() - t0 < 1.0
    assert pool.join(timeout=60)
    assert time.monotonic() - t0 >= 1.4 and all(proc.returncode == 0 for proc in pool._procs)


def _state(pid):
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(")")[-1].split()[0]
    except OSError:
        return "Z"


def test_default_workers_leaves_a_core_to_the_stepping_process():
    cores = len(os.sched_getaffinity(0))
    assert default_workers() == max(0, min(8, cores - 1))
    assert default_workers(jobs=1) <= 1
    assert default_workers(most=16) == max(0, min(16, cores - 1))


def test_warpsim_run_with_a_writer_process_writes_the_same_bytes(tmp_path, monkeypatch):
    """``warpsim run dam_break`` (a surface mesh whose size changes every frame) written by a
    worker process, as on a GPU, and by the run's own process: every file the same."""
    import io

    from warpsim.cli import main

    for workers in ("0", "1"):
        monkeypatch.setenv("WARPSIM_WRITE_WORKERS", workers)
        out, err = io.StringIO(), io.StringIO()
        code = main(["run", "dam_break", "--frames", "30", "--chunk", "8", "--set", "spacing=0.05",
                     "--out", str(tmp_path / workers / "d.usda"), "--no-progress", "--device", "cpu"], out, err)
        assert code == 0, err.getvalue()
    same = files_equal(tmp_path / "0", tmp_path / "1")
    assert len(same) >= 6 and all(same.values()), same


def test_thumbnails_read_and_encoded_by_workers_are_the_same_pictures(tmp_path):
    """A sweep's pictures drawn with worker processes reading the layer and encoding the PNGs
    are the bytes drawn in one process (the same geometry, camera and renderer)."""
    import io

    from warpsim.browse.occupancy import OccupancyRecord, occupancy_path
    from warpsim.browse.panel import thumbnail_camera
    from warpsim.browse.thumbs import draw_thumbnails
    from warpsim.cli import main
    from warpsim.render.renderer import Renderer

    out = tmp_path / "s.usda"
    code = main(["sweep", "bounce", "--worlds", "5", "--frames", "10", "--vary", "height=0.02:0.06", "--out", str(out),
                 "--no-progress", "--no-thumbnails", "--device", "cpu"], io.StringIO(), io.StringIO())
    assert code == 0
    record = OccupancyRecord.load(occupancy_path(out))
    camera = thumbnail_camera(record)
    for workers in (0, 1):
        folder = tmp_path / f"t{workers}"
        folder.mkdir()
        n = draw_thumbnails(str(folder), [str(tmp_path / "s.batch_0000.usdc")], camera, Renderer(128, 96, device="cpu"),
                            workers=workers)
        assert n == 5
    same = files_equal(tmp_path / "t0", tmp_path / "t1")
    assert len(same) == 5 and all(same.values()), same


def test_thumbnail_workers_started_during_the_sweep_draw_the_same_pictures(tmp_path, monkeypatch):
    """The thumbnails' workers a sweep starts once its frames are stepped (they warm up while the
    layer, record, table and root are completed) draw the bytes drawn in one process."""
    import io

    from warpsim.browse import thumbs
    from warpsim.cli import main

    started, drawn = [], []
    start, draw = thumbs.start_workers, thumbs.draw_thumbnails
    monkeypatch.setattr(thumbs, "start_workers", lambda *a: started.append(start(*a)) or started[-1])
    monkeypatch.setattr(thumbs, "draw_thumbnails", lambda *a, **k: drawn.append(k.get("pool")) or draw(*a, **k))
    for workers in (0, 2):
        monkeypatch.setattr(thumbs, "thumbnail_workers", lambda world_count, jobs=None, n=workers: n)
        code = main(["sweep", "bounce", "--worlds", "5", "--frames", "10", "--vary", "height=0.02:0.06", "--out",
                     str(tmp_path / f"w{workers}" / "s.usda"), "--no-progress", "--thumbnails", "--device", "cpu"],
                    io.StringIO(), io.StringIO())
        assert code == 0
    pools = [pool for pool in started if pool is not None]  # (none for the sweep drawing in this process)
    assert len(pools) == 1 and pools[0].workers == 2
    assert drawn == [None, pools[0]] and pools[0]._closed  # the early pool drew them, and was closed after
    same = files_equal(tmp_path / "w0" / "s.thumbs", tmp_path / "w2" / "s.thumbs")
    assert len(same) == 5 and all(same.values()), same
