"""What a newcomer meets first: ``dir(ws)`` lists the public names (tab completion); a slow run's
estimate leaves the first frame's kernel compilation out; every run says how to look at its cache
without usdview (which pip's usd-core lacks); the tables of ``sweep --rank`` and ``query`` are
aligned in columns; the plot's angle axis has its unit; the getting-started page's Python blocks
each run on their own and print what the page says; the tutorials' stability figures are the
simulators' own."""
from __future__ import annotations

import io
import os
import re
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from warpsim.cli import main

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"


def run(*argv):
    out, err = io.StringIO(), io.StringIO()
    code = main([str(a) for a in argv], out=out, err=err)
    return code, out.getvalue(), err.getvalue()


def test_dir_lists_the_public_names_before_their_first_use():
    """A fresh ``import warpsim as ws``: ``dir(ws)`` holds every name of ``__all__`` (loaded lazily)
    and not the import machinery."""
    code = "import warpsim as ws; print(repr(dir(ws))); print(repr(ws.__all__))"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    names, public = (eval(line) for line in result.stdout.splitlines()[-2:])
    assert "Simulator" in names and "ModelBuilder" in names and set(public) <= set(names)
    assert "TYPE_CHECKING" not in names and not [n for n in names if n.startswith("_") and n != "__version__"]


def test_the_run_estimate_leaves_kernel_compilation_out(tmp_path, monkeypatch):
    """The first frame compiles Warp's kernels (minutes on a cold cache) and says nothing of the
    rest: the note estimates the run from the second frame. Here the first frame takes 1.5 s (the
    compilation), the others 0.3 s: the estimate is 0.3 s a frame, not 1.5 s."""
    from warpsim.scenes import get_scene
    from warpsim.sweeps import preflight

    monkeypatch.setattr(preflight, "FRAME_TIME_NOTE", 0.2)
    cls = get_scene("bounce")
    advance = cls.advance
    calls = []

    def slow(self, frame_dt, substeps):
        calls.append(1)
        time.sleep(1.5 if len(calls) == 1 else 0.3)
        return advance(self, frame_dt, substeps)

    monkeypatch.setattr(cls, "advance", slow)
    frames = 5
    code, out, err = run("run", "bounce", "--frames", frames, "--no-progress", "--device", "cpu",
                         "--out", tmp_path / "b.usda")
    assert code == 0, err
    note = re.search(r"frame (\d+) took ([\d.]+) s .* the other (\d+) frames take about ([\d.]+) s", err)
    assert note, err
    frame, took, left, total = int(note[1]), float(note[2]), int(note[3]), float(note[4])
    assert frame == 2 and left == frames - 2 and "compiles Warp's kernels, left out" in err
    assert 0.3 <= took < 1.0 and total == pytest.approx(took * left, rel=0.01)


def test_a_run_says_how_to_look_at_its_cache(tmp_path):
    code, out, err = run("run", "bounce", "--frames", 2, "--no-progress", "--device", "cpu", "--out", tmp_path / "b.usda")
    assert code == 0, err
    line = next(line for line in out.splitlines() if line.startswith("open: "))
    path = os.path.relpath(tmp_path / "b.usda")
    assert f"warpsim view {path}" in line and "usd-core" in line and f"usdview {path}" not in line


def columns(lines):
    """Where each cell of each line ends (its last character's index + 1)."""
    return [[m.end() for m in re.finditer(r"\S+", line)] for line in lines]


def table(out):
    """The lines of the picked-worlds table of ``out`` (header and rows)."""
    lines = out.splitlines()
    start = next(i for i, line in enumerate(lines) if re.match(r"picked \d+ of \d+ worlds", line)) + 1
    return [line for line in lines[start:] if line.startswith("  ")]


def test_rank_and_query_tables_are_aligned(tmp_path):
    """Numbers of different widths (0.02, 0.0316979, 10) line up: every row's cells end where the
    header's do (numeric columns are right-aligned), in the sweep's --rank table and in query's."""
    root = tmp_path / "b.usda"
    code, out, err = run("sweep", "bounce", "--worlds", 12, "--vary", "height=0.02:0.2:log", "--vary",
                         "restitution=0.3,0.9", "--frames", 30, "--rank", "peak_center_y:desc", "--no-progress",
                         "--no-thumbnails", "--device", "cpu", "--out", root)
    assert code == 0, err
    code, query, err = run("query", root, "--inside", "-0.5,0,-0.5,0.5,0.1,0.5@0.2:0.5", "--rank", "inside1_entry")
    assert code == 0, err
    for text in (out, query):
        rows = table(text)
        assert len(rows) == 13 and len({len(line) for line in rows}) == 1, "\n".join(rows)
        assert len({tuple(c) for c in columns(rows)}) == 1, "\n".join(rows)
        assert len({len(line.split()[1]) for line in rows[1:]}) > 1  # the cells differ in width


