"""Commands that need an optional extra check for it before any work and print one line naming
``pip install "warpsim[EXTRA]"`` with exit status 2. A missing module is simulated with
``sys.modules[name] = None`` (what Python does for a blocked import)."""

import io
import os

import pytest

from warpsim import cli
from warpsim.extras import EXTRAS, missing_modules, require_extra


def run_cli(argv):
    out, err = io.StringIO(), io.StringIO()
    return cli.main(argv, out, err), out.getvalue(), err.getvalue()


def block(monkeypatch, *modules):
    for name in modules:
        monkeypatch.setitem(__import__("sys").modules, name, None)


def assert_one_line(code, err, extra):
    assert code == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("warpsim: error: "), err
    assert f'pip install "warpsim[{extra}]"' in lines[0]


def test_missing_modules_sees_a_blocked_import(monkeypatch):
    assert missing_modules(["os", "no_such_module_warpsim_x"]) == ["no_such_module_warpsim_x"]
    block(monkeypatch, "json")
    assert missing_modules(["json"]) == ["json"]
    with pytest.raises(ValueError, match="unknown extra 'nope'"):
        require_extra("nope", "x")


def test_extras_match_pyproject():
    text = open(os.path.join(os.path.dirname(cli.__file__), "..", "pyproject.toml")).read()
    for extra in EXTRAS:
        assert f"\n{extra} = [" in text, f"extra {extra!r} is not in pyproject.toml"


@pytest.mark.parametrize("suffix, blocked", [(".gif", "PIL"), (".mp4", "imageio_ffmpeg")])
def test_render_without_its_extra(monkeypatch, tmp_path, suffix, blocked):
    block(monkeypatch, blocked)
    code, _, err = run_cli(["render", str(tmp_path / "missing.usda"), "--out", str(tmp_path / f"x{suffix}")])
    assert_one_line(code, err, "render")  # the extra is named before the (missing) cache is even looked at
    assert ("pillow" if blocked == "PIL" else "imageio-ffmpeg") in err


def test_png_needs_no_extra(monkeypatch, tmp_path):
    """A .png is written by warpsim.render.png (zlib only): Pillow blocked, the picture is written."""
    cache, png = tmp_path / "b.usda", tmp_path / "b.png"
    assert run_cli(["run", "bounce", "--frames", "2", "--out", str(cache), "--no-progress"])[0] == 0
    block(monkeypatch, "PIL")
    code, _, err = run_cli(["render", str(cache), "--out", str(png), "--size", "32x24"])
    assert code == 0, err
    monkeypatch.undo()
    from PIL import Image

    assert Image.open(png).size == (32, 24)


def test_run_preview_without_render_extra_stops_before_simulating(monkeypatch, tmp_path):
    block(monkeypatch, "PIL")
    cache = tmp_path / "b.usda"
    code, out, err = run_cli(["run", "bounce", "--frames", "2", "--out", str(cache), "--preview", "b.gif",
                              "--no-progress"])
    assert_one_line(code, err, "render")
    assert not cache.exists() and out == ""  # no simulation ran


def test_plot_without_its_extra(monkeypatch, tmp_path):
    block(monkeypatch, "matplotlib")
    code, _, err = run_cli(["plot", str(tmp_path / "missing.usda")])
    assert_one_line(code, err, "plot")


def test_view_without_its_extra(monkeypatch):
    block(monkeypatch, "viser")
    code, _, err = run_cli(["view", "bounce"])
    assert_one_line(code, err, "viewer")


def test_sweep_ray_without_its_extra(monkeypatch, tmp_path):
    block(monkeypatch, "ray")
    out_path = tmp_path / "s.usda"
    code, _, err = run_cli(["sweep", "bounce", "--worlds", "2", "--frames", "2", "--vary", "restitution=0.3,0.9",
                            "--ray", "--out", str(out_path)])
    assert_one_line(code, err, "ray")
    assert not os.listdir(tmp_path)  # nothing written
