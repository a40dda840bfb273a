"""Sweeps on a Ray cluster (``warpsim sweep ... --ray``): same results as one process, faults, resume.

One local Ray cluster with 2 CPUs is shared by the module (Ray starts slowly on two cores); world
counts and frames are tiny. The single-process sweep is the oracle: the Ray sweep must give the
same table (byte for byte) and the same per-world time samples through the root's ``world``
variant set, also after a worker was killed mid-batch and after the driver was killed and the
sweep resumed.
"""
from __future__ import annotations

import io
import json
import os
import re
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from warpsim.distributed.batches import load_rows, publish_batch, split_batches, temp_batch_dir, tree_checksum
from warpsim.distributed.manifest import SweepManifest, manifest_path
from warpsim.sweeps import run_batch, sample_worlds

SCENE = "springs"
VARY = ["stiffness=100,400,1000,1e9", "damping=0.01,0.5"]  # grid of 8; the last two worlds blow up
WORLDS = 8
FRAMES = 40
# one step of dt = 1/480 s (the scene's) per frame: the stiff worlds blow up (auto sub-steps would keep them stable)
FIXED_STEPS = ["--fps", "480", "--substeps", "1"]


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


def test_ray_options_without_ray_or_out_of_range_exit_2_with_one_line(tmp_path):
    from warpsim.cli import main

    base = ["sweep", SCENE, "--worlds", "2", "--vary", "stiffness=100,200", "--frames", "1", "--device", "cpu",
            "--out", str(tmp_path / "s.usda")]
    for extra, words in [(["--resume"], "--resume: no interrupted sweep"), (["--batch-size", "4"], "--batch-size goes"),
                         (["--ray", "--batch-size", "0"], "--batch-size 0: it must be >= 1"),
                         (["--ray", "--ray-cpus", "0"], "--ray-cpus 0: it must be >= 1"),
                         (["--ray", "--resume"], "--resume: no manifest")]:
        err = io.StringIO()
        assert main([*base, *extra], out=io.StringIO(), err=err) == 2
        assert words in err.getvalue() and err.getvalue().count("\n") == 1, err.getvalue()
    assert os.listdir(tmp_path) == []  # nothing written


def test_import_warpsim_does_not_import_ray():
    code = ("import sys, warpsim, warpsim.distributed.ray_sweep, warpsim.sweeps.command, warpsim.cli as c; "
            "c._parser(); assert 'ray' not in sys.modules, 'ray imported'")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


# --- on a local cluster ---------------------------------------------------------------------------

