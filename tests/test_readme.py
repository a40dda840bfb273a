"""The README cannot rot: every command it names runs here, and must exit 0 and print what the
README says it does: the shell commands of its 4-space indented blocks, every `warpsim ...` and
`python ...` command in its prose and tables (inline code), and every ```python block. They run in
README order in one working folder (later commands read the caches earlier ones wrote), in this
process: ``warpsim`` commands through ``warpsim.cli.main`` (the console script's entry point),
``python`` scripts (named by their path in the repository) and modules through runpy; Python
blocks in a fresh interpreter. The scene list equals ``warpsim list``.

The table is the contract. Each README command maps to ``run(expect, *changes)``: the README's text
with the listed visible changes (``"OLD => NEW"`` or ``"+ EXTRA"``), each one of the size changes
``SHRINK`` allows (fewer worlds or pixels, a coarser scene, the CPU, a placeholder's value; never
fewer frames than the README's, or than the default 120 where it gives none: a false alarm late in a
run must show here),
and a text its output must hold; a query (``picks=True``) must pick at least one world and not all.
``skip("why")`` is only for what cannot run in a test (installs, the suite itself, servers,
clusters). A README command missing from the table fails the test: add a row. A bare command name
(`warpsim info`) must be a command the README also runs.
"""

import io
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path


ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"


class skip(str):
    """A README command the test does not run, with the reason."""


class run:
    """A README command run here: the README's text with visible ``changes`` (``"OLD => NEW"``,
    ``"+ EXTRA"``; each one of ``SHRINK``), the text its output must hold, and for a query
    (``picks=True``) at least one world picked and not all."""

    def __init__(self, expect, *changes, picks=False):
        self.expect, self.changes, self.picks = expect, changes, picks

    def command(self, readme):
        """The command run for README command ``readme``."""
        text = readme
        for change in self.changes:
            if change.startswith("+ "):
                text += " " + change[2:]
                continue
            old, new = change.split(" => ")
            tokens = shlex.split(text, posix=False)
            if " " not in old.strip() and tokens.count(old) == 1:  # one token (a placeholder such as N)
                text = " ".join(new if t == old else t for t in tokens)
            else:
                assert text.count(old) == 1, f"change {change!r}: {old!r} is not once in {readme!r}"
                text = text.replace(old, new)
        return " ".join(text.split())


# the changes a row may make: (pattern OLD and NEW (or an EXTRA) each match, why)
SHRINK = [
    (r"--(worlds|steps) \d+", "fewer worlds or steps (a benchmark's)"),
    (r"--frames \d+:\d+", "a few frames of a picture"),
    (r"--frame \d+", "a frame inside the shorter run"),
    (r"--vary seed=[\d,]+", "fewer seeds (worlds)"),
    (r"--size \d+x\d+", "fewer pixels"),
    (r"--grid( \d+)+", "a smaller grid"),
    (r"--set (resolution|spacing|count|zombies|birds|geese)=[\w.]+", "a coarser or smaller scene"),
    (r"--device (cpu|cuda:0)", "the CPU (tests have no GPU)"),
    (r"--scenes \w+", "one scene of a per-scene script"),
    (r"pip install -e [.\w\"\[\],]* && ", "the install: the test runs in the installed package"),
    (r"(\[--\w+ )?[A-Z][A-Z_]*\]?", "a placeholder (OLD) ..."),
]
PLACEHOLDER_VALUE = r"(--\w+ )?[\w./:]+"  # ... and the value it stands for (NEW)


