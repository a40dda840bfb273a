"""Package discovery (metadata lives in pyproject.toml): every package under warpsim/ is found, and
the top-level kernels/ folder installs as warpsim.kernels (no top-level ``kernels`` module)."""

from setuptools import find_packages, setup

setup(
    packages=find_packages(include=["warpsim", "warpsim.*"])
    + ["warpsim.kernels"] + [f"warpsim.kernels.{p}" for p in find_packages("kernels")],
    package_dir={"warpsim.kernels": "kernels"},
)