@pytest.fixture(scope="module")
def cluster():
    """A local Ray cluster with 2 CPUs for the whole module; yields its address."""
    import logging

    import ray  # the ray extra (.ci/run installs it): these tests fail, never skip, without it

    mode = os.environ.get("RAY_AUTH_MODE")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, logging_level=logging.ERROR)
    try:
        yield ray.get_runtime_context().gcs_address
    finally:
        ray.shutdown()
        if mode is None:  # ray.init sets it for this process; later tests start from the usual environment
            os.environ.pop("RAY_AUTH_MODE", None)


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The single-process sweep (``warpsim sweep`` without --ray): (worlds, table text, {world: samples},
    occupancy record bytes)."""
    from warpsim.cli import main

    folder = tmp_path_factory.mktemp("single")
    err = io.StringIO()
    assert main(["sweep", SCENE, "--worlds", str(WORLDS), "--frames", str(FRAMES), "--device", "cpu",
                 "--out", str(folder / "s.usda"), "--no-progress", *FIXED_STEPS, *[f"--vary={v}" for v in VARY]],
                out=io.StringIO(), err=err) == 0, err.getvalue()
    worlds = sample_worlds(SCENE, {}, VARY, WORLDS)
    samples = _samples(folder / "s.usda", WORLDS)
    key = next(k for k in samples[0] if k.endswith(".points"))
    assert samples[0][key].shape[0] == FRAMES + 1  # every frame, and the worlds differ (the variant switches)
    assert not np.allclose(samples[0][key], samples[2][key])
    return worlds, _read(folder / "s.csv"), samples, (folder / "s.occupancy.npz").read_bytes()


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
    """The table and the merged occupancy record byte for byte (each batch recorded its worlds on
    the whole sweep's grid) and every world's samples, as the single-process sweep's."""
    _worlds, table, samples, record_bytes = reference
    assert _read(table_path) == table
    from warpsim.browse.occupancy import occupancy_path

    with open(occupancy_path(root), "rb") as fh:
        assert fh.read() == record_bytes
    got = _samples(root, len(samples))
    for w in samples:
        assert got[w].keys() == samples[w].keys()
        for key in samples[w]:
            np.testing.assert_allclose(got[w][key], samples[w][key], rtol=0, atol=1e-6, err_msg=f"world {w} {key}")


def test_ray_without_an_address_starts_a_local_cluster_and_matches_the_single_process_sweep(reference, tmp_path):
    # before the module's cluster exists: the command starts (and stops) its own, as a user's would
    out = tmp_path / "s.usda"
    r = subprocess.run([sys.executable, "-m", "warpsim", "sweep", SCENE, "--worlds", str(WORLDS), "--frames",
                        str(FRAMES), "--device", "cpu", "--out", str(out), "--no-progress", "--ray", "--ray-cpus", "2",
                        "--batch-size", "4", *FIXED_STEPS, *[f"--vary={v}" for v in VARY]],
                       capture_output=True, text=True, timeout=300, check=False)
    assert r.returncode == 0, r.stderr
    assert re.findall(r"^batch (\d)/2 ", r.stderr, re.MULTILINE) in (["1", "2"], ["2", "1"])
    assert "2 went unstable" in r.stdout  # the two stiffest worlds: the energy balance flags them (issue 49)
    assert "occupancy record: 8 worlds x 41 frames" in r.stdout
    _assert_same(reference, tmp_path / "s.csv", out)


def test_ray_sweep_equals_single_process_and_survives_a_killed_worker(cluster, reference, tmp_path):
    from warpsim.distributed.ray_sweep import run_ray_sweep

    worlds = reference[0]
    marker = str(tmp_path / "killed.marker")
    out = str(tmp_path / "ray" / "s.usda")
    result = run_ray_sweep(SCENE, worlds, frames=FRAMES, fps=480.0, substeps=1, out_path=out,
                           table_path=str(tmp_path / "ray" / "s.csv"),
                           device="cpu", batch_size=3, _kill_once=marker, occupancy={"resolution": 16})
    # one worker was SIGKILLed after writing its layer, before publishing it; Ray ran the batch again
    killed_batch, killed_pid = map(int, _read(marker).split())
    assert result["batches"][killed_batch]["pid"] != killed_pid
    assert result["ran"] == [0, 1, 2] and result["skipped"] == []
    assert [r["world"] for r in result["rows"]] == list(range(WORLDS))
    _assert_same(reference, result["table"], result["root"])
    # nothing partial is left or referenced: only the three published batch folders
    assert sorted(os.listdir(tmp_path / "ray" / "s.batches")) == ["batch_0000", "batch_0001", "batch_0002"]
    assert ".tmp-" not in _read(result["root"])


def _listed(mpath):
    """Batch indices a manifest lists as finished."""
    with open(mpath) as fh:
        return {int(k) for k in json.load(fh)["batches"]}


def test_resume_after_the_driver_is_killed_runs_only_the_remaining_batches(cluster, reference, tmp_path):
    from warpsim.cli import main

    out = tmp_path / "s.usda"
    argv = ["sweep", SCENE, "--worlds", str(WORLDS), "--frames", str(FRAMES), "--device", "cpu", "--out", str(out),
            "--batch-size", "2", "--no-progress", *FIXED_STEPS] + [f"--vary={v}" for v in VARY]
    # a fresh shell's environment: the driver finds the cluster's authentication token by itself
    env = {k: v for k, v in os.environ.items() if k != "RAY_AUTH_MODE"}
    driver = subprocess.Popen([sys.executable, "-m", "warpsim", *argv, "--ray", cluster], cwd=tmp_path, env=env,
                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    mpath = manifest_path(str(out))
    try:
        deadline = time.monotonic() + 90
        while not (os.path.exists(mpath) and _listed(mpath)):
            assert driver.poll() is None, driver.stderr.read().decode()
            assert time.monotonic() < deadline, "no batch finished within 90 s"
            time.sleep(0.02)
    finally:
        driver.send_signal(signal.SIGKILL)
        driver.wait()
        driver.stderr.close()
    finished = _listed(mpath)
    assert 1 <= len(finished) < 4, f"the driver was killed after batches {finished}"
    stamps = {i: os.stat(tmp_path / "s.batches" / f"batch_{i:04d}").st_ino for i in finished}
    assert not out.exists()  # no root before every batch is done

    err = io.StringIO()  # a resume must keep the sweep's settings
    assert main([*argv, "--ray", cluster, "--resume", "--frames", "7"], out=io.StringIO(), err=err) == 2
    assert "frames=7 differs from the manifest's frames=40" in err.getvalue() and _listed(mpath) == finished
    err = io.StringIO()
    assert main([*argv, "--ray", cluster, "--resume"], out=io.StringIO(), err=err) == 0, err.getvalue()
    ran = {int(m) - 1 for m in re.findall(r"^batch (\d+)/4 ", err.getvalue(), re.MULTILINE)}
    assert ran == {0, 1, 2, 3} - finished  # the remaining batches only
    for i, ino in stamps.items():  # the finished batches' folders were kept, not written again
        assert os.stat(tmp_path / "s.batches" / f"batch_{i:04d}").st_ino == ino
    _assert_same(reference, tmp_path / "s.csv", out)
    rows = load_rows(str(tmp_path / "s.batches" / "batch_0003"))
    assert [r["blown_up"] for r in rows] == [1, 1]  # the stiff batch blew up: flagged, not fatal
    assert sorted(os.listdir(tmp_path / "s.batches")) == [f"batch_{i:04d}" for i in range(4)]


def test_a_batch_that_raises_is_flagged_and_the_root_spans_the_other_batches(cluster, reference, tmp_path):
    from warpsim.distributed.ray_sweep import run_ray_sweep

    def runner(scene, worlds, *, first_world, **kw):  # pickled by value into the Ray task
        if first_world == 2:
            raise RuntimeError("out of device memory\n(details)")
        return run_batch(scene, worlds, first_world=first_world, **kw)

    worlds = reference[0][:6]
    result = run_ray_sweep(SCENE, worlds, frames=FRAMES, fps=480.0, substeps=1, out_path=str(tmp_path / "s.usda"),
                           table_path=str(tmp_path / "s.csv"), device="cpu", batch_size=2, runner=runner)
    rows = result["rows"]
    assert [r["world"] for r in rows] == list(range(6))
    assert [r.get("batch_error") for r in rows] == [None, None, "RuntimeError: out of device memory", \
        "RuntimeError: out of device memory", None, None]
    assert [bool(r["blown_up"]) for r in rows] == [False, False, True, True, False, False]
    assert result["batches"][1]["error"] and not result["batches"][0]["error"]
    from pxr import Usd

    stage = Usd.Stage.Open(result["root"])
    vset = stage.GetPrimAtPath("/World").GetVariantSets().GetVariantSet("world")
    assert sorted(vset.GetVariantNames()) == [f"world_{w:06d}" for w in (0, 1, 4, 5)]
    with open(result["table"]) as fh:
        assert fh.read().count("RuntimeError: out of device memory") == 2
    # --resume runs the failed batch again (the memory may be there now) and nothing else
    again = run_ray_sweep(SCENE, worlds, frames=FRAMES, fps=480.0, substeps=1, out_path=str(tmp_path / "s.usda"),
                          table_path=str(tmp_path / "s.csv"), device="cpu", batch_size=2, resume=True)
    assert again["ran"] == [1] and again["skipped"] == [0, 2]
    with open(again["table"]) as fh:
        assert fh.read().splitlines() == reference[1].splitlines()[:7]  # header + worlds 0..5
