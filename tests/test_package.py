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