# README command -> run(...) or skip(reason), in README order
COMMANDS = {
    "pip install -e . && warpsim run bounce":
        run("wrote 121 frames", "pip install -e . &&  => "),
    'pip install -e ".[docs]" && python -m sphinx -W -b html docs docs/_build/html':
        skip(".ci/run builds the reference with -W"),
    'pip install -e ".[test,all]" && python -m pytest -q': skip("the suite itself"),
    "python -m pytest -q -m quick": skip("a subset of the suite itself"),
    "warpsim info usd_out/bounce.usda": run("frames 0..120"),
    "warpsim info ROOT": skip("a sweep killed mid-run: tests/test_hardening_records.py "
                              "test_info_on_a_killed_first_sweep_names_the_staged_frames_and_resume"),
    "warpsim list": run("teapot"),
    "warpsim run teapot --frames 120 --set drag=spout:0.3,0.9,0@0.3-0.8 --set obstacle=sphere":
        run("of scene 'teapot'", "+ --set resolution=3"),
    "warpsim run cloth --integrator implicit_euler --frames 240":
        run("wrote 241 frames", "+ --set resolution=12"),
    "warpsim run dam_break --frames 90 --flatten":
        run("open: usd_out/dam_break.usdc", "+ --set spacing=0.06"),
    "warpsim info usd_out/dam_break.usdc": run("frames 0..90"),
    "warpsim run zombies --frames 2400 --checkpoint-every 200":
        run("wrote 2401 frames", "+ --set zombies=20"),
    "warpsim info usd_out/teapot.usda": run("teapot"),
    "warpsim run teapot --preview":
        run("preview: usd_out/teapot.gif", "+ --set resolution=3"),
    "warpsim render usd_out/dam_break.usdc --out dam_break.mp4 --size 640x480":
        run("wrote dam_break.mp4", "--size 640x480 => --size 64x48", "+ --frames 0:4"),
    "warpsim render usd_out/teapot.usda --frame 60 --out teapot.png --camera 2,1.5,3,0,0.4,0":
        run("wrote teapot.png", "+ --size 64x48"),
    "warpsim export usd_out/dam_break.usdc --frame 60 --out splash.obj --surface":
        run("wrote frame 60", "+ --device cpu"),
    "warpsim run pendulum --integrator rk4 --frames 600":
        run("wrote 601 frames"),
    "warpsim plot usd_out/pendulum.usda": run("wrote usd_out/pendulum.plot.png"),
    'pip install -e ".[viewer]"': skip("an install"),
    "warpsim view teapot": skip("serves until stopped (tests/test_viewer*.py drive the viewer)"),
    "warpsim view cloth --set integrator=implicit_euler --port 8090": skip("serves until stopped"),
    "warpsim view dam_break --device cuda:0 --max-points 200000": skip("serves until stopped, on a GPU"),
    "warpsim view usd_out/teapot.usda": skip("serves until stopped"),
    "python docs/viewer_pictures.py":
        skip("the README's viewer pictures in headless Chromium: tests/test_readme_pictures.py runs it"),
    "warpsim view usd_out/bounce.usda": skip("serves until stopped"),
    "warpsim view SCENE": skip("serves until stopped"),
    "warpsim render CACHE": run("wrote usd_out/pendulum.gif", "CACHE => usd_out/pendulum.usda", "+ --size 64x48",
                                "+ --frames 0:4"),
    "warpsim plot CACHE": run("wrote usd_out/pendulum.plot.png", "CACHE => usd_out/pendulum.usda"),
    "warpsim export CACHE [--frame N] --out FILE":
        run("wrote frame 2 to", "CACHE => usd_out/teapot.usda", "[--frame N] => --frame 2", "FILE => teapot.obj"),
    "python -m warpsim.render.gallery": run("1 previews", "+ --scenes bounce"),
    "warpsim run donuts --set count=1000 --set segments=12 --set sides=6 --set lattice_cells=5 --set box=2.4 "
    "--frames 18 --fps 20 --substeps 60 --out usd_out/donuts_heap.usdc":
        run("usd_out/donuts_heap.usdc", "--set count=1000 => --set count=2"),
    "warpsim render usd_out/donuts_heap.usdc --out docs/donuts_heap.png --size 960x540 --camera 2.6,2.2,4.2,0,0.1,0.2":
        run("wrote docs/donuts_heap.png", "--size 960x540 => --size 64x36"),
    "warpsim sweep teapot --worlds 64 --vary stiffness=20:60 --vary restitution=0.2,0.5,0.8 --sample lhs --seed 1":
        run("teapot_sweep", "--worlds 64 => --worlds 4", "+ --set resolution=3"),
    "warpsim sweep bounce --worlds 12 --vary height=0.02:0.2:log --vary restitution=0.3,0.9 --layout grid":
        run("bounce_sweep", "--worlds 12 => --worlds 4"),
    "warpsim sweep teapot --worlds 256 --vary height=0.3:0.6 --track spout --rank spout_peak_y:desc --top 5":
        run("picked 5 of 6", "--worlds 256 => --worlds 6", "+ --set resolution=3", picks=True),
    'warpsim sweep cloth --worlds 16 --vary bend=1:100:log --where "peak_speed<12" --set integrator=semi_implicit_euler':
        run("cloth_sweep", "--worlds 16 => --worlds 4", "+ --set resolution=12", picks=True),
    "warpsim sweep flock --vary seed=0,1,2,3":
        run("flock_sweep", "--vary seed=0,1,2,3 => --vary seed=0,1", "+ --set birds=20",
            "+ --set geese=4"),
    "warpsim view usd_out/teapot_sweep.usda": skip("serves until stopped"),
    'warpsim sweep bounce --worlds 15 --vary height=0.2:1.6 --set restitution=0 --fps 50 --frames 40 '
    '--inside "-0.5,0.4,-0.5,0.5,0.6,0.5@0.2:0.5" --rank inside1_entry':
        run("inside1_entry", "--worlds 15 => --worlds 8", picks=True),
    'warpsim query usd_out/bounce_sweep.usda --inside "-0.5,0.4,-0.5,0.5,0.6,0.5@0.2:0.5" --rank inside1_entry':
        run("inside1_entry", picks=True),
    'warpsim query usd_out/teapot_sweep.usda --outside "-1,0,-1,1,0.55,1@0:0.25"':
        run("picked", picks=True),
    "warpsim pick usd_out/bounce_sweep.usda --world 7 --out world7.usdc --flatten": run("world7.usdc"),
    "warpsim view usd_out/bounce_sweep.usda": skip("serves until stopped"),
    "warpsim sweep --ray ADDRESS": skip("a Ray cluster (tests/test_ray_sweep.py)"),
    "warpsim sweep teapot --worlds 512 --vary stiffness=20:60 --vary restitution=0.2:0.8 --sample lhs "
    "--out usd_out/t.usda":
        run("usd_out/t.usda", "--worlds 512 => --worlds 40", "+ --set resolution=3"),
    "warpsim run teapot --from-sweep usd_out/t.usda --world 39": run("t.world_000039"),
    "warpsim sweep teapot --worlds 512 --vary stiffness=20:60 --vary restitution=0.2:0.8 --sample lhs --rerun 39":
        run("39", "--worlds 512 => --worlds 40", "+ --set resolution=3"),
    "warpsim sweep teapot --worlds 1024 --vary stiffness=20:80 --vary restitution=0.2:0.8 --sample lhs "
    "--ray --batch-size 256 --out usd_out/teapots.usda": skip("starts a Ray cluster (tests/test_ray_sweep.py)"),
    "ray start --head --port=6379": skip("a multi-machine Ray cluster"),
    "ray start --address=HEAD_IP:6379": skip("a multi-machine Ray cluster"),
    "warpsim sweep teapot --worlds 4096 --vary stiffness=20:80 --sample lhs "
    "--ray HEAD_IP:6379 --batch-size 256 --out /shared/sweeps/teapots.usda": skip("a multi-machine Ray cluster"),
    "ray stop": skip("a multi-machine Ray cluster"),
    "warpsim run SCENE --from-sweep ROOT --world N":
        run("t.world_000039", "SCENE => teapot", "ROOT => usd_out/t.usda", "N => 39"),
    "python benchmarks/check_determinism.py --device cuda:0 --frames 30":
        run("identical", "--device cuda:0 => --device cpu", "+ --scenes bounce"),
    "python benchmarks/bench_mass_spring.py --device cuda:0 --grid 64 256 512":
        run("numpy ms", "--device cuda:0 => --device cpu", "--grid 64 256 512 => --grid 8", "+ --steps 2"),
}