def test_aligned_pads_text_left_and_numbers_right():
    from warpsim.sweeps.metrics import aligned

    lines = aligned([["world", "shape", "k"], ["3", "lattice", "1.5"], ["12", "chain", "100"]])
    assert lines == ["world  shape      k", "    3  lattice  1.5", "   12  chain    100"]


def test_the_plot_gives_the_angle_its_unit(tmp_path):
    from pxr import Usd

    from warpsim.render.plot import cache_series
    from warpsim.usd.prims import PrimDecl

    cache = tmp_path / "p.usda"
    code, out, err = run("run", "pendulum", "--frames", 5, "--no-progress", "--device", "cpu", "--out", cache)
    assert code == 0, err
    stage = Usd.Stage.Open(str(cache))
    unit = stage.GetPrimAtPath("/World/bob").GetAttribute("warpsim:angle").GetCustomDataByKey("unit")
    _, panels = cache_series(str(cache))
    assert unit == "rad" and "angle [rad]" in [p["ylabel"] for p in panels]
    with pytest.raises(ValueError, match=r"attribute 'warpsim:x' of 'bob': unit '' is not a unit name"):
        PrimDecl("bob").add_attribute("warpsim:x", "double", unit="")


def python_blocks(page):
    return [textwrap.dedent(b) for b in re.findall(r"^\.\. code-block:: python\n\n((?:   .*\n|\n)+)",
                                                  page.read_text(), re.M)]


def test_getting_started_blocks_run_alone_and_print_what_the_page_says(tmp_path):
    """Each Python block of the getting-started page runs in a fresh interpreter (no block leans on
    an earlier one's ``sim``: the cache's frame 0 is the initial state), and prints what its
    comments say."""
    blocks = python_blocks(DOCS / "getting_started.rst")
    assert len(blocks) >= 3
    outputs = []
    for block in blocks:
        result = subprocess.run([sys.executable, "-c", block], cwd=tmp_path, capture_output=True, text=True,
                                timeout=600)
        assert result.returncode == 0, f"{block}\n{result.stderr[-3000:]}"
        outputs.append(result.stdout)
    assert "0.024304" in outputs[0] and "-0.3924" in outputs[0]
    stable = next(o for o in outputs if "stable_dt" in o)
    for said in re.findall(r"^   # (\w+: stable_dt = [\d.inf]+ s)", (DOCS / "getting_started.rst").read_text(), re.M):
        assert said in stable, (said, stable)
    from pxr import Usd

    cache = Usd.Stage.Open(str(tmp_path / "usd_out" / "ball.usda"))
    ball = cache.GetPrimAtPath("/World/ball").GetAttribute("points")
    assert tuple(ball.Get(0)[0]) == pytest.approx((0.0, 0.04, 0.0))  # frame 0: the ball at rest, not a step in
    assert tuple(ball.Get(1)[0]) == pytest.approx((0.0, 0.024304, 0.0), abs=1e-6)


def test_the_tutorials_stability_figures_are_the_simulators():
    """The bodies and cloth tutorials quote ``stable_dt()`` of their examples: those figures."""
    sys.path.insert(0, str(ROOT / "examples"))
    try:
        import cloth_implicit
        import teapot
    finally:
        sys.path.remove(str(ROOT / "examples"))
    bodies = (DOCS / "tutorials" / "bodies.rst").read_text()
    cloth = (DOCS / "tutorials" / "cloth.rst").read_text()
    heavy, light = (teapot.Example(mass=m, device="cpu").sim for m in (1.0, 0.02))
    assert f"is {heavy.stable_dt() * 1e3:.3g} ms at 1 kg" in bodies
    assert f"and {light.stable_dt() * 1e3:.2g} ms at 0.02 kg" in bodies
    assert f"spring {heavy.stability().index}," in bodies
    stiff = cloth_implicit.Example("semi_implicit_euler", device="cpu").sim
    assert f"is {stiff.stable_dt() * 1e3:.2g} ms (spring {stiff.stability().index}," in cloth
    assert cloth_implicit.Example("implicit_euler", device="cpu").sim.stable_dt() == float("inf")
    assert "``Example(\"implicit_euler\").sim.stable_dt()`` is ``inf``" in cloth
