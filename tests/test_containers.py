"""Containers and floors as DCC tools read them: a scene's box of walls or tank is render-purpose
geometry bound to a ``UsdPreviewSurface`` material whose ``inputs:opacity`` equals its
``displayOpacity`` (what Blender's importer and usdview read; ``guide`` prims they skip), and a
scene whose bodies rest on a container's bottom has an opaque floor prim there. Pure helpers stay
``guide``. Checked through pxr on caches the scenes write."""

import io

import numpy as np
import pytest

from warpsim import cli

pxr = pytest.importorskip("pxr")


def write(scene, tmp_path, *sets):
    cache = tmp_path / f"{scene}.usda"
    argv = ["run", scene, "--frames", "1", "--out", str(cache), "--device", "cpu", "--no-progress"]
    for s in sets:
        argv += ["--set", s]
    code = cli.main(argv, io.StringIO(), err := io.StringIO())
    assert code == 0, err.getvalue()
    from pxr import Usd

    return Usd.Stage.Open(str(cache))


def material_opacity(prim):
    from pxr import UsdShade

    material, _ = UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial()
    assert material, f"{prim.GetPath()} has no bound material"
    shader = material.ComputeSurfaceSource()[0]
    assert shader.GetIdAttr().Get() == "UsdPreviewSurface"
    return float(shader.GetInput("opacity").Get()), np.asarray(shader.GetInput("diffuseColor").Get())


def check_container(stage, name, floor_y):
    from pxr import Usd, UsdGeom

    prim = stage.GetPrimAtPath(f"/World/{name}")
    assert UsdGeom.Imageable(prim).ComputePurpose() == "render"
    display = float(UsdGeom.PrimvarsAPI(prim).GetPrimvar("displayOpacity").Get()[0])
    opacity, color = material_opacity(prim)
    assert opacity == pytest.approx(display) and 0.0 < opacity < 0.5
    assert np.allclose(color, UsdGeom.PrimvarsAPI(prim).GetPrimvar("displayColor").Get()[0])
    floor = stage.GetPrimAtPath("/World/floor")
    assert floor and UsdGeom.Imageable(floor).ComputePurpose() == "default"
    assert not UsdGeom.PrimvarsAPI(floor).GetPrimvar("displayOpacity").HasValue()  # opaque
    box = UsdGeom.BBoxCache(Usd.TimeCode.Default(), ["default", "render"]).ComputeWorldBound(floor).ComputeAlignedRange()
    assert box.GetMin()[1] == pytest.approx(floor_y) and box.GetMax()[1] == pytest.approx(floor_y)
    walls = UsdGeom.BBoxCache(Usd.TimeCode.Default(), ["render"]).ComputeWorldBound(prim).ComputeAlignedRange()
    assert walls.GetMin()[1] == pytest.approx(floor_y)  # the floor lies under the container's bottom
    for axis in (0, 2):  # and spans its footprint
        assert box.GetMin()[axis] < walls.GetMin()[axis] and box.GetMax()[axis] > walls.GetMax()[axis]
    mesh = UsdGeom.Mesh(floor)
    p = np.asarray(mesh.GetPointsAttr().Get())
    n = np.cross(p[1] - p[0], p[2] - p[0])
    assert n[1] > 0.0  # faces up


def test_teapot_walls_and_floor(tmp_path):
    stage = write("teapot", tmp_path, "resolution=3", "springs=false")
    check_container(stage, "walls", 0.0)


def test_liquid_tank_and_floor(tmp_path):
    stage = write("liquid", tmp_path, "resolution=8")
    from warpsim.usd.validate import validate_cache  # the cache stays valid USD with materials nested

    check_container(stage, "tank", float(np.asarray(
        stage.GetPrimAtPath("/World/tank").GetAttribute("points").Get()).min(0)[1]))
    assert not validate_cache(stage)


def test_pure_helpers_stay_guides(tmp_path):
    from pxr import UsdGeom

    stage = write("smoke", tmp_path, "resolution=8")
    assert UsdGeom.Imageable(stage.GetPrimAtPath("/World/smoke_surface")).ComputePurpose() == "guide"
