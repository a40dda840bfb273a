"""The host work of a large sweep made fast without changing a result (issue 50): the stability
estimate's spring adjacency taken from the model's own CSR (tiled on the device for a batch) is
the sorted definition entry for entry; per-world bounds taken one component at a time are NumPy's
plain min/max bit for bit; automatic chunks hold at most 128 MiB."""

import numpy as np

from warpsim.core.stability import _adjacency
from warpsim.scenes import get_scene
from warpsim.sweeps.sweep import make_batch, sample_worlds
from warpsim.sweeps.usd import AUTO_CHUNK_BYTES, MAX_CHUNK_FRAMES, auto_chunk_frames
from warpsim.usd.frame_arrays import world_bounds, world_extents


def sorted_adjacency(idx, n):
    """The definition: every spring end, by particle and then spring index."""
    S = len(idx)
    owner = np.concatenate([idx[:, 0], idx[:, 1]])
    other = np.concatenate([idx[:, 1], idx[:, 0]])
    spring = np.concatenate([np.arange(S), np.arange(S)])
    order = np.lexsort((spring, owner))
    offsets = np.zeros(n + 1, np.int64)
    np.cumsum(np.bincount(owner, minlength=n), out=offsets[1:])
    return offsets, spring[order], other[order]


def test_stability_adjacency_is_the_sorted_definition():
    batch = make_batch(get_scene("teapot"), sample_worlds("teapot", {}, ["stiffness=20:60"], 7), device="cpu")
    for model in (batch.scene.sim.model, batch._springs_model()):
        offsets, springs, other, idx = _adjacency(model)
        want = sorted_adjacency(idx, model.particle_count)
        assert model.spring_count > 0
        for got, expected in zip((offsets, springs, other), want):
            assert np.array_equal(got.numpy(), expected)


def test_world_bounds_are_numpys_min_and_max():
    rng = np.random.default_rng(5)
    points = rng.normal(size=(9, 37, 3)).astype(np.float32)
    points[4, 3, 1] = np.nan  # a blown-up world: NaN bounds, as NumPy gives
    lo, hi = world_bounds(points)
    assert np.array_equal(lo, points.min(axis=1), equal_nan=True)
    assert np.array_equal(hi, points.max(axis=1), equal_nan=True)
    ok = np.delete(points, 4, axis=0)
    pad = rng.uniform(0.0, 0.1, 37).astype(np.float32)
    extents = world_extents(ok, pad)
    assert np.array_equal(extents[:, 0], (ok - pad[None, :, None]).min(axis=1))
    assert np.array_equal(extents[:, 1], (ok + pad[None, :, None]).max(axis=1))
    extents = world_extents(ok, 0.25)
    assert np.array_equal(extents[:, 0], ok.min(axis=1) - np.float32(0.25))


def test_automatic_chunks_hold_at_most_128_mib():
    assert auto_chunk_frames(1_000) == MAX_CHUNK_FRAMES == 24  # small sweeps: as before
    teapots = 2000 * 18_888  # 2,000 teapots' points, velocities and springs a frame [bytes]
    frames = auto_chunk_frames(teapots)
    assert frames * teapots <= AUTO_CHUNK_BYTES < (frames + 1) * teapots
    assert auto_chunk_frames(10 * AUTO_CHUNK_BYTES) == 1  # a frame larger than a chunk: one frame each


def test_stability_by_world_blocks_is_all_springs_at_once_bit_for_bit(monkeypatch):
    """A batch's estimate by blocks of whole worlds (``tiled``, blocks of a few worlds here, worked on in
    threads) gives every limit of the estimate over all springs at once, bit for bit: the limiting
    spring, its values and each world's per-spring and per-particle limits."""
    import warpsim.core.stability as stability

    batch = make_batch(get_scene("teapot"), sample_worlds("teapot", {}, ["stiffness=20:60"], 7), device="cpu")
    monkeypatch.setattr(stability, "SPRING_BLOCK", 3 * batch.model.world_spring_count)  # 3 worlds a block
    sim, model = batch.sim, batch._springs_model()
    runs = [stability.particle_limits(model, batch.model.particle_q, sim.integrator, sim.forces, sim.colliders,
                                      particle_world=batch.model.particle_world.numpy(), world_count=batch.world_count,
                                      iterations=20, tiled=tiled)
            for tiled in (None, (batch.model.world_particle_count, batch.model.world_spring_count))]
    for w, (a, b) in enumerate(zip(*runs)):
        assert a.limiting == "spring" and a.index // batch.model.world_spring_count == w  # a spring of its own world
        assert vars(a).keys() == vars(b).keys()
        for name, value in vars(a).items():
            other = vars(b)[name]
            assert np.array_equal(value, other) if isinstance(value, np.ndarray) else value == other, name
