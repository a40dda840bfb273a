"""``warpsim plot`` (warpsim.render.plot); the examples' figures are checked where the examples run
(tests/test_examples.py, tests/test_sph.py).

The series read back from a cache are checked against what made them: the pendulum's energies
against an independent ``ws.Pendulum`` run (kinetic + potential = total, RK4 keeps it), agents per
state against the agent count, changing counts against the points written."""

import io

import numpy as np
import pytest
from PIL import Image

import warpsim as ws
from warpsim.cli import main
from warpsim.render.plot import cache_series, plot_cache
from warpsim.usd.writer import UsdCacheWriter


def _run(*argv):
    out, err = io.StringIO(), io.StringIO()
    return main(list(argv), out, err), out.getvalue(), err.getvalue()


def _panel(panels, title):
    return next(p for p in panels if p["title"] == title)


def test_pendulum_energies_match_an_independent_run(tmp_path):
    cache = str(tmp_path / "p.usda")
    code, _, err = _run("run", "pendulum", "--frames", "30", "--out", cache, "--device", "cpu", "--no-progress",
                        "--set", "angle=1.2")
    assert code == 0, err
    times, panels = cache_series(cache)
    assert len(times) == 31 and times[1] == pytest.approx(1 / 60)
    energy = _panel(panels, "bob: energy")["lines"]
    assert set(energy) == {"kineticEnergy", "potentialEnergy", "totalEnergy"}
    np.testing.assert_allclose(energy["kineticEnergy"] + energy["potentialEnergy"], energy["totalEnergy"], rtol=1e-6)
    ref = ws.Pendulum(1.2, integrator="rk4", device="cpu").run(60, 1 / 120)  # 2 substeps per frame
    np.testing.assert_allclose(energy["totalEnergy"], ref["total"][::2, 0], rtol=1e-5)
    assert np.ptp(energy["totalEnergy"]) < 1e-4 * energy["totalEnergy"][0]  # RK4 holds the energy
    angle = _panel(panels, "bob: angle")["lines"]["angle"]
    assert angle[0] == pytest.approx(1.2) and angle.min() < 1.0
    out = str(tmp_path / "p.png")
    assert plot_cache(cache, out) == (out, 2)
    with Image.open(out) as fig:
        assert fig.size == (720, 468)  # 8 x (2 x 2.6) inches at 90 dpi: one panel per series


def test_agents_per_state_and_counts(tmp_path):
    cache = str(tmp_path / "z.usda")
    code, _, err = _run("run", "zombies", "--frames", "4", "--out", cache, "--device", "cpu", "--no-progress",
                        "--set", "zombies=8")
    assert code == 0, err
    times, panels = cache_series(cache)
    states = _panel(panels, "agents: agents per state")["lines"]
    assert "walking" in states
    np.testing.assert_array_equal(np.sum(list(states.values()), axis=0), np.full(len(times), 8))

    path = str(tmp_path / "c.usda")
    counts = [3, 5, 2, 7]
    with UsdCacheWriter(path, fps=10) as w:
        w.add_points("drops", count_changes=True, velocities=False)
        w.add_attribute("drops", "warpsim:meanHeight", "double")
        for f, n in enumerate(counts):
            p = np.random.default_rng(f).random((n, 3))
            w.write_frame(f, {"drops": {"points": p, "ids": np.arange(n), "warpsim:meanHeight": p[:, 1].mean()}})
    times, panels = cache_series(path)
    np.testing.assert_array_equal(_panel(panels, "element counts")["lines"]["drops"], counts)
    heights = [np.random.default_rng(f).random((n, 3))[:, 1].mean() for f, n in enumerate(counts)]
    np.testing.assert_allclose(_panel(panels, "drops: meanHeight")["lines"]["meanHeight"], heights)
    code, text, _ = _run("plot", path, "--out", str(tmp_path / "c.png"))
    assert code == 0 and "2 panels" in text and (tmp_path / "c.png").exists()


def test_nothing_to_plot_is_a_usage_error(tmp_path):
    path = str(tmp_path / "s.usda")
    with UsdCacheWriter(path, fps=10) as w:
        w.add_points("p", velocities=False)
        for f in range(3):
            w.write_frame(f, {"p": {"points": np.zeros((2, 3))}})
    code, _, err = _run("plot", path)
    assert code == 2 and "no per-frame scalar data" in err
    code, _, err = _run("plot", str(tmp_path / "missing.usda"))
    assert code == 2 and "does not exist" in err