# ```python blocks, by their first line -> (text the output must contain) or skip(reason)
PYTHON = {
    "import warpsim as ws\n\nv = ws.Viewer(": skip("serves on ports 8080 and 8081 until stopped (tests/test_viewer*.py "
                                                  "drive the viewer)"),
    "import warpsim as ws\n\nbuilder = ws.ModelBuilder()": "0.024304",
}
# what a Python block's comments promise, checked against its output (e.g. "y = 0.024304, v_y = -0.3924")
PROMISES = {"import warpsim as ws\n\nbuilder = ws.ModelBuilder()": ["0.024304", "-0.3924"]}


INLINE = re.compile(r"`((?:[A-Z_]+=\S+ )?(?:warpsim|python3?) [^`]+)`")
"""Inline code that is a command: `warpsim ...`, `python ...` (an environment variable first allowed)."""


def readme_parts(text):
    """(commands, python blocks, command names) of README text. Commands, in README order: the lines
    of 4-space indented blocks outside fences (comments stripped, backslash continuations joined)
    and inline code in prose and tables that is a command (``INLINE``); a bare `warpsim NAME` is a
    command name, not a command."""
    found, python, fence, body, pending, prose = [], [], None, [], "", []
    for number, line in enumerate(text.splitlines()):
        prose.append("")
        if fence is not None:
            if line.startswith("```"):
                if fence == "python":
                    python.append("\n".join(body))
                fence, body = None, []
            else:
                body.append(line)
            continue
        if line.startswith("```"):
            fence = line[3:].strip()
            continue
        if not line.startswith("    ") or not line.strip():
            prose[-1] = line
            continue
        code = re.sub(r"\s+#.*$", "", line.strip()) if not line.strip().startswith("#") else ""
        if not code:
            continue
        if code.endswith("\\"):
            pending += code[:-1].strip() + " "
            continue
        found.append((number, " ".join((pending + code).split())))
        pending = ""
    names, prose_text = [], "\n".join(prose)
    for match in INLINE.finditer(prose_text):
        command = " ".join(match.group(1).split())
        if re.fullmatch(r"warpsim [a-z]+", command):
            names.append(command)
        else:
            found.append((prose_text.count("\n", 0, match.start()), command))
    return [c for _, c in sorted(found, key=lambda item: item[0])], python, names


