"""One rule for where outputs go, stated in every writing command's ``--help`` and the README: a
path you give (``--out``, ``--preview``, ``--record-dir``) is taken as written, a relative one from
the current folder; without one a new cache goes to usd_out/ and what is made from a cache (a
picture, a plot) goes beside it."""

import io
import re
from pathlib import Path

import pytest

from warpsim import cli

RULE = "a relative path is taken from the current folder"
# command -> the options that name what it writes
WRITERS = {"run": ["--out", "--preview"], "sweep": ["--out"], "render": ["--out"], "plot": ["--out"],
           "export": ["--out"], "pick": ["--out"], "view": ["--record-dir"]}


def warpsim(*argv):
    out, err = io.StringIO(), io.StringIO()
    code = cli.main([str(a) for a in argv], out, err)
    return code, out.getvalue() + err.getvalue()


@pytest.mark.parametrize("command", sorted(WRITERS))
def test_every_writing_option_states_the_rule(command):
    parser = cli._parser([command])._subparsers._group_actions[0].choices[command]  # what --help prints
    for option in WRITERS[command]:
        text = " ".join(parser._option_string_actions[option].help.split())
        assert RULE in text, f"warpsim {command} {option}: --help says {text!r}, not '{RULE}'"


def test_readme_states_the_rule():
    text = " ".join((Path(__file__).resolve().parents[1] / "README.md").read_text().split())
    assert "taken as written, a relative one from the current folder" in text


def test_given_paths_are_taken_from_the_current_folder(tmp_path, monkeypatch):
    """``run --preview NAME`` writes NAME in the current folder like ``render --out`` and ``export
    --out`` do (it went beside the cache); without a path, pictures go beside their cache."""
    pytest.importorskip("PIL")
    monkeypatch.chdir(tmp_path)
    code, text = warpsim("run", "bounce", "--frames", 2, "--out", "sub/b.usda", "--preview", "p.gif",
                         "--no-progress")
    assert code == 0, text
    assert (tmp_path / "p.gif").is_file() and not (tmp_path / "sub" / "p.gif").exists()
    assert "preview: p.gif" in text
    code, text = warpsim("run", "bounce", "--frames", 2, "--out", "sub/c.usda", "--preview", "--no-progress")
    assert code == 0 and (tmp_path / "sub" / "c.gif").is_file(), text  # no name: beside the cache
    code, text = warpsim("render", "sub/b.usda", "--out", "r.png", "--size", "32x24", "--device", "cpu")
    assert code == 0 and (tmp_path / "r.png").is_file(), text
    code, text = warpsim("render", "sub/b.usda", "--size", "32x24", "--frames", "0:1", "--device", "cpu")
    assert code == 0 and (tmp_path / "sub" / "b.gif").is_file(), text
    code, text = warpsim("export", "sub/b.usda", "--out", "e.ply", "--prims", "ball")
    assert code == 0 and (tmp_path / "e.ply").is_file(), text
