"""The package: public names resolve, import stays light, the version is set."""

import subprocess
import sys

import warpsim as ws


def test_every_public_name_resolves():
    missing = [name for name in ws.__all__ if not hasattr(ws, name)]
    assert not missing, missing
    for name in ("ModelBuilder", "Simulator", "Gravity", "Plane", "__version__"):
        assert name in ws.__all__


def test_import_does_not_load_usd_or_trimesh():
    code = "import sys, warpsim; print('pxr' in sys.modules, 'trimesh' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out == ["False", "False"]


def test_kernels_ship_inside_the_package():
    import warpsim.kernels

    assert warpsim.kernels.__name__ == "warpsim.kernels"
    assert ws.__version__.count(".") == 2


def test_every_scene_module_imports_and_registers():
    """The registry skips a scene module that fails to import (so one broken scene cannot take the
    command line down); this test makes such a failure loud."""
    import importlib
    import pkgutil

    import warpsim.scenes as scenes

    for info in pkgutil.iter_modules(scenes.__path__, scenes.__name__ + "."):
        importlib.import_module(info.name)
    names = set(scenes.scenes())
    expected = {"bounce", "pendulum", "springs", "teapot", "cloth", "drape", "metaballs", "dam_break", "pour",
                "smoke", "liquid", "flip_splash", "flock", "school", "zombies", "crowd"}
    assert expected <= names, sorted(expected - names)
