"""Shared pytest setup: Warp quiet, every test on the "cpu" device (CUDA too when present)."""

import pytest
import warp as wp

wp.config.quiet = True
wp.init()

DEVICES = ["cpu"] + (["cuda:0"] if wp.is_cuda_available() else [])


@pytest.fixture(params=DEVICES)
def device(request):
    """Each test that takes ``device`` runs on the CPU, and on CUDA when one is present."""
    return request.param
