"""Quiet by default, verbose on request (issue 42): a five-line API script and a ``warpsim``
command print none of Warp's start-up banner, its native "no CUDA driver" line or its module-load
lines; ``WARPSIM_VERBOSE=1`` brings them back; a cold kernel cache is announced once, before the
first compile, and a warm one not at all. Each check is a fresh Python process."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

FIVE_LINES = """
import warpsim as ws
builder = ws.ModelBuilder()
builder.add_particle((0.0, 0.04, 0.0), mass=1.0)
sim = ws.Simulator(builder.finalize(), forces=[ws.Gravity()], colliders=[ws.Plane()])
sim.step(0.04)
print("height", float(sim.state.positions.numpy()[0, 1]))
"""

# two kernels in two modules of their own: two compiles on a cold cache, one notice
TWO_KERNELS = """
import warpsim as ws
import warp as wp
ws.Gravity  # the first public name applies warpsim's verbosity
@wp.kernel(module="unique")
def twice(a: wp.array(dtype=float)):
    a[wp.tid()] = 2.0 * a[wp.tid()]
@wp.kernel(module="unique")
def plus_one(a: wp.array(dtype=float)):
    a[wp.tid()] = a[wp.tid()] + 1.0
x = wp.ones(3, dtype=float, device="cpu")
wp.launch(twice, dim=3, inputs=[x], device="cpu")
wp.launch(plus_one, dim=3, inputs=[x], device="cpu")
print("values", x.numpy().tolist())
"""

NOISE = ("Could not find or load the NVIDIA CUDA driver", "initialized:", "Module ", "Kernel cache:")


def _run(args, tmp_path, **env):
    base = {k: v for k, v in os.environ.items() if k not in ("WARPSIM_VERBOSE", "WARP_QUIET")}
    return subprocess.run([sys.executable, *args], check=False, cwd=tmp_path, capture_output=True, text=True,
                          timeout=300,
                          env={**base, "PYTHONPATH": str(ROOT), **env})


def test_an_api_script_is_quiet(tmp_path):
    quiet = _run(["-c", FIVE_LINES], tmp_path)
    assert quiet.returncode == 0, quiet.stderr
    assert abs(float(quiet.stdout.split()[-1]) - (0.04 - 9.81 * 0.04 ** 2)) < 1e-6  # it ran: v = -g h, x += v h
    said = quiet.stdout + quiet.stderr
    assert not [n for n in NOISE if n in said], said


def test_a_cold_kernel_cache_is_announced_once(tmp_path):
    cache = tmp_path / "kernels"
    (tmp_path / "two_kernels.py").write_text(TWO_KERNELS)  # Warp reads a kernel's source from its file
    first = _run(["two_kernels.py"], tmp_path, WARP_CACHE_PATH=str(cache))
    assert first.returncode == 0 and "values [3.0, 3.0, 3.0]" in first.stdout, first.stderr
    assert first.stderr.count("compiling Warp kernels on first use") == 1, first.stderr
    assert str(cache) in first.stderr and "cached" in first.stderr  # where they are kept
    assert not [n for n in NOISE if n in first.stdout + first.stderr], first.stderr
    second = _run(["two_kernels.py"], tmp_path, WARP_CACHE_PATH=str(cache))
    assert second.returncode == 0 and second.stderr == "", second.stderr  # warm: nothing to say
    verbose = _run(["two_kernels.py"], tmp_path, WARP_CACHE_PATH=str(cache), WARPSIM_VERBOSE="1")
    said = verbose.stdout + verbose.stderr  # on request: Warp's banner and module-load lines
    assert verbose.returncode == 0 and "initialized:" in said and "(cached)" in said, said
    assert "compiling Warp kernels" not in said


def test_the_command_line_is_quiet(tmp_path):
    result = _run(["-m", "warpsim", "run", "bounce", "--frames", "1", "--device", "cpu", "--out", "b.usda"],
                  tmp_path)
    assert result.returncode == 0, result.stderr
    said = result.stdout + result.stderr
    assert "wrote" in result.stdout and not [n for n in NOISE if n in said], said
