"""Batched worlds on the shared-topology path (issue 27): springs, adjacency and base parameters
stored once, one fused kernel per sub-step. Bit-identical to the tiled path and to each world's
scene run alone; within 1e-6 m of the former float-atomic spring scatter over 240 steps."""

import numpy as np
import pytest
import warp as wp

from warpsim.scenes import get_scene
from warpsim.sweeps import sample_worlds
from warpsim.worlds import WorldBatch
from warpsim.worlds.plan import StructuralError
from warpsim.scenes.timing import resolve_timing
from warpsim.scenes.timing import resolve_timing

# (varying the teapot's mass scales its per-vertex masses as (mass at 1 kg) x mass in float32, which
# rounds differently from the scene's own total / count: worlds then agree with their scenes to
# rounding only, world 0 included)
CASES = {
    "teapot": ({"resolution": "3"}, ["stiffness=20:60", "restitution=0.2:0.8", "height=0.3:0.6"]),
    "springs": ({"shape": "lattice", "count": 4}, ["stiffness=200:600", "mass=0.02:0.1", "damping=0.01:0.2",
                                                   "gravity=3:12"]),
    "bounce": ({}, ["restitution=0.2:0.9", "height=0.02:0.1", "friction=0:0.5"]),
}


def _worlds(name, n=4):
    fixed, vary = CASES[name]
    return get_scene(name), sample_worlds(name, fixed, vary, n, sample="lhs", seed=1)


def _fixed_steps(*scenes_or_batches):
    """Sub-step counts fixed at the scene's default: auto sub-stepping follows the stiffest world
    of a batch, a scene alone its own limit (another step count, another result)."""
    for x in scenes_or_batches:
        scene = getattr(x, "batch_scene", None) or x
        scene.use_timing(resolve_timing(type(scene), scene.params, substeps=type(scene).substeps))


def _frames(batch, frame_dt, substeps, frames):
    for _ in range(frames):
        batch.advance(frame_dt, substeps)
    return batch.world_slices()


@pytest.mark.parametrize("name", sorted(CASES))
def test_shared_path_is_bit_identical_to_the_tiled_path_and_to_each_world_alone(name):
    cls, worlds = _worlds(name)
    timing = resolve_timing(cls, cls.resolve_params(worlds[0]))
    substeps, frame_dt = timing.steps, timing.frame_dt
    shared = WorldBatch(cls, worlds, device="cpu")
    tiled = WorldBatch(cls, worlds, device="cpu", shared=False)
    assert shared.shared and not tiled.shared
    _fixed_steps(shared, tiled)
    frames = 8
    xs, vs = _frames(shared, frame_dt, substeps, frames)
    xt, vt = _frames(tiled, frame_dt, substeps, frames)
    assert xs.tobytes() == xt.tobytes() and vs.tobytes() == vt.tobytes()
    assert np.abs(xs[0] - xs[1]).max() > 1e-4  # the worlds differ
    # world 0 (the tiling base) equals its scene run alone bit for bit; every world within rounding
    for w in range(len(worlds)):
        scene = cls(cls.resolve_params(worlds[w]), device="cpu")
        _fixed_steps(scene)
        for _ in range(frames):
            scene.advance(frame_dt, substeps)
        alone = scene.sim.state.positions.numpy()
        if w == 0:
            assert alone.tobytes() == xs[0].tobytes()
        assert np.abs(alone - xs[w]).max() <= 1e-6, w
    assert np.abs(xs[0] - shared.scene.sim.model.particle_q.numpy()).max() > 1e-3  # it moved


def test_shared_topology_is_stored_once():
    cls, worlds = _worlds("teapot")
    batch = WorldBatch(cls, worlds, device="cpu")
    m = batch.model
    S = m.world_spring_count
    assert S > 0 and m.spring_count == len(worlds) * S
    per_world = [name for name, a in vars(m).items() if isinstance(a, wp.array) and a.shape[0] >= len(worlds) * S]
    assert per_world == []  # no array per spring per world
    springs = batch.stepper.springs
    assert springs.entries.shape[0] == 2 * S and springs.keys.shape[0] == 2 * S  # once, not per world


def test_shared_world_gathers_follow_the_atomics_path_within_a_micrometre_over_240_steps():
    cls, worlds = _worlds("springs")
    params = cls.resolve_params(worlds[0])
    timing = resolve_timing(cls, params)
    substeps, frame_dt = timing.steps, timing.frame_dt
    shared = WorldBatch(cls, worlds, device="cpu")
    atomics = WorldBatch(cls, worlds, device="cpu", shared=False)
    springs = [f for f in atomics.sim.forces if type(f).__name__ == "Springs"]
    assert len(springs) == 1
    springs[0].deterministic = False  # the former scatter with float atomics
    frames = -(-240 // substeps)
    xs, _ = _frames(shared, frame_dt, substeps, frames)
    xa, _ = _frames(atomics, frame_dt, substeps, frames)
    assert frames * substeps >= 240
    assert 0.0 <= np.abs(xs - xa).max() <= 1e-6  # [m]
    assert np.abs(xs - atomics.scene.sim.model.particle_q.numpy()[None]).max() > 1e-2  # it swung


def test_shared_true_names_what_the_scene_lacks():
    cls = get_scene("cloth")
    worlds = sample_worlds("cloth", {"resolution": 4, "integrator": "semi_implicit_euler"}, ["density=0.1:0.3"], 2,
                           sample="lhs")
    with pytest.raises(StructuralError, match="ClothSimulator"):
        WorldBatch(cls, worlds, device="cpu", shared=True)
    assert not WorldBatch(cls, worlds, device="cpu").shared  # cloth keeps its own simulator


@pytest.mark.parametrize("substeps", [3, 4])  # odd: the frame ends in the spare buffers and copies home
def test_one_launch_per_frame_gives_the_per_step_paths_bits(substeps):
    cls, worlds = _worlds("teapot")
    frame_dt = resolve_timing(cls, cls.resolve_params(worlds[0])).frame_dt
    steps = WorldBatch(cls, worlds, device="cpu")
    blocks = WorldBatch(cls, worlds, device="cpu", block_per_world=True)
    _fixed_steps(steps, blocks)
    xs, vs = _frames(steps, frame_dt / 10 * substeps, substeps, 6)
    xb, vb = _frames(blocks, frame_dt / 10 * substeps, substeps, 6)
    assert blocks.stepper.block_per_world and blocks.sim.state.positions is blocks.stepper._home[0]
    assert xs.tobytes() == xb.tobytes() and vs.tobytes() == vb.tobytes()
    assert np.abs(xs - blocks.scene.sim.model.particle_q.numpy()[None]).max() > 1e-3
