"""The README cannot rot: every shell command (4-space indented blocks) and every ```python block
of README.md is run here, in README order in one working folder (later commands read the caches
earlier ones wrote), and must exit 0 and print what the table below says (``warpsim`` commands run
through ``warpsim.cli.main`` in this process, the console script's entry point; Python blocks run
in a fresh interpreter). The scene list equals ``warpsim list``.

The table is the contract. Each README command (exactly as written, comments stripped) maps to
the command run here (small ``--frames``/``--worlds`` substituted) and a text its output must hold,
or to ``skip("why")`` for what cannot run in a test (installs, the suite itself, servers, clusters,
GPUs). A README command missing from the table fails the test: add a row.
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


# README command -> (command run here, text the output must contain) or skip(reason)
COMMANDS = {
    "pip install -e . && warpsim run bounce": ("warpsim run bounce --frames 3", "wrote 4 frames"),
    'pip install -e ".[docs]" && python -m sphinx -W -b html docs docs/_build/html':
        skip(".ci/run builds the reference with -W"),
    'pip install -e ".[test,all]" && python -m pytest -q': skip("the suite itself"),
    "warpsim list": ("warpsim list", "teapot"),
    "warpsim run teapot --frames 120 --set drag=spout:0.3,0.9,0@0.3-0.8 --set obstacle=sphere":
        ("warpsim run teapot --frames 3 --set drag=spout:0.3,0.9,0@0.01-0.04 --set obstacle=sphere "
         "--set resolution=3", "of scene 'teapot'"),
    "warpsim run cloth --integrator implicit_euler --frames 240":
        ("warpsim run cloth --integrator implicit_euler --frames 3 --set resolution=8", "of scene 'cloth'"),
    "warpsim run dam_break --frames 90 --flatten":
        ("warpsim run dam_break --frames 61 --flatten --set spacing=0.06", "open: usd_out/dam_break.usdc"),
    "warpsim info usd_out/dam_break.usdc": ("warpsim info usd_out/dam_break.usdc", "frames 0..61"),
    "warpsim run zombies --frames 2400 --checkpoint-every 200":
        ("warpsim run zombies --frames 4 --checkpoint-every 2 --set zombies=20", "of scene 'zombies'"),
    "warpsim info usd_out/teapot.usda": ("warpsim info usd_out/teapot.usda", "teapot"),
    "warpsim run teapot --preview teapot.gif":
        ("warpsim run teapot --preview teapot.gif --frames 3 --set resolution=3", "preview: usd_out/teapot.gif"),
    "warpsim render usd_out/dam_break.usdc --out dam_break.mp4 --size 640x480":
        ("warpsim render usd_out/dam_break.usdc --out dam_break.mp4 --size 64x48 --frames 0:4", "wrote dam_break.mp4"),
    "warpsim render usd_out/teapot.usda --frame 60 --out teapot.png --camera 2,1.5,3,0,0.4,0":
        ("warpsim render usd_out/teapot.usda --frame 2 --out teapot.png --camera 2,1.5,3,0,0.4,0 --size 64x48",
         "wrote teapot.png"),
    "warpsim export usd_out/dam_break.usdc --frame 60 --out splash.obj --surface":
        ("warpsim export usd_out/dam_break.usdc --frame 60 --out splash.obj --surface --device cpu", "wrote frame 60"),
    "warpsim run pendulum --integrator rk4 --frames 600":
        ("warpsim run pendulum --integrator rk4 --frames 20", "of scene 'pendulum'"),
    "warpsim plot usd_out/pendulum.usda": ("warpsim plot usd_out/pendulum.usda", "wrote usd_out/pendulum.plot.png"),
    'pip install -e ".[viewer]"': skip("an install"),
    "warpsim view teapot": skip("serves until stopped (tests/test_viewer*.py drive the viewer)"),
    "warpsim view cloth --set integrator=implicit_euler --port 8090": skip("serves until stopped"),
    "warpsim view dam_break --device cuda:0 --max-points 200000": skip("serves until stopped, on a GPU"),
    "warpsim view usd_out/teapot.usda": skip("serves until stopped"),
    "warpsim sweep teapot --worlds 64 --vary stiffness=20:60 --vary restitution=0.2,0.5,0.8 --sample lhs --seed 1":
        ("warpsim sweep teapot --worlds 4 --frames 3 --vary stiffness=20:60 --vary restitution=0.2,0.5,0.8 "
         "--sample lhs --seed 1 --set resolution=3", "teapot_sweep"),
    "warpsim sweep bounce --worlds 12 --vary height=0.02:0.2:log --vary restitution=0.3,0.9 --layout grid":
        ("warpsim sweep bounce --worlds 4 --frames 3 --vary height=0.02:0.2:log --vary restitution=0.3,0.9 "
         "--layout grid", "bounce_sweep"),
    "warpsim sweep teapot --worlds 256 --vary height=0.3:0.6 --track spout --rank spout_peak_y:desc --top 5":
        ("warpsim sweep teapot --worlds 6 --frames 3 --vary height=0.3:0.6 --track spout --rank spout_peak_y:desc "
         "--top 5 --set resolution=3", "picked"),
    'warpsim sweep cloth --worlds 16 --vary bend=1:100:log --where "peak_speed<12" --set integrator=semi_implicit_euler':
        ('warpsim sweep cloth --worlds 2 --frames 3 --vary bend=1:100:log --where "peak_speed<12" '
         "--set integrator=semi_implicit_euler --set resolution=6", "cloth_sweep"),
    "warpsim sweep flock --vary seed=0,1,2,3":
        ("warpsim sweep flock --vary seed=0,1 --frames 3 --set birds=20 --set geese=4", "flock_sweep"),
    "warpsim view usd_out/teapot_sweep.usda": skip("serves until stopped"),
    'warpsim sweep bounce --worlds 15 --vary height=0.2:1.6 --set restitution=0 --fps 50 --frames 40 '
    '--inside "-0.5,0.4,-0.5,0.5,0.6,0.5@0.2:0.5" --rank inside1_entry':
        ('warpsim sweep bounce --worlds 8 --vary height=0.2:1.6 --set restitution=0 --fps 50 --frames 40 '
         '--inside "-0.5,0.4,-0.5,0.5,0.6,0.5@0.2:0.5" --rank inside1_entry', "inside1_entry"),
    'warpsim query usd_out/bounce_sweep.usda --inside "-0.5,0.4,-0.5,0.5,0.6,0.5@0.2:0.5" --rank inside1_entry':
        ('warpsim query usd_out/bounce_sweep.usda --inside "-0.5,0.4,-0.5,0.5,0.6,0.5@0.2:0.5" --rank inside1_entry',
         "inside1_entry"),
    'warpsim query usd_out/teapot_sweep.usda --outside "0.3,0,-1,1,1,1@0.5:" --where "peak_speed<3"':
        ('warpsim query usd_out/teapot_sweep.usda --outside "0.3,0,-1,1,1,1@0.02:" --where "peak_speed<3"',
         "world"),
    "warpsim pick usd_out/bounce_sweep.usda --world 7 --out world7.usdc --flatten":
        ("warpsim pick usd_out/bounce_sweep.usda --world 7 --out world7.usdc --flatten", "world7.usdc"),
    "warpsim view usd_out/bounce_sweep.usda": skip("serves until stopped"),
    "python benchmarks/check_determinism.py --device cuda:0 --frames 30": skip("a GPU check (benchmarks/)"),
    "warpsim sweep teapot --worlds 512 --vary stiffness=20:60 --vary restitution=0.2:0.8 --sample lhs "
    "--out usd_out/t.usda":
        ("warpsim sweep teapot --worlds 40 --frames 3 --vary stiffness=20:60 --vary restitution=0.2:0.8 --sample lhs "
         "--out usd_out/t.usda --set resolution=3", "usd_out/t.usda"),
    "warpsim run teapot --from-sweep usd_out/t.usda --world 39":
        ("warpsim run teapot --from-sweep usd_out/t.usda --world 39", "t.world_000039"),
    "warpsim sweep teapot --worlds 512 --vary stiffness=20:60 --vary restitution=0.2:0.8 --sample lhs --rerun 39":
        ("warpsim sweep teapot --worlds 40 --frames 3 --vary stiffness=20:60 --vary restitution=0.2:0.8 --sample lhs "
         "--set resolution=3 --rerun 39", "39"),
    "warpsim sweep teapot --worlds 1024 --vary stiffness=20:80 --vary restitution=0.2:0.8 --sample lhs "
    "--ray --batch-size 256 --out usd_out/teapots.usda": skip("starts a Ray cluster (tests/test_ray_sweep.py)"),
    "ray start --head --port=6379": skip("a multi-machine Ray cluster"),
    "ray start --address=HEAD_IP:6379": skip("a multi-machine Ray cluster"),
    "warpsim sweep teapot --worlds 4096 --vary stiffness=20:80 --sample lhs "
    "--ray HEAD_IP:6379 --batch-size 256 --out /shared/sweeps/teapots.usda": skip("a multi-machine Ray cluster"),
    "ray stop": skip("a multi-machine Ray cluster"),
}

# ```python blocks, by their first line -> (text the output must contain) or skip(reason)
PYTHON = {
    "import warpsim as ws\n\nv = ws.Viewer(": skip("serves on ports 8080 and 8081 until stopped (tests/test_viewer*.py "
                                                  "drive the viewer)"),
    "import warpsim as ws\n\nbuilder = ws.ModelBuilder()": "0.024304",
}
# what a Python block's comments promise, checked against its output (e.g. "y = 0.024304, v_y = -0.3924")
PROMISES = {"import warpsim as ws\n\nbuilder = ws.ModelBuilder()": ["0.024304", "-0.3924"]}


def readme_parts(text):
    """(shell commands, python blocks) of README text, in order. Shell commands are the lines of
    4-space indented blocks outside fences, comments stripped, backslash continuations joined."""
    commands, python, fence, body, pending = [], [], None, [], ""
    for line in text.splitlines():
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
            continue
        code = re.sub(r"\s+#.*$", "", line.strip()) if not line.strip().startswith("#") else ""
        if not code:
            continue
        if code.endswith("\\"):
            pending += code[:-1].strip() + " "
            continue
        commands.append(" ".join((pending + code).split()))
        pending = ""
    return commands, python


def python_key(block):
    return next((k for k in PYTHON if block.startswith(k)), None)


def run_command(command, cwd):
    """(exit status, stdout + stderr) of one command: ``warpsim ...`` through ``warpsim.cli.main``
    in this process (Warp starts once for all of them), anything else in a shell."""
    if command.startswith("warpsim "):
        from warpsim import cli

        out, err = io.StringIO(), io.StringIO()
        here = os.getcwd()
        os.chdir(cwd)
        try:
            code = cli.main(shlex.split(command)[1:], out, err)
        finally:
            os.chdir(here)
        return code, out.getvalue() + err.getvalue()
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    result = subprocess.run(command, shell=True, cwd=cwd, env=env, capture_output=True, text=True, timeout=600)
    return result.returncode, result.stdout + result.stderr


def test_every_readme_command_is_in_the_table():
    commands, python = readme_parts(README.read_text())
    assert len(commands) >= 20 and len(python) >= 2
    unknown = [c for c in commands if c not in COMMANDS]
    assert not unknown, "README commands missing from tests/test_readme.py's table (add a row each):\n" + \
        "\n".join(unknown)
    assert not [b.splitlines()[0] for b in python if python_key(b) is None], "README python blocks missing from PYTHON"
    stale = set(COMMANDS) - set(commands)
    assert not stale, f"table rows whose command the README no longer has: {sorted(stale)}"


def test_scene_list_equals_warpsim_list():
    from warpsim.scenes import scenes

    text = README.read_text()
    listed = re.search(r"^Scenes: (.*?)\. Options:", text, re.M | re.S)
    assert listed, "README lost its 'Scenes: ...' line"
    shipped = [n for n, cls in scenes().items() if cls.__module__.startswith("warpsim.")]  # not tests' own
    assert sorted(re.findall(r"`(\w+)`", listed.group(1))) == sorted(shipped)


def test_readme_runs(tmp_path):
    commands, python = readme_parts(README.read_text())
    ran = 0
    for command in commands:
        row = COMMANDS.get(command)
        if row is None or isinstance(row, skip):
            continue
        run_as, expect = row
        code, out = run_command(run_as, tmp_path)
        assert code == 0, f"README: {command}\nran: {run_as}\n{out[-3000:]}"
        assert expect in out, f"README: {command}\nran: {run_as}\nexpected {expect!r} in:\n{out[-3000:]}"
        ran += 1
    for block in python:
        key = python_key(block)
        if isinstance(PYTHON.get(key), skip):
            continue
        result = subprocess.run([sys.executable, "-c", block], cwd=tmp_path, capture_output=True, text=True,
                                timeout=600, env=dict(os.environ, PYTHONPATH=str(ROOT)))
        assert result.returncode == 0, f"README python block:\n{block}\n{result.stderr[-3000:]}"
        for promise in PROMISES.get(key, [PYTHON[key]]):
            assert promise in result.stdout, f"README python block prints {result.stdout!r}, README says {promise}"
        ran += 1
    assert ran >= 15
