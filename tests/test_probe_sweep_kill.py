"""Sweeps survive a kill (issue 28): the single-process ``warpsim sweep`` streams its batch layer
in chunk files, so a SIGKILL at a random moment leaves every completed chunk readable (``warpsim
info`` exit 0, samples equal to an uninterrupted run's), ``--resume`` finishes it sample for
sample equal to the uninterrupted run, and a sweep re-run into a finished sweep's folder leaves
the old result readable and unchanged until the new one is complete."""

import csv
import glob
import shutil
import io
import os
import random
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

pytest.importorskip("pxr")
from pxr import Usd

from warpsim.cli import main

FRAMES, CHUNK, WORLDS = 240, 8, 3
OLD, NEW = "height=0.02:0.05", "height=0.06:0.09"


def argv(out, vary=OLD, *extra):
    return ["sweep", "bounce", "--worlds", str(WORLDS), "--vary", vary, "--frames", str(FRAMES), "--chunk",
            str(CHUNK), "--out", str(out), "--no-progress", "--device", "cpu", *extra]


def run(*args):
    out, err = io.StringIO(), io.StringIO()
    return main(list(args), out, err), out.getvalue(), err.getvalue()


def samples(layer, frames=range(FRAMES + 1)):
    """(worlds, frames, 3) positions of the ball of every world of a batch layer (or sweep root)."""
    stage = Usd.Stage.Open(str(layer))
    out = []
    for w in range(WORLDS):
        prim = stage.GetPrimAtPath(f"/Worlds/world_{w:06d}/ball")
        attr = prim.GetAttribute("points")
        out.append([np.asarray(attr.Get(float(f)), np.float32).reshape(3) for f in frames])
    return np.array(out)


def table(path):
    with open(path) as f:
        return list(csv.reader(f))


def partial_layer(folder):
    """The staged batch layer (not a chunk, the manifest, or the temporary of a root rewrite the kill
    interrupted: ``s.batch_0000.runT.tmp-PID.usdc`` may hold the next root, never renamed)."""
    found = [p for p in glob.glob(os.path.join(folder, "s.batch_0000.run*.usdc")) if ".chunk" not in p
             and ".manifest" not in p and ".tmp-" not in p]
    return found[0] if found else None


