"""Damaged caches are never drawn as if whole (issue 28): ``render``, ``plot``, ``view`` and the
Python readers check the chunk index (size, CRC-32) like ``warpsim info`` and refuse a cache with
a deleted, truncated or overwritten chunk file (exit 1, one line naming the chunk and the frames
still readable), or with ``--allow-damaged`` leave those frames out and say so; ``info`` on a
sweep root checks every batch layer; ``info`` on a FIFO answers at once."""

import io
import os
import shutil
import time

import numpy as np
import pytest

pytest.importorskip("pxr")

from warpsim.cli import main
from warpsim.usd.validate import DamagedCacheError

RUN = ["--device", "cpu", "--no-progress"]


def run(*argv):
    out, err = io.StringIO(), io.StringIO()
    code = main(list(argv), out, err)
    return code, out.getvalue(), err.getvalue()


def damage(path, action):
    if action == "delete":
        os.remove(path)
    elif action == "truncate":
        data = open(path, "rb").read()
        open(path, "wb").write(data[: len(data) // 3])
    else:  # same size, flipped bytes: only the CRC-32 sees it
        data = bytearray(open(path, "rb").read())
        data[len(data) // 2] ^= 0xFF
        open(path, "wb").write(bytes(data))


@pytest.fixture(scope="module")
def caches(tmp_path_factory):
    d = tmp_path_factory.mktemp("damaged")
    code, _, err = run("run", "pendulum", "--frames", "20", "--chunk", "5", "--out", str(d / "base" / "p.usda"), *RUN)
    assert code == 0, err
    code, _, err = run("sweep", "bounce", "--worlds", "2", "--vary", "height=0.02:0.05", "--frames", "12", "--chunk",
                       "4", "--out", str(d / "sweep" / "s.usda"), *RUN)
    assert code == 0, err
    made = {}

    def copy(kind, action):
        key = (kind, action)
        if key not in made:
            dest = d / f"{kind}-{action}"
            shutil.copytree(d / kind, dest)
            if kind == "base":
                damage(dest / "p.chunk000005.usdc", action)
                made[key] = str(dest / "p.usda")
            else:
                name = "s.batch_0000.usdc" if action == "layer" else \
                    next(f for f in os.listdir(dest) if f.endswith("chunk000004.usdc"))
                damage(dest / name, "delete" if action == "layer" else action)
                made[key] = str(dest / "s.usda")
        return made[key]

    return {"dir": d, "copy": copy, "good": str(d / "base" / "p.usda")}


@pytest.mark.parametrize("action", ["delete", "truncate", "flip"])
@pytest.mark.parametrize("command", ["render", "plot"])
def test_damaged_cache_is_refused_naming_the_chunk_and_the_readable_frames(caches, command, action):
    cache = caches["copy"]("base", action)
    out = os.path.join(os.path.dirname(cache), f"{command}.png")
    extra = ["--frame", "12", "--size", "32x24", *RUN] if command == "render" else []
    code, stdout, err = run(command, cache, "--out", out, *extra)
    lines = err.strip().splitlines()
    assert code == 1 and len(lines) == 1 and lines[0].startswith("warpsim: error:"), (code, err)
    assert "p.chunk000005.usdc (frames 5..9)" in lines[0] and "readable frames: 0..4, 10..20" in lines[0]
    assert "--allow-damaged" in lines[0] and "pxrInternal" not in err and not os.path.exists(out)


def test_allow_damaged_skips_the_damaged_frames_and_says_so(caches):
    cache = caches["copy"]("base", "flip")
    gif = os.path.join(os.path.dirname(cache), "clip.gif")
    code, out, err = run("render", cache, "--out", gif, "--frames", "3:12", "--size", "32x24", "--allow-damaged", *RUN)
    assert code == 0, err
    assert "skipping 5 frame(s) of damaged chunk files: 5..9" in err
    assert "(5 frames" in out  # 3, 4, 10, 11, 12
    from warpsim.render.plot import cache_series

    with pytest.raises(DamagedCacheError, match="p.chunk000005.usdc"):
        cache_series(cache)
    said = []
    times, panels = cache_series(cache, allow_damaged=True, on_skip=said.append)
    assert len(times) == 16 and said and np.allclose(times[5] / times[1], 10.0)  # frames 0..4, 10..20
    for panel in panels:
        for values in panel["lines"].values():
            assert np.isfinite(values).all()
    good_times, good_panels = cache_series(caches["good"])  # the intact frames read the same values
    keep = [f for f in range(21) if not 5 <= f <= 9]
    assert np.array_equal(np.asarray(list(good_panels[0]["lines"].values())[0])[keep],
                          np.asarray(list(panels[0]["lines"].values())[0]))


def test_python_reader_refuses_too(caches):
    from warpsim.render.cache import render_cache

    cache = caches["copy"]("base", "delete")
    with pytest.raises(DamagedCacheError, match="readable frames: 0..4, 10..20"):
        render_cache(cache, os.path.join(os.path.dirname(cache), "x.png"), device="cpu", size=(32, 24))


@pytest.mark.parametrize("action, words", [
    ("layer", ["s.batch_0000.usdc", "missing (a batch layer of this sweep)", "readable frames: none"]),
    ("delete", ["chunk000004.usdc", "frames 4..7: missing", "readable frames: 0..3, 8..12"]),
    ("truncate", ["chunk000004.usdc", "frames 4..7: damaged"]),
    ("flip", ["chunk000004.usdc", "CRC-32 mismatch"]),
])
def test_info_on_a_sweep_root_checks_every_batch_layer(caches, action, words):
    code, out, err = run("info", caches["copy"]("sweep", action))
    assert code == 1 and "DAMAGED" in out, (out, err)
    for word in words:
        assert word in out + err
    assert err.count("\n") == 1 and "pxrInternal" not in err
    code, out, _ = run("info", str(caches["dir"] / "sweep" / "s.usda"))
    assert code == 0 and "frames 0..12" in out


def test_render_of_a_damaged_sweep_root_is_refused(caches):
    cache = caches["copy"]("sweep", "delete")
    code, _, err = run("render", cache, "--out", os.path.join(os.path.dirname(cache), "x.png"), "--size", "32x24",
                       *RUN)
    assert code == 1 and "chunk000004.usdc (frames 4..7) is missing" in err and err.count("\n") == 1, err


def test_view_of_a_damaged_cache_is_refused_before_serving(caches):
    pytest.importorskip("viser")
    code, _, err = run("view", caches["copy"]("base", "truncate"), "--port", "8791")
    assert code == 1 and "p.chunk000005.usdc" in err and err.count("\n") == 1 and "Traceback" not in err, err


def test_info_on_a_fifo_answers_at_once(tmp_path):
    fifo = tmp_path / "x.usda"
    os.mkfifo(fifo)
    t0 = time.perf_counter()
    code, _, err = run("info", str(fifo))
    assert code == 2 and "not a regular file" in err and time.perf_counter() - t0 < 5


@pytest.mark.parametrize("command", ["info", "render", "plot"])
@pytest.mark.parametrize("content", [b"#usda 1.0\n(((( nonsense", b"PXR-USDC" + b"\0" * 100, b""])
def test_a_file_that_is_not_usd_is_named_in_warpsims_words(tmp_path, command, content):
    bad = tmp_path / "bad.usda" if content.startswith(b"#usda") or not content else tmp_path / "bad.usdc"
    bad.write_bytes(content)
    extra = ["--out", str(tmp_path / "x.png")] if command != "info" else []
    code, _, err = run(command, str(bad), *extra, *(RUN if command == "render" else []))
    lines = err.strip().splitlines()
    assert code in (1, 2) and len(lines) == 1 and "pxrInternal" not in err and "line " not in err.split("says")[0], err
    assert bad.name in lines[0] and ("is empty (0 bytes)" if not content else "is not a readable USD file") in lines[0]
