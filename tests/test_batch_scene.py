"""A sweep's worlds drawn from their shared declarations (issue 50, thumbnails): the geometry and
ground height of every world are those of reading its prims alone, bit for bit, also for worlds
whose prims a layer overrides (read alone: no shared declaration used)."""

import io
import shutil

import numpy as np
import pytest

pytest.importorskip("pxr")

from warpsim.render.batch_scene import BatchScene
from warpsim.render.cache import ground_height
from warpsim.render.usd_scene import CacheScene

FIELDS = ("points", "triangles", "face_colors", "corner_normals", "glass_points", "glass_triangles", "glass_colors",
          "glass_alpha", "cap_a", "cap_b", "cap_r", "cap_colors")


@pytest.fixture(scope="module")
def sweep_layer(tmp_path_factory):
    from warpsim.cli import main

    out = tmp_path_factory.mktemp("sweep") / "s.usda"
    code = main(["sweep", "springs", "--worlds", "4", "--frames", "3", "--vary", "stiffness=200:600", "--out", str(out),
                 "--no-progress", "--no-thumbnails", "--device", "cpu", "--set", "shape=lattice", "--set", "count=4"],
                io.StringIO(), io.StringIO())
    assert code == 0
    return out.parent / "s.batch_0000.usdc"


def alone(layer, world, frame):
    """Today's reading of one world: CacheScene.geometry of its prims and ground_height."""
    scene = CacheScene(str(layer))
    scene.prims = [p for p in scene.prims if str(p.GetPath()).startswith(f"/Worlds/{world}/")]
    return scene.geometry(frame), ground_height(scene, [frame])


def assert_same(a, b):
    for name in FIELDS:
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes(), name
    assert (a.volume is None) == (b.volume is None)


def test_every_world_is_the_geometry_of_reading_it_alone(sweep_layer):
    batch = BatchScene(str(sweep_layer))
    assert sorted(batch.worlds) == [f"world_{g:06d}" for g in range(4)]
    assert all(set(batch._shared.of(world).values()) == {"points"} for world in batch.worlds)  # masses, springs
    for frame in (batch.frames[-1], batch.frames[1]):
        for world in batch.worlds:
            geom, ground = alone(sweep_layer, world, frame)
            assert_same(batch.geometry(world, frame), geom)
            assert batch.ground(world, frame) == ground
    assert len(batch.geometry("world_000000", batch.frames[-1]).cap_r) > 16  # spheres and springs drawn


def test_a_world_overriding_its_declaration_is_read_alone(sweep_layer, tmp_path):
    from pxr import Gf, Sdf, Vt

    for part in sweep_layer.parent.glob("s.batch_0000*"):  # the layer, its manifest and chunks
        shutil.copy(part, tmp_path / part.name)
    layer = Sdf.Layer.FindOrOpen(str(tmp_path / "s.batch_0000.usdc"))
    masses = layer.GetPrimAtPath("/Worlds/world_000001/masses")  # a colour of its own
    attr = Sdf.AttributeSpec(masses, "primvars:displayColor", Sdf.ValueTypeNames.Color3fArray)
    attr.default = Vt.Vec3fArray([Gf.Vec3f(1.0, 0.0, 0.0)])
    world = layer.GetPrimAtPath("/Worlds/world_000002")  # moved as a whole
    op = Sdf.AttributeSpec(world, "xformOp:translate", Sdf.ValueTypeNames.Double3)
    op.default = Gf.Vec3d(0.5, 0.25, 0.0)
    order = Sdf.AttributeSpec(world, "xformOpOrder", Sdf.ValueTypeNames.TokenArray, variability=Sdf.VariabilityUniform)
    order.default = Vt.TokenArray(["xformOp:translate"])
    layer.Save()
    path = tmp_path / "s.batch_0000.usdc"
    batch = BatchScene(str(path))
    assert set(batch._shared.of("world_000001")) == {"springs"} and batch._shared.of("world_000002") == {}
    frame = batch.frames[-1]
    for name in ("world_000000", "world_000001", "world_000002", "world_000003"):
        geom, ground = alone(path, name, frame)
        assert_same(batch.geometry(name, frame), geom)
        assert batch.ground(name, frame) == ground
    red = batch.geometry("world_000001", frame).cap_colors
    assert np.any(np.all(red == np.float32([1.0, 0.0, 0.0]), axis=1))
