"""Sweeps on a Ray cluster (``warpsim sweep ... --ray``): same results as one process, faults, resume.

One local Ray cluster with 2 CPUs is shared by the module (Ray starts slowly on two cores); world
counts and frames are tiny. The single-process sweep is the oracle: the Ray sweep must give the
same table (byte for byte) and the same per-world time samples through the root's ``world``
variant set, also after a worker was killed mid-batch and after the driver was killed and the
sweep resumed.
"""
from __future__ import annotations

import os

import numpy as np
import pytest

from warpsim.distributed.batches import load_rows, publish_batch, split_batches, temp_batch_dir, tree_checksum
from warpsim.distributed.manifest import SweepManifest, manifest_path
from warpsim.worlds import run_batch, sample_worlds, write_sweep_root, write_table

SCENE = "springs"
VARY = ["stiffness=50:2000", "damping=0.01,0.5"]
WORLDS = 8
FRAMES = 40


# --- no cluster needed ---------------------------------------------------------------------------

def test_split_batches_cover_every_world_once():
    assert split_batches(10, 3) == [(0, 3), (3, 3), (6, 3), (9, 1)]
    assert split_batches(4, 4) == [(0, 4)]
    for n, b in [(1, 1), (64, 16), (65, 16), (7, 100)]:
        worlds = [w for first, count in split_batches(n, b) for w in range(first, first + count)]
        assert worlds == list(range(n))
    with pytest.raises(ValueError, match="batch-size 0"):
        split_batches(5, 0)
    with pytest.raises(ValueError, match="world count 0"):
        split_batches(0, 4)


def test_publish_is_whole_and_manifest_detects_a_changed_batch(tmp_path):
    final = str(tmp_path / "s.batches" / "batch_0000")
    os.makedirs(os.path.dirname(final))
    tmp = temp_batch_dir(final)
    with open(os.path.join(tmp, "layer.usdc"), "wb") as fh:
        fh.write(b"first")
    sha = publish_batch(tmp, final, [{"world": 0, "x": 1.5}])
    assert not os.path.exists(tmp) and sha == tree_checksum(final)
    assert load_rows(final) == [{"world": 0, "x": 1.5}]
    # a rerun replaces the folder whole: no file of the old run survives
    with open(os.path.join(final, "stray.txt"), "w") as fh:
        fh.write("old")
    tmp = temp_batch_dir(final)
    with open(os.path.join(tmp, "layer.usdc"), "wb") as fh:
        fh.write(b"second")
    sha2 = publish_batch(tmp, final, [{"world": 0, "x": 2.5}])
    assert sorted(os.listdir(final)) == ["layer.usdc", "rows.pkl"] and sha2 != sha
    assert os.listdir(os.path.dirname(final)) == ["batch_0000"]

    out = str(tmp_path / "s.usda")
    m = SweepManifest.new(manifest_path(out), {"scene": "springs", "world_count": 1})
    m.record(0, {"dir": "s.batches/batch_0000", "sha256": sha2, "error": None})
    loaded = SweepManifest.load(manifest_path(out))
    assert loaded.finished(0) and not loaded.finished(1)
    assert loaded.mismatch({"scene": "springs", "world_count": 1}) is None
    assert "world_count=2" in loaded.mismatch({"scene": "springs", "world_count": 2})
    with open(os.path.join(final, "layer.usdc"), "ab") as fh:  # a damaged batch is not trusted
        fh.write(b"!")
    assert not loaded.finished(0)
    with pytest.raises(FileNotFoundError, match="no manifest"):
        SweepManifest.load(str(tmp_path / "none.ray-manifest.json"))


# --- on a local cluster ---------------------------------------------------------------------------

@pytest.fixture(scope="module")
def cluster():
    """A local Ray cluster with 2 CPUs for the whole module; yields its address."""
    import logging

    import ray  # the ray extra (.ci/run installs it): these tests fail, never skip, without it

    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, logging_level=logging.ERROR)
    try:
        yield ray.get_runtime_context().gcs_address
    finally:
        ray.shutdown()


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The single-process sweep: (worlds, table text, {world: samples})."""
    folder = tmp_path_factory.mktemp("single")
    worlds = sample_worlds(SCENE, {}, VARY, WORLDS)
    rows = run_batch(SCENE, worlds, frames=FRAMES, device="cpu", layer_path=str(folder / "s.worlds.usdc"))
    table = write_table(str(folder / "s.csv"), rows)
    root = write_sweep_root(str(folder / "s.usda"), [str(folder / "s.worlds.usdc")], WORLDS)
    return worlds, _read(table), _samples(root, WORLDS)


def _read(path):
    with open(path) as fh:
        return fh.read()


def _samples(root, world_count):
    """{world: {attribute path: array (frames, ...)}} read through the root's variant set."""
    from pxr import Usd

    stage = Usd.Stage.Open(str(root))
    vset = stage.GetPrimAtPath("/World").GetVariantSets().GetVariantSet("world")
    names = vset.GetVariantNames()
    assert len(names) == world_count
    out = {}
    for w, name in enumerate(sorted(names)):
        vset.SetVariantSelection(name)
        samples = {}
        for prim in Usd.PrimRange(stage.GetPrimAtPath("/World")):
            for attr in prim.GetAttributes():
                times = attr.GetTimeSamples()
                if times and attr.GetName() in ("points", "velocities"):
                    key = str(attr.GetPath()).replace(name, "W")
                    samples[key] = np.array([np.asarray(attr.Get(t)) for t in times])
        assert samples, f"world {w} has no time samples"
        out[w] = samples
    return out


def _assert_same(reference, table_path, root):
    _worlds, table, samples = reference
    assert _read(table_path) == table
    got = _samples(root, len(samples))
    for w in samples:
        assert got[w].keys() == samples[w].keys()
        for key in samples[w]:
            np.testing.assert_allclose(got[w][key], samples[w][key], rtol=0, atol=1e-6, err_msg=f"world {w} {key}")


def test_ray_sweep_equals_single_process_and_survives_a_killed_worker(cluster, reference, tmp_path):
    from warpsim.distributed.ray_sweep import run_ray_sweep

    worlds = reference[0]
    marker = str(tmp_path / "killed.marker")
    out = str(tmp_path / "ray" / "s.usda")
    result = run_ray_sweep(SCENE, worlds, frames=FRAMES, out_path=out, table_path=str(tmp_path / "ray" / "s.csv"),
                           device="cpu", batch_size=3, _kill_once=marker)
    # one worker was SIGKILLed after writing its layer, before publishing it; Ray ran the batch again
    killed_batch, killed_pid = map(int, _read(marker).split())
    assert result["batches"][killed_batch]["pid"] != killed_pid
    assert result["ran"] == [0, 1, 2] and result["skipped"] == []
    assert [r["world"] for r in result["rows"]] == list(range(WORLDS))
    _assert_same(reference, result["table"], result["root"])
    # nothing partial is left or referenced: only the three published batch folders
    assert sorted(os.listdir(tmp_path / "ray" / "s.batches")) == ["batch_0000", "batch_0001", "batch_0002"]
    assert ".tmp-" not in _read(result["root"])