def python_key(block):
    return next((k for k in PYTHON if block.startswith(k)), None)


def run_command(command, cwd):
    """(exit status, stdout + stderr) of one command, run in ``cwd`` in this process (Warp starts
    once for all of them): ``warpsim ...`` through ``warpsim.cli.main`` (the console script's entry
    point), ``python SCRIPT.py ...`` (a script under the repository) and ``python -m MODULE ...``
    through runpy as ``__main__``."""
    import contextlib
    import runpy

    argv = shlex.split(command)
    out, err = io.StringIO(), io.StringIO()
    here, saved_argv, saved_path = os.getcwd(), sys.argv, list(sys.path)
    os.chdir(cwd)
    try:
        if argv[0] == "warpsim":
            from warpsim import cli

            return cli.main(argv[1:], out, err), out.getvalue() + err.getvalue()
        assert argv[0] in ("python", "python3"), f"cannot run {command!r} here: add a way to run it"
        module = argv[2] if argv[1] == "-m" else None
        sys.argv = [module or str(ROOT / argv[1]), *argv[3 if module else 2:]]
        code = 0
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                if module:
                    runpy.run_module(module, run_name="__main__", alter_sys=True)
                else:  # as `python SCRIPT` does: the script's folder first on the path
                    sys.path.insert(0, os.path.dirname(sys.argv[0]))
                    runpy.run_path(sys.argv[0], run_name="__main__")
            except SystemExit as exc:
                code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        return code, out.getvalue() + err.getvalue()
    finally:
        sys.argv, sys.path[:] = saved_argv, saved_path
        os.chdir(here)


def test_every_readme_command_is_in_the_table():
    commands, python, names = readme_parts(README.read_text())
    assert len(commands) >= 40 and len(python) >= 2 and len(names) >= 5
    assert "warpsim run SCENE --from-sweep ROOT --world N" in commands  # inline code over two lines
    assert "python -m warpsim.render.gallery" in commands  # prose
    unknown = [c for c in commands if c not in COMMANDS]
    assert not unknown, "README commands missing from tests/test_readme.py's table (add a row each):\n" + \
        "\n".join(unknown)
    assert not [b.splitlines()[0] for b in python if python_key(b) is None], "README python blocks missing from PYTHON"
    stale = set(COMMANDS) - set(commands)
    assert not stale, f"table rows whose command the README no longer has: {sorted(stale)}"


