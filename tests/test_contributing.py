"""CONTRIBUTING.md cannot rot: every command in its ```bash blocks is in ``COMMANDS`` and runs here
(``run``) or is run by CI or needs a GPU (``skip`` with the reason, checked where it can be); its
```python blocks run (the smallest solver steps through the protocol; the smallest scene and
the smallest command run from the command line); and its floors table, like the docs page's, is
``FLOORS`` of tests/test_import_graph.py."""

import io
import re
import runpy
import subprocess
from pathlib import Path

import numpy as np
from test_import_graph import FLOORS
from test_readme import run_command

ROOT = Path(__file__).resolve().parents[1]
GUIDE = ROOT / "CONTRIBUTING.md"
DOCS_PAGE = ROOT / "docs" / "contributing.rst"


class skip(str):
    """A command the test does not run, with the reason."""


class run:
    """A command run here, with a text its output must hold."""

    def __init__(self, expect):
        self.expect = expect


CI = "CI runs it (.ci/run)"
COMMANDS = {
    'python3 -m pip install -q -e ".[test,all,docs]"': skip(CI),
    "warpsim list": run("bounce"),
    "warpsim run bounce --frames 3 --out usd_out/bounce.usda": run("bounce.usda"),
    "warpsim info usd_out/bounce.usda": run("frames"),
    "python3 -m pytest -q tests/test_import_graph.py": skip("the suite runs it"),
    "python3 -m mypy": skip(CI),
    "python3 -m sphinx -q -W -b html docs docs/_build/html": skip(CI),
    "python3 benchmarks/bench_mass_spring.py --device cpu --grid 16 --steps 20": run("ratio"),
    "bash benchmarks/run_gpu.sh core": skip("needs a CUDA device"),
}


def guide_blocks(text):
    """(commands of ```bash blocks, ```python blocks) in order."""
    commands, python = [], []
    for lang, body in re.findall(r"^```(\w*)\n(.*?)^```", text, re.M | re.S):
        if lang == "bash":
            commands += [" ".join(line.split()) for line in body.splitlines() if line.strip()]
        elif lang == "python":
            python.append(body)
    return commands, python


def test_every_command_is_in_the_table():
    commands, python = guide_blocks(GUIDE.read_text())
    assert len(commands) >= 8 and len(python) == 3
    assert not [c for c in commands if c not in COMMANDS], "add a row to COMMANDS for each new command"
    assert not set(COMMANDS) - set(commands), "COMMANDS has rows the guide no longer shows"


def test_what_ci_runs_is_in_ci_and_the_gpu_group_exists():
    ci = (ROOT / ".ci" / "run").read_text()
    for command, row in COMMANDS.items():
        if row == CI:
            assert command in ci, f"{command!r} is not what .ci/run runs"
        if row == "the suite runs it":
            assert (ROOT / command.split()[-1]).is_file()
    script = ROOT / "benchmarks" / "run_gpu.sh"
    assert subprocess.run(["bash", "-n", str(script)], check=False).returncode == 0
    assert re.search(r"^\s*core\)", script.read_text(), re.M)


def test_the_commands_run(tmp_path):
    commands, _ = guide_blocks(GUIDE.read_text())
    for command in commands:
        row = COMMANDS[command]
        if isinstance(row, skip):
            continue
        code, out = run_command(command, tmp_path)  # in this process; what they write lands in tmp_path
        assert code == 0, f"{command}: exit {code}\n{out[-3000:]}"
        assert row.expect in out, f"{command}: {row.expect!r} not in its output\n{out[-3000:]}"


def test_the_smallest_solver_steps_through_the_protocol(tmp_path):
    _, python = guide_blocks(GUIDE.read_text())
    path = tmp_path / "drift.py"  # a file: Warp reads a kernel's source
    path.write_text(python[0])
    namespace = runpy.run_path(str(path))  # the block asserts x = v t after a frame of 5 steps
    from warpsim.core.solver import Solver

    assert isinstance(namespace["drift"], Solver)


def test_the_smallest_scene_runs_from_the_command_line(tmp_path, monkeypatch):
    from pxr import Usd

    from warpsim import cli, scenes

    monkeypatch.setattr(scenes, "_REGISTRY", dict(scenes.scenes()))  # the guide's scene stays in this test
    _, python = guide_blocks(GUIDE.read_text())
    path = tmp_path / "drop.py"
    path.write_text(python[1])
    runpy.run_path(str(path))
    out, err = io.StringIO(), io.StringIO()
    cache = tmp_path / "drop.usda"
    assert cli.main(["run", "drop", "--frames", "30", "--set", "count=5", "--out", str(cache)], out, err) == 0, \
        err.getvalue()
    stage = Usd.Stage.Open(str(cache))
    points = stage.GetPrimAtPath("/World/particles").GetAttribute("points")
    y0, y1 = (np.asarray(points.Get(f))[:, 1] for f in (0, 30))
    assert (y1 < y0).all() and (y1 > -0.011).all()  # they fell and the floor held them


def test_the_smallest_command_runs_through_the_dispatcher(tmp_path, monkeypatch):
    from warpsim import cli

    _, python = guide_blocks(GUIDE.read_text())
    (tmp_path / "hello_command.py").write_text(python[2])
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setitem(cli.COMMANDS, "hello", "hello_command")  # the one line in COMMANDS
    for argv, status, text in ((["hello", "--name", "floors"], 0, "hello, floors"),
                               (["hello", "--name", " "], 2, "warpsim: error: --name is empty"),
                               (["hello", "--shout"], 2, "unrecognized arguments: --shout")):
        out, err = io.StringIO(), io.StringIO()
        assert cli.main(argv, out, err) == status, err.getvalue()
        assert text in out.getvalue() + err.getvalue()
        assert len(err.getvalue().splitlines()) == (status != 0)  # a mistake is one line


def _floors_of(text, row):
    """{floor: folder names} from the table rows ``row`` matches (floor number, then the folders)."""
    return {int(m.group(1)): re.findall(r"`+(\w+)`+", m.group(2)) for m in re.finditer(row, text, re.M)}


def test_the_floors_tables_are_the_tests_floors():
    expected = {i: list(rooms) for i, rooms in enumerate(FLOORS)}
    assert _floors_of(GUIDE.read_text(), r"^\| (\d+) \| (.*?) \|") == expected
    assert _floors_of(DOCS_PAGE.read_text(), r"^   \* - (\d+)\n     - (.*)$") == expected
    index = (ROOT / "docs" / "index.rst").read_text()
    assert re.search(r"^   contributing$", index, re.M), "docs/contributing.rst is not in the toctree"
