"""The hair scene's frame stepping (``warpsim.strands.frame.HairFrame``): the head's poses read
from the device give the same bits as the eager steps with launch-parameter poses, and a frame
allocates nothing (what a CUDA graph of the frame needs; the graph itself is measured on the GPU
by benchmarks/bench_hair.py, its bits by benchmarks/check_hair_graph.py)."""

import numpy as np
import pytest
import warp as wp

from warpsim.scenes import get_scene

DEVICE = "cpu"
PARAMS = {"strands": 6, "segments": 8, "still": 0.0, "motion": "turn_nod", "sag_free": False}


def test_frames_with_device_poses_equal_eager_steps_bit_for_bit():
    """The head turning and nodding from t = 0: 20 frames through ``HairFrame`` (posed head and
    roots) and 20 frames of plain ``Simulator.step`` calls (the head's poses as launch
    parameters) give identical positions, velocities, head pose, clock and step count."""
    framed = get_scene("hair")(PARAMS, device=DEVICE)
    eager = get_scene("hair")(PARAMS, device=DEVICE)
    n = framed.frame_steps(1.0 / 60.0, 1)
    assert n == 4
    for _ in range(20):
        framed.advance(1.0 / 60.0, 1)
        for _ in range(n):
            eager.sim.step(1.0 / 60.0 / n)
    a, b = framed.sim.state, eager.sim.state
    assert np.array_equal(a.positions.numpy(), b.positions.numpy())
    assert np.array_equal(a.velocities.numpy(), b.velocities.numpy())
    for x, y in zip(framed.head.world_pose(), eager.head.world_pose()):
        assert np.array_equal(x, y)
    assert (framed.sim.time, framed.sim.step_count) == (eager.sim.time, eager.sim.step_count)
    assert framed.sim.step_count == 80 and abs(framed.sim.time - 20 / 60) < 1e-12
    tips = framed.hair.tip_particles()
    assert np.abs(a.positions.numpy()[tips] - framed.model.particle_q.numpy()[tips]).max() > 0.01  # it moved


def test_hair_frames_allocate_nothing(monkeypatch):
    """After the first frame (buffers, the device pose array), a frame of the implicit step with
    the head moving allocates no memory: every allocation on the CPU device goes through its
    allocator, counted here."""
    scene = get_scene("hair")(PARAMS, device=DEVICE)
    for _ in range(2):
        scene.advance(1.0 / 60.0, 1)
    allocator = wp.get_device(DEVICE).default_allocator
    sizes = []
    allocate = allocator.allocate
    monkeypatch.setattr(allocator, "allocate", lambda size: sizes.append(size) or allocate(size))
    wp.zeros(4, dtype=float, device=DEVICE)
    assert sizes == [16]  # the counter sees allocations
    sizes.clear()
    for _ in range(3):
        scene.advance(1.0 / 60.0, 1)
    monkeypatch.undo()
    assert sizes == []
