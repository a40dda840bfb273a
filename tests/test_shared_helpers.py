"""The generic helpers one floor down (``warpsim.core.memory``, ``warpsim.core.names``) and their
users: the donuts scene's memory check reads the shared host figure, scene parameters get the
shared "Did you mean" hint."""

import types

import numpy as np
import pytest
import warp as wp

from warpsim.core.memory import available_host_bytes
from warpsim.core.names import close_matches


def test_available_host_bytes_is_meminfo():
    try:
        with open("/proc/meminfo") as f:
            kib = next(int(line.split()[1]) for line in f if line.startswith("MemAvailable:"))
    except OSError:
        pytest.skip("no /proc/meminfo")
    # the figure moves while other processes run: within 1 GiB of a read made just before
    assert abs(available_host_bytes() - kib * 1024) < 1 << 30


def test_close_matches_names_the_near_ones():
    assert close_matches("stifness", ["stiffness", "damping"]) == " Did you mean 'stiffness'?"
    assert close_matches("zzz", ["stiffness", "damping"]) == ""


def test_the_donuts_check_refuses_more_tori_than_the_host_holds():
    from warpsim.scenes.fracture import check_donut_memory

    torus = types.SimpleNamespace(faces=np.zeros((4000, 3)), particle_count=2000, spring_count=10000)
    per_torus = 300 * 2000 + 120 * 10000 + 260 * 4000 + 200 * 2000 + 250 * 10000  # host and CPU device bytes
    too_many = int(available_host_bytes() / per_torus) + 1
    with pytest.raises(ValueError, match=f"count={too_many} tori .* need about .* on the host"):
        check_donut_memory(too_many, torus, wp.get_device("cpu"))
    check_donut_memory(1, torus, wp.get_device("cpu"))  # one torus fits


def test_scene_parameters_get_the_hint():
    from warpsim.scenes import get_scene

    with pytest.raises(ValueError, match="Did you mean 'stiffness'"):
        get_scene("springs").resolve_params({"stifness": "3"})
