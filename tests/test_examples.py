"""Every example runs for a few frames in a subprocess (as a user would run it)."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]

# example script -> arguments that keep it short
EXAMPLES = {
    "bouncing_ball.py": ["--frames", "3"],
    "pendulum_integrators.py": ["--steps", "20", "--rows", "2", "--figure", "out/energy.png"],
    "implicit_surface.py": ["--resolution", "24", "--out", "implicit_surface.usda"],
    "flock.py": ["--frames", "3", "--out", "flock.usda"],
    "fit_launch.py": ["--quick"],  # exits 1 unless the landing is within 1 mm of the target
    "fit_cloth.py": ["--quick"],  # exits 1 unless both values are within 1 % of the hidden ones
    "hair_implicit.py": ["--frames", "3", "--strands", "12", "--segments", "6"],
}


def run_example(name, args, tmp_path):
    env = dict(os.environ, WARP_QUIET="1")
    return subprocess.run([sys.executable, str(ROOT / "examples" / name), *args], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=600)


# example script -> the figure it saves (relative to its working folder) and its size [px]
FIGURES = {"pendulum_integrators.py": ("out/energy.png", (630, 360))}


@pytest.mark.parametrize("name", sorted(EXAMPLES))
def test_example_runs(name, tmp_path):
    result = run_example(name, EXAMPLES[name], tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    if name in FIGURES:
        from PIL import Image

        path, size = FIGURES[name]
        with Image.open(tmp_path / path) as fig:
            assert fig.size == size
            assert len(np.unique(np.asarray(fig.convert("RGB")).reshape(-1, 3), axis=0)) > 50  # curves drawn


def test_bouncing_ball_prints_the_seed_frame_table(tmp_path):
    out = run_example("bouncing_ball.py", ["--frames", "2"], tmp_path).stdout.splitlines()
    rows = {int(line.split()[0]): [float(x) for x in line.split()[1:]] for line in out if line.strip()[:1].isdigit()}
    assert rows[1][2] == pytest.approx(0.024304, abs=1e-6) and rows[1][3] == pytest.approx(-0.3924, abs=1e-4)
    assert rows[2][2] == pytest.approx(0.5 * 0.007088, abs=1e-6) and rows[2][3] == pytest.approx(0.3924, abs=1e-4)



def _fit_launch():
    import importlib.util

    spec = importlib.util.spec_from_file_location("fit_launch", ROOT / "examples" / "fit_launch.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.Example(duration=1.1, device="cpu")


def test_fit_launch_gradient_matches_central_differences():
    """The example's dL/dv0 (crossings seeded by hand, the tape through the reflection) against
    central differences of its own loss, at launches whose two touch-down steps stay put."""
    example = _fit_launch()
    for v in (np.array([2.0, 2.3, 0.5]), np.array([1.5, 2.8, 0.4])):
        _, grad = example.loss_and_gradient(v)
        steps = [k for k, *_ in example.touchdowns(v)]
        fd = []
        for i in range(3):
            h = np.eye(3)[i] * 1.0e-3
            assert [k for k, *_ in example.touchdowns(v + h)] == steps == [k for k, *_ in example.touchdowns(v - h)]
            fd.append((example.loss_and_gradient(v + h)[0] - example.loss_and_gradient(v - h)[0]) / 2.0e-3)
        assert np.abs(grad - fd).max() < 1.0e-3 * np.abs(fd).max()


def test_fit_launch_landing_time_is_a_sawtooth_under_reflection():
    """The docstring's reason for fitting the first-bounce time, not the landing time: with the
    lecture's reflection the landing time falls with vy while the first bounce stays in one step
    and jumps up by about 2.7 dt when it moves on; the first-bounce time rises smoothly."""
    example = _fit_launch()
    landing, bounce = [], []
    for vy in np.arange(2.0, 2.2001, 0.01):
        _, t, t1 = example.result(np.array([1.0, vy, 0.3]))
        landing.append(t)
        bounce.append(t1)
    d_landing, d_bounce = np.diff(landing), np.diff(bounce)
    assert np.all((d_bounce > 0.0015) & (d_bounce < 0.0025))  # ~ dt1/dvy = (1 + vy / |v_impact|) / g
    falls, jumps = d_landing[d_landing < 0.0], d_landing[d_landing > 0.0]
    assert len(falls) >= 14 and np.all(falls > -0.004)
    assert len(jumps) == 4 and np.all((jumps > 2.5 * example.dt) & (jumps < 2.9 * example.dt))
    assert landing[-1] > landing[0]  # the trend the exact gradient does not see

def test_every_example_is_listed():
    scripts = {p.name for p in (ROOT / "examples").glob("*.py")}
    missing = scripts - set(EXAMPLES) - OTHER_TESTED
    assert not missing, f"examples without a smoke test: {sorted(missing)}"


# examples smoke-tested in their own area's test file
OTHER_TESTED = {
    "metaballs.py",  # tests/test_marching_cubes.py
    "dam_break.py",  # tests/test_sph.py
    "teapot.py",  # tests/test_softbody.py
    "collisions.py",  # tests/test_colliders.py
    "cloth_drape.py",  # tests/test_cloth.py
    "cloth_implicit.py",  # tests/test_cloth.py
    "smoke.py",  # tests/test_grid_fluids.py
    "levelset_liquid.py",  # tests/test_grid_fluids.py
}


def test_teapot_that_blows_up_exits_1_and_says_so(tmp_path):
    # 20 g spread over 538 particles with 40 N/m springs at dt = 1/600 s is far past the stability limit
    result = run_example("teapot.py", ["--mass", "0.02", "--frames", "3", "--out", "t.usda"], tmp_path)
    assert result.returncode == 1, result.stdout[-2000:] + result.stderr[-2000:]
    assert "blew up at frame 1" in result.stderr and "wrote" not in result.stdout
    assert (tmp_path / "t.usda").is_file()  # the frames before the blow-up stay readable


def test_examples_print_no_warp_module_lines(tmp_path):
    # (--verbose goes through the same warpsim.verbosity switch the CLI test below turns on)
    quiet = run_example("bouncing_ball.py", ["--frames", "2"], tmp_path)
    assert quiet.returncode == 0
    assert "Module warpsim.kernels" not in quiet.stdout + quiet.stderr
    assert "Warp " not in quiet.stdout  # nor the start-up banner inside the table


def test_cli_prints_warp_module_lines_only_with_verbose(tmp_path):
    def run(*extra):
        return subprocess.run([sys.executable, "-m", "warpsim", "run", "bounce", "--frames", "2", "--no-progress",
                               "--out", "b.usda", *extra], cwd=tmp_path, capture_output=True, text=True, timeout=600)

    quiet, loud = run(), run("--verbose")
    assert quiet.returncode == 0 and loud.returncode == 0, quiet.stderr + loud.stderr
    assert "Module warpsim.kernels" not in quiet.stdout + quiet.stderr
    assert "Module warpsim.kernels" in loud.stdout + loud.stderr


def test_examples_write_under_usd_out():
    """Every output flag's default (``--out``, ``--figure``) is under usd_out/ (or None / '')."""
    import ast

    bad = []
    for path in sorted((ROOT / "examples").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if not (isinstance(node, ast.Call) and getattr(node.func, "attr", "") == "add_argument" and node.args):
                continue
            flag = getattr(node.args[0], "value", None)
            default = next((k.value for k in node.keywords if k.arg == "default"), None)
            if flag in ("--out", "--figure") and isinstance(default, ast.Constant) and default.value:
                if not str(default.value).startswith("usd_out/"):
                    bad.append(f"{path.name} {flag}={default.value!r}")
        for line in path.read_text().splitlines():  # the usage lines in the docstring too
            if line.startswith("    python examples/") and "--out " in line and "--out usd_out/" not in line \
                    and "--out ''" not in line:  # ('' writes no cache)
                bad.append(f"{path.name}: {line.strip()}")
    assert not bad, f"examples writing outside usd_out/: {bad}"


@pytest.mark.parametrize("name, blocked, args, says", [
    ("pendulum_integrators.py", "matplotlib", ["--steps", "5", "--rows", "1"], 'pip install "warpsim[plot]"'),
    ("fit_launch.py", "scipy", ["--quick"], "pip install scipy"),
])
def test_examples_name_a_missing_optional_module(tmp_path, name, blocked, args, says):
    """An example needing an optional module says which install brings it, before any work."""
    code = (f"import sys, runpy; sys.modules[{blocked!r}] = None; sys.argv = [{name!r}, *{args!r}]; "
            f"runpy.run_path({str(ROOT / 'examples' / name)!r}, run_name='__main__')")
    result = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert result.returncode in (1, 2) and says in result.stderr, result.stderr[-2000:]
    assert "Traceback" not in result.stderr and not list(tmp_path.iterdir())


def _example_module(name):
    import importlib.util

    spec = importlib.util.spec_from_file_location(name[:-3], ROOT / "examples" / name)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


ALL_EXAMPLES = sorted(p.name for p in (ROOT / "examples").glob("*.py"))


@pytest.mark.parametrize("name", ALL_EXAMPLES)
def test_every_example_fails_in_one_line_and_shows_its_defaults(name, tmp_path, capsys, monkeypatch):
    """A device that does not exist is one line naming the devices there are and exit 2 (as the
    ``warpsim`` command line), before anything is built or written; ``--help`` shows the defaults."""
    from warpsim.cli_common import run_script

    monkeypatch.chdir(tmp_path)
    assert "run_script(main)" in (ROOT / "examples" / name).read_text()  # so from a shell too
    module = _example_module(name)
    capsys.readouterr()
    assert run_script(module.main, ["--device", "nosuch:0"], prog=name) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"{name}: error: --device 'nosuch:0' is not available"), err
    assert "available: cpu" in err and not list(tmp_path.iterdir())
    with pytest.raises(SystemExit) as exit_:
        module.main(["--help"])
    assert exit_.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    parser_defaults = [line for line in (ROOT / "examples" / name).read_text().splitlines()
                       if "add_argument(" in line and "default=" in line and "store_true" not in line
                       and "default=None" not in line]
    assert parser_defaults and text.count("(default:") >= len(parser_defaults), text


@pytest.mark.parametrize("script, args, says", [
    ("examples/dam_break.py", ["--spacing", "0.06"], "dam_break.py: error: --spacing 0.06 m is too coarse"),
    ("examples/teapot.py", ["--frames", "ten"], "argument --frames: invalid int value: 'ten'"),
    ("benchmarks/bench_mass_spring.py", ["--device", "cuda:9"], "bench_mass_spring.py: error: --device 'cuda:9'"),
])
def test_a_bad_value_is_one_line_and_exit_2(script, args, says, tmp_path):
    """Run as a user runs them: no traceback, one line on stderr, exit status 2, nothing written."""
    result = subprocess.run([sys.executable, str(ROOT / script), *args], check=False, cwd=tmp_path,
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 2, result.stderr[-2000:]
    assert "Traceback" not in result.stderr and says in result.stderr, result.stderr
    assert result.stderr.strip().splitlines()[-1].count(":") >= 2 and not list(tmp_path.iterdir())
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 or script.endswith("teapot.py"), lines  # argparse: usage line + the error
