"""warpsim: physics-based animation solvers written as NVIDIA Warp kernels."""
from ._version import __version__
