"""Hardening III (issue 36), classes 1 and 2: one writer per output (two real processes; a
SIGKILLed writer's stale lock taken over; chunks of two runs detected by ``info``) and no command
writing over its own input or another result's files."""
from __future__ import annotations

import io
import json
import os
import signal
import subprocess
import sys
import time

import pytest

pytest.importorskip("pxr")

from warpsim.cli import main
from warpsim.usd import lock as output_lock


def run(*argv):
    out, err = io.StringIO(), io.StringIO()
    code = main([str(a) for a in argv], out=out, err=err)
    return code, out.getvalue(), err.getvalue()


def one_error_line(err):
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("warpsim: error: "), err
    return lines[0]


def _wait_for(cond, proc, seconds=120.0):
    t0 = time.monotonic()
    while not cond():
        assert proc.poll() is None, f"the writer exited early: {proc.communicate()}"
        assert time.monotonic() - t0 < seconds, "the writer did not start"
        time.sleep(0.05)


# ------------------------------------------------------------------------------- class 1: one writer
def test_second_writer_is_refused_and_a_killed_writers_lock_is_taken_over(tmp_path):
    out = tmp_path / "s.usda"
    proc = subprocess.Popen([sys.executable, "-m", "warpsim", "run", "bounce", "--frames", "1000000", "--chunk", "2",
                             "--no-progress", "--device", "cpu", "--out", str(out)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    lock_file = tmp_path / "s.lock"
    index = tmp_path / "s.chunks.jsonl"
    try:
        _wait_for(lambda: index.exists() and index.read_text().count("\n") >= 2, proc)
        holder = json.loads(lock_file.read_text())
        assert holder["pid"] == proc.pid and holder["host"] and holder["start"] and "run bounce" in holder["command"]
        # a second writer of the same output, in this (another) process: one line, exit 2, nothing touched
        before = [n for n in os.listdir(tmp_path) if ".tmp-" not in n]  # (the writer renames its temporaries)
        for argv in (["run", "bounce", "--frames", 3, "--out", out],
                     ["run", "bounce", "--frames", 3, "--out", tmp_path / "s.usdc"],  # shares s.chunkNNNNNN.usdc
                     ["sweep", "bounce", "--worlds", 2, "--vary", "height=0.2:0.8", "--frames", 3, "--out", out]):
            code, _, err = run(*argv, "--no-progress", "--device", "cpu")
            line = one_error_line(err)
            assert code == 2 and f"pid {proc.pid}" in line and "being written by another warpsim process" in line
        assert proc.poll() is None  # the first writer goes on
        assert set(before) <= set(os.listdir(tmp_path))
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    # the killed writer left its lock file (stale: the kernel dropped its flock)
    assert json.loads(lock_file.read_text())["pid"] == proc.pid
    code, text, err = run("run", "bounce", "--frames", 5, "--chunk", 2, "--no-progress", "--device", "cpu", "--out", out)
    assert code == 0, err
    assert not lock_file.exists()  # released when the command ended
    code, text, err = run("info", out)
    assert code == 0 and "frames 0..5 (6 frames" in text, text + err


def test_lock_is_reentrant_in_a_process_and_released_by_the_scope(tmp_path):
    out = tmp_path / "a.gif"
    with output_lock.command_scope():
        path = output_lock.hold(out)
        assert path == str(tmp_path / "a.gif.lock") and os.path.exists(path)
        with output_lock.OutputLock(out):  # the same process again: re-entrant
            pass
        assert os.path.exists(path)
        code = subprocess.run([sys.executable, "-c", f"from warpsim.usd import lock; lock.hold({str(out)!r})"],
                              capture_output=True, text=True)
        assert code.returncode != 0 and "OutputLockedError" in code.stderr
    assert not os.path.exists(path)


def test_info_detects_a_cache_whose_chunks_come_from_different_runs(tmp_path):
    a, b = tmp_path / "a" / "s.usda", tmp_path / "b" / "s.usda"
    for path, height in ((a, 0.5), (b, 0.9)):
        code, _, err = run("run", "bounce", "--frames", 7, "--chunk", 4, "--set", f"height={height}", "--no-progress",
                           "--device", "cpu", "--out", path)
        assert code == 0, err
    code, _, _ = run("info", a)
    assert code == 0
    # what two writers interleaving leave: a chunk file and its index line from the other run
    (a.parent / "s.chunk000004.usdc").write_bytes((b.parent / "s.chunk000004.usdc").read_bytes())
    other = [json.loads(x) for x in (b.parent / "s.chunks.jsonl").read_text().splitlines()][1]
    with open(a.parent / "s.chunks.jsonl", "a") as f:
        f.write(json.dumps(other) + "\n")
    code, text, err = run("info", a)
    assert code == 1
    assert "s.chunk000004.usdc  frames 4..7: written by another run" in text
    assert "readable frames: 0..3" in text


# ------------------------------------------------------------------- class 2: never one's own input
@pytest.fixture(scope="module")
def sweep(tmp_path_factory):
    root = tmp_path_factory.mktemp("own") / "S.usda"
    code, _, err = run("sweep", "bounce", "--worlds", 3, "--vary", "height=0.2:0.8", "--frames", 4, "--no-progress",
                       "--device", "cpu", "--out", root)
    assert code == 0, err
    return root


def _snapshot(folder):
    return {p.relative_to(folder): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_every_writing_command_refuses_its_own_input(sweep, tmp_path):
    import warpsim as ws
    from warpsim.viewer.record import Recorder

    folder = sweep.parent
    batch = folder / "S.batch_0000.usdc"
    chunk = next(folder / n for n in os.listdir(folder) if ".chunk0" in n)
    cache = tmp_path / "c.usda"
    assert run("run", "bounce", "--frames", 3, "--no-progress", "--device", "cpu", "--out", cache)[0] == 0
    link = tmp_path / "link.png"
    os.symlink(cache, link)  # the same file after resolving the link
    obj_link = tmp_path / "link.obj"
    os.symlink(cache, obj_link)
    before, cache_before = _snapshot(folder), cache.read_bytes()
    cases = [
        (["pick", sweep, "--world", 1, "--out", sweep], "this command's input"),
        (["pick", sweep, "--world", 1, "--out", batch], "this command's input"),
        (["pick", sweep, "--world", 1, "--out", folder / "S.usdc"], "is a file of"),
        (["pick", sweep, "--world", 1, "--out", chunk], "chunk"),
        (["pick", sweep, "--world", 1, "--out", folder / "S.picked.usda", "--flatten"], "picked worlds"),
        (["run", "bounce", "--from-sweep", sweep, "--world", 1, "--out", sweep, "--no-progress"], "input"),
        (["run", "bounce", "--from-sweep", sweep, "--world", 1, "--out", batch, "--no-progress"], "input"),
        (["run", "bounce", "--frames", 2, "--out", batch, "--no-progress"], "a batch layer"),
        (["run", "bounce", "--frames", 2, "--out", chunk, "--no-progress"], "a batch layer"),
        (["sweep", "bounce", "--worlds", 2, "--vary", "height=0.2:0.8", "--frames", 2, "--out", batch,
          "--no-progress"], "a batch layer"),
        (["sweep", "bounce", "--worlds", 2, "--vary", "height=0.2:0.8", "--frames", 2, "--out", tmp_path / "T.usda",
          "--table", folder / "S.csv", "--no-progress"], "its table"),
        (["plot", cache, "--out", link], "this command's input"),
        (["render", cache, "--out", link, "--no-progress"], "this command's input"),
        (["export", cache, "--out", obj_link], "this command's input"),
    ]
    for argv, words in cases:
        code, _, err = run(*argv)
        line = one_error_line(err)
        assert code == 2 and words in line, (argv, line)
    with pytest.raises(ValueError, match="this command's input"):
        ws.rerun_world(sweep, 1, out=sweep)
    with pytest.raises(ValueError, match="this command's input"):
        ws.rerun_world(sweep, 1, out=batch)
    with pytest.raises(ValueError, match="is a file of the cache or sweep"):
        Recorder(None, folder / "S.batch_0000.manifest.usda", 60.0)
    assert _snapshot(folder) == before and cache.read_bytes() == cache_before  # nothing was touched
    # its own files and a re-run's default cache stay writable
    code, _, err = run("pick", sweep, "--world", 1, "--out", tmp_path / "w1.usda")
    assert code == 0, err


def test_viewer_api_misuse_is_named():
    """Issue 36, class 5: bad viewer arguments and calls in the wrong order raise the right type with a fix."""
    import warpsim as ws

    with pytest.raises(TypeError, match="params must be a dict"):
        ws.Viewer("bounce", params="x", device="cpu")
    with pytest.raises(RuntimeError, match="before start"):
        ws.Viewer("bounce", device="cpu").update()
