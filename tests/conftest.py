"""Shared pytest setup: Warp quiet, every test on the "cpu" device (CUDA too when present), and the
quick subset (``python -m pytest -q -m quick``: the modules in ``QUICK``, 36 s on 2 cores with
Warp's kernel cache warm, 53 s with an empty one): integrators, forces, plane collisions, cloth contact, fracture, timing,
bad input, hardening, the public API and the import floors."""

import pytest
import warp as wp

wp.config.quiet = True
wp.init()

QUICK = ("test_bad_input", "test_cloth_contact", "test_forces", "test_fracture", "test_hardening_iv",
         "test_import_graph", "test_integrators", "test_plane_collisions", "test_public_api", "test_shared_helpers",
         "test_timing")
"""Test modules marked ``quick``."""

DEVICES = ["cpu"] + (["cuda:0"] if wp.is_cuda_available() else [])


@pytest.fixture(params=DEVICES)
def device(request):
    """Each test that takes ``device`` runs on the CPU, and on CUDA when one is present."""
    return request.param


def pytest_collection_modifyitems(config, items):
    """Mark the tests of the ``QUICK`` modules ``quick``."""
    for item in items:
        if item.path.stem in QUICK:
            item.add_marker(pytest.mark.quick)
