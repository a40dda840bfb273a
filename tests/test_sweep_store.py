"""Issue 50: every world's frame data at once (the scene's frame_arrays) equals the per-world
frame_data() on a swapped-in state, sample for sample; the sweep's --store modes."""
import os

import numpy as np
import pytest

from warpsim.scenes import get_scene
from warpsim.sweeps.sweep import make_batch
from warpsim.usd.frame_arrays import described, world_samples
from warpsim.sweeps.usd import BatchLayerWriter

# every scene a WorldBatch steps (small sizes), with a key that varies between its worlds
SWEEPABLE = [
    ("bounce", {}, "restitution", [0.3, 0.8]),
    ("springs", {}, "stiffness", [50.0, 200.0]),
    ("teapot", {"resolution": 6}, "stiffness", [20.0, 60.0]),
    ("teapot", {"resolution": 6, "obstacle": "paddle"}, "stiffness", [20.0, 60.0]),
    ("hair", {"strands": 8, "segments": 4}, "mass", [0.001, 0.002]),
    ("donuts", {"count": 2}, "stiffness", [1000.0, 2000.0]),
    ("cloth", {"resolution": 6, "integrator": "semi_implicit_euler"}, "structural", [500.0, 900.0]),
    ("wall", {}, "ball_speed", [3.0, 5.0]),
]


@pytest.mark.parametrize("name,fixed,key,values", SWEEPABLE, ids=[f"{s[0]}-{i}" for i, s in enumerate(SWEEPABLE)])
def test_batch_frame_data_equals_each_worlds_frame_data(tmp_path, name, fixed, key, values):
    cls = get_scene(name)
    params = [{**fixed, key: v} for v in values]
    batch = make_batch(cls, params, device="cpu")
    writer = BatchLayerWriter(tmp_path / f"{name}.usdc", batch.scene, 0, batch.world_count, 25.0)  # declares
    for _ in range(2):  # frame 0 and a stepped frame (the worlds differ by then)
        x, v = batch.world_slices()
        batched = batch.batch_frame_data(x, v)
        if name == "wall":  # its springs are each world's unbroken ones: asked world by world
            assert batched is None and described(batch.scene) is None
            break
        assert batched is not None
        per = [batch.world_frame_data(x[w], v[w], w) for w in range(batch.world_count)]
        for prim, decl in writer.dynamic.items():
            every = world_samples(decl, batched[prim], 3, batch.world_count)
            for w, data in enumerate(per):
                one = decl.frame_samples(data[prim], 3)
                assert list(one) == list(every), prim  # the order samples are authored in
                for attr, value in one.items():
                    got = np.asarray(every[attr][w])
                    assert got.dtype == np.asarray(value).dtype and got.tobytes() == np.asarray(value).tobytes(), \
                        (prim, attr, w)
        if any(not np.array_equal(x[0], x[w]) for w in range(1, batch.world_count)):
            assert not all(np.array_equal(batched[p]["points"][0], batched[p]["points"][1])
                           for p in batched if "points" in batched[p])
        batch.advance(1.0 / 25.0, 2)


def test_lone_frame_data_derives_from_the_description(tmp_path):
    """A lone run's frame_data() is the description applied to its own state (the teapot's
    surface rows of the positions; the bounce's arrays passed through as the simulator holds them)."""
    teapot = get_scene("teapot")(get_scene("teapot").resolve_params({"resolution": 6}), device="cpu")
    data = teapot.frame_data()
    x = teapot.sim.state.positions.numpy()
    n = teapot.body.surface_count
    assert np.array_equal(data["teapot"]["points"], x[:n]) and np.array_equal(data["springs"]["points"], x)
    bounce = get_scene("bounce")(get_scene("bounce").resolve_params({}), device="cpu")
    BatchLayerWriter(tmp_path / "b.usdc", bounce, 0, 1, 25.0)  # declares its prims, writes nothing
    assert bounce.frame_data()["ball"]["points"] is bounce.sim.state.positions


def test_a_subclass_overriding_frame_data_alone_is_asked_per_world():
    """A scene subclass that overrides frame_data() without describing it keeps the per-world path."""
    cls = get_scene("bounce")

    class Odd(cls):
        def frame_data(self):
            data = super().frame_data()
            return {k: {"points": np.asarray(v["points"].numpy()) * 2.0, "velocities": v["velocities"]}
                    for k, v in data.items()}

    scene = Odd(cls.resolve_params({}), device="cpu")
    assert described(scene) is None
    assert described(cls(cls.resolve_params({}), device="cpu")) is not None