def test_every_command_name_is_a_command_the_readme_runs():
    from warpsim import cli

    commands, _, names = readme_parts(README.read_text())
    known = cli._parser(["--help"])._subparsers._group_actions[0].choices
    ran = [c for c in commands if isinstance(COMMANDS.get(c), run)]
    for name in set(names):
        assert name.split()[1] in known, f"README names `{name}`, not a warpsim command"
        assert any(c.startswith(name + " ") for c in ran), f"README names `{name}` but runs no such command"


def test_scene_list_equals_warpsim_list():
    from warpsim.scenes import scenes

    text = README.read_text()
    listed = re.search(r"^Scenes: (.*?)\. Options:", text, re.M | re.S)
    assert listed, "README lost its 'Scenes: ...' line"
    shipped = [n for n, cls in scenes().items() if cls.__module__.startswith("warpsim.")]  # not tests' own
    assert sorted(re.findall(r"`(\w+)`", listed.group(1))) == sorted(shipped)


def _shrinks(change):
    """Whether one change of a row is a size change ``SHRINK`` allows."""
    sizes = [pattern for pattern, _ in SHRINK[:-1]]
    if change.startswith("+ "):
        return any(re.fullmatch(p, change[2:]) for p in sizes)
    old, new = change.split(" => ")
    if re.fullmatch(SHRINK[-1][0], old):
        return re.fullmatch(PLACEHOLDER_VALUE, new) is not None
    return any(re.fullmatch(p, old) and (re.fullmatch(p, new) or (p.startswith("pip") and new == "")) for p in sizes)


def test_rows_change_only_sizes():
    bad = [(c, change) for c, row in COMMANDS.items() if isinstance(row, run) for change in row.changes
           if not _shrinks(change)]
    assert not bad, f"changes beyond SHRINK's size changes: {bad}"
    assert not _shrinks("--set stiffness=80 => --set stiffness=20") and not _shrinks("+ --set integrator=rk4")
    # never fewer frames than the README's (or the default 120 where it gives none): issue 49's cloth died at
    # frame 21 of the README's 240 while this test ran 3
    assert not _shrinks("--frames 240 => --frames 3") and not _shrinks("+ --frames 3")
    assert run("x", "--worlds 64 => --worlds 4", "+ --frames 3").command(
        "warpsim sweep teapot --worlds 64 --seed 1") == "warpsim sweep teapot --worlds 4 --seed 1 --frames 3"


def picked(out):
    """(picked, of) from a sweep's or query's 'picked K of N worlds' line."""
    found = re.findall(r"picked (\d+) of (\d+) worlds", out)
    assert len(found) == 1, out[-2000:]
    return tuple(map(int, found[0]))


def test_readme_runs(tmp_path):
    commands, python, _ = readme_parts(README.read_text())
    ran = 0
    for command in commands:
        row = COMMANDS.get(command)
        if not isinstance(row, run):
            continue
        run_as = row.command(command)
        code, out = run_command(run_as, tmp_path)
        assert code == 0, f"README: {command}\nran: {run_as}\n{out[-3000:]}"
        assert row.expect in out, f"README: {command}\nran: {run_as}\nexpected {row.expect!r} in:\n{out[-3000:]}"
        if row.picks:  # a query the README shows picks something, not everything
            k, n = picked(out)
            assert 0 < k < n, f"README: {command}\nran: {run_as}\npicks {k} of {n} worlds"
        ran += 1
    for block in python:
        key = python_key(block)
        if isinstance(PYTHON.get(key), skip):
            continue
        result = subprocess.run([sys.executable, "-c", block], cwd=tmp_path, capture_output=True, text=True,
                                timeout=600,
                                env=dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])))
        assert result.returncode == 0, f"README python block:\n{block}\n{result.stderr[-3000:]}"
        for promise in PROMISES.get(key, [PYTHON[key]]):
            assert promise in result.stdout, f"README python block prints {result.stdout!r}, README says {promise}"
        ran += 1
    assert ran >= 30