def start_and_kill(out, rng, vary=OLD, workers="0"):
    """Start a sweep in a subprocess and SIGKILL it at a random moment after a random number of
    completed chunks; returns the number of chunks the index listed at the kill. ``workers``:
    processes authoring its chunks (``WARPSIM_WRITE_WORKERS``; "0": the sweep's own process)."""
    pattern = os.path.join(os.path.dirname(out), "s.batch_0000.run*.chunks.jsonl")
    before = set(glob.glob(pattern))  # a finished sweep's own index
    proc = subprocess.Popen([sys.executable, "-m", "warpsim", *argv(out, vary)], stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, env={**os.environ, "WARPSIM_WRITE_WORKERS": workers})
    want = rng.randint(1, FRAMES // CHUNK // 2)
    deadline = time.time() + 120
    listed = 0
    while proc.poll() is None and time.time() < deadline:
        index = sorted(set(glob.glob(pattern)) - before)
        listed = sum(1 for _ in open(index[0])) if index else 0
        if listed >= want:
            break
        time.sleep(0.01)
    time.sleep(rng.uniform(0.0, 0.05))  # anywhere inside the next chunk, its save or its rename
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert proc.returncode == -signal.SIGKILL, "the sweep finished before it could be killed: make it longer"
    return listed


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    d = tmp_path_factory.mktemp("kill_ref")
    code, _, err = run(*argv(d / "s.usda"))
    assert code == 0, err
    return {"samples": samples(d / "s.batch_0000.usdc"), "table": table(d / "s.csv"), "dir": d}


@pytest.mark.parametrize("seed, workers", [(1, "0"), (2, "2")])
def test_killed_sweep_keeps_completed_chunks_and_resume_equals_an_uninterrupted_run(tmp_path, reference, seed,
                                                                                   workers):
    """Killed while its own process writes the chunks, or while two worker processes do."""
    rng = random.Random(seed)
    out = tmp_path / "s.usda"
    for attempt in range(6):  # the workers may complete every chunk between two polls of the index:
        listed = start_and_kill(out, rng, workers=workers)  # then the kill came after the last frame was
        layer = partial_layer(tmp_path)  # listed (nothing to resume); a new sweep there starts afresh
        assert listed >= 1 and layer is not None, os.listdir(tmp_path)
        stage = Usd.Stage.Open(layer)
        end = int(stage.GetEndTimeCode())
        if end < FRAMES:
            break
        del stage
    info_out, info_err = io.StringIO(), io.StringIO()
    assert main(["info", layer], info_out, info_err) == 0, info_err.getvalue()  # every completed chunk intact
    assert stage.HasAuthoredTimeCodeRange() and end < FRAMES, attempt  # killed part-way
    assert (end + 1) % CHUNK == 0 and end + 1 >= listed * CHUNK
    assert f"frames 0..{end}" in info_out.getvalue()
    kept = samples(layer, range(end + 1))
    assert np.array_equal(kept, reference["samples"][:, : end + 1])  # sample for sample
    assert not out.exists()  # a first sweep has no root until it is complete
    code, _, err = run(*argv(out), "--resume")
    assert code == 0, err
    assert f"resuming: frames 0..{end} are in" in err  # the kept chunks were not written again
    assert np.array_equal(samples(tmp_path / "s.batch_0000.usdc"), reference["samples"])
    assert table(tmp_path / "s.csv") == reference["table"]
    leftovers = [p for p in os.listdir(tmp_path) if ".run" in p and "chunk" not in p and "manifest" not in p
                 and "chunks.jsonl" not in p]
    assert leftovers == [] and not (tmp_path / "s.sweep-partial.json").exists(), os.listdir(tmp_path)
    tokens = {p.split(".run")[1].split(".")[0] for p in os.listdir(tmp_path) if ".run" in p}
    assert len(tokens) == 1  # only the published run's chunks remain


def test_rerun_into_a_finished_sweep_keeps_the_old_result_until_the_new_one_is_complete(tmp_path, reference):
    folder = tmp_path / "f"
    folder.mkdir()
    for name in os.listdir(reference["dir"]):  # the finished sweep's files (its thumbnails are a folder)
        src = reference["dir"] / name
        if src.is_dir():
            shutil.copytree(src, folder / name)
        else:
            (folder / name).write_bytes(src.read_bytes())
    out = folder / "s.usda"
    old_root = Usd.Stage.Open(str(out))
    before = np.asarray(old_root.GetPrimAtPath("/World/ball").GetAttribute("points").Get(30.0))
    del old_root
    start_and_kill(out, random.Random(7), vary=NEW)
    assert partial_layer(folder) is not None, os.listdir(folder)  # the new run was under way
    code, info, err = run("info", str(out))
    assert code == 0 and f"frames 0..{FRAMES}" in info, err  # the old sweep, whole
    assert np.array_equal(samples(folder / "s.batch_0000.usdc"), reference["samples"])
    assert table(folder / "s.csv") == reference["table"]
    stage = Usd.Stage.Open(str(out))
    assert np.array_equal(np.asarray(stage.GetPrimAtPath("/World/ball").GetAttribute("points").Get(30.0)), before)
    code, _, err = run(*argv(out, NEW))  # the new sweep, to the end: now it replaces the old one
    assert code == 0, err
    heights = sorted(float(r[1]) for r in table(folder / "s.csv")[1:])
    assert heights == pytest.approx([0.06, 0.075, 0.09])
    new = samples(folder / "s.batch_0000.usdc")
    assert new[:, 0, 1].min() > reference["samples"][:, 0, 1].max()  # higher drops than the old sweep
    tokens = {p.split(".run")[1].split(".")[0] for p in os.listdir(folder) if ".run" in p}
    assert len(tokens) == 1 and not (folder / "s.sweep-partial.json").exists(), os.listdir(folder)
