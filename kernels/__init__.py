"""Warp kernels of warpsim, one module per stage (installed as ``warpsim.kernels``)."""
