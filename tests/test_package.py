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


def _source_modules(root):
    """Dotted names of every module in the checkout's warpsim/ and kernels/ (as installed)."""
    names = []
    for top, installed in (("warpsim", "warpsim"), ("kernels", "warpsim.kernels")):
        for path in sorted((root / top).rglob("*.py")):
            parts = list(path.relative_to(root / top).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            if parts and parts[-1] == "__main__":
                continue
            names.append(".".join([installed, *parts]))
    return names


def test_installed_wheel_holds_every_module(tmp_path):
    """Build the wheel from a copy of the checkout, unpack it, and import every module of the source
    tree from the unpacked wheel in a fresh interpreter outside the checkout: a sub-package that
    packaging misses fails here."""
    import pathlib
    import shutil
    import zipfile

    root = pathlib.Path(__file__).resolve().parents[1]
    src = tmp_path / "src"
    src.mkdir()
    for name in ("pyproject.toml", "setup.py", "README.md"):
        shutil.copy(root / name, src / name)
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc")
    for name in ("warpsim", "kernels"):
        shutil.copytree(root / name, src / name, ignore=ignore)
    wheels = tmp_path / "wheels"
    subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", "-w",
                    str(wheels), str(src)], check=True, capture_output=True, text=True)
    (wheel,) = wheels.glob("warpsim-*.whl")
    site = tmp_path / "site"
    zipfile.ZipFile(wheel).extractall(site)
    assert not (site / "kernels").exists(), "the wheel installs a top-level 'kernels' package"

    modules = _source_modules(root)
    code = ("import importlib, sys, pathlib\n"
            "bad = []\n"
            f"for name in {modules!r}:\n"
            "    m = importlib.import_module(name)\n"
            f"    if not pathlib.Path(m.__file__).resolve().is_relative_to(pathlib.Path({str(site)!r}).resolve()):\n"
            "        bad.append((name, m.__file__))\n"
            "print(len(sys.modules)); print(bad)\n")
    env = {k: v for k, v in __import__("os").environ.items() if k != "PYTHONPATH"}
    env["PYTHONPATH"] = str(site)
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split("\n")[1] == "[]", out.stdout
    assert len(modules) > 60
