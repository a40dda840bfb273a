"""``warpsim export``: one frame of a cache as .obj/.ply/.stl/.glb, read back with trimesh and
compared with the positions written for that frame; particles meshed with ``--surface`` enclose
the volume of the ball they fill; a Z-up file is the Y-up file turned +90 degrees about x (the
default for .ply and .stl); ``--prims`` chooses prims and .stl leaves curves out with a note; an
.obj point cloud is what Blender's OBJ importer reads as points (``v`` lines alone); every mistake
is one line with exit status 2 and no file."""

import io

import numpy as np
import pytest

from warpsim import cli
from warpsim.usd.writer import UsdCacheWriter

trimesh = pytest.importorskip("trimesh")

TET_POINTS = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
TET_FACES = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])  # outward


def ball_points(radius=0.1, spacing=0.01):
    g = np.arange(-radius, radius + 1e-9, spacing)
    p = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    return p[np.linalg.norm(p, axis=1) <= radius]


def shift(frame):
    return np.array([0.1 * frame, 0.5, 0.0])


def write_cache(path, frames=3, with_guide_only=False):
    """A tetrahedron (mesh) moving +0.1 m in x per frame, a ball of particles, a two-curve polyline
    set and a static box (1 x 2 x 3 m)."""
    ball = ball_points()
    with UsdCacheWriter(str(path), fps=30) as w:
        if with_guide_only:
            w.add_box("walls", (0, 0, 0), (1, 1, 1), purpose="guide")
            for f in range(frames):
                w.write_frame(f, {})
            return ball
        w.add_mesh("tet", [3] * 4, TET_FACES.reshape(-1), velocities=False)
        w.add_points("ball", radius=0.005, velocities=False)
        w.add_curves("hair", curve_vertex_counts=[3, 2])
        w.add_box("box", (2.0, 0.0, 0.0), (3.0, 2.0, 3.0))
        for f in range(frames):
            w.write_frame(f, {"tet": {"points": TET_POINTS + shift(f)},
                              "ball": {"points": ball + shift(f)},
                              "hair": {"points": np.array([[0, 0, 0], [0, 1, 0], [0, 2, 0], [1, 0, 0], [1, 1, 0]])
                                       + shift(f)}})
    return ball


def run_cli(argv):
    out, err = io.StringIO(), io.StringIO()
    return cli.main(["export", *map(str, argv)], out, err), out.getvalue(), err.getvalue()


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    path = tmp_path_factory.mktemp("export") / "c.usda"
    write_cache(path)
    return path


def test_obj_per_prim_holds_the_frames_geometry(cache, tmp_path):
    code, out, err = run_cli([cache, "--frame", 1, "--out", tmp_path / "f.obj"])
    assert code == 0, err
    tet = trimesh.load(tmp_path / "f_tet.obj", process=False)
    np.testing.assert_allclose(tet.vertices, TET_POINTS + shift(1), atol=1e-6)
    np.testing.assert_array_equal(tet.faces, TET_FACES)
    assert tet.is_watertight and tet.volume == pytest.approx(1.0 / 6.0, rel=1e-6)  # outward winding kept
    box = trimesh.load(tmp_path / "f_box.obj", process=False)
    assert box.volume == pytest.approx(1.0 * 2.0 * 3.0, rel=1e-6)
    text = (tmp_path / "f_hair.obj").read_text()
    assert sum(line.startswith("l ") for line in text.splitlines()) == 3  # 2 + 1 segments
    points = [line for line in (tmp_path / "f_ball.obj").read_text().splitlines() if not line.startswith("#")]
    # Blender's OBJ importer reads a file without faces or lines as a point cloud, and warns once per
    # line at 'p' elements (obj_import_file_reader.cc: use_all_vertices_if_no_faces)
    assert sum(line.startswith("v ") for line in points) == len(ball_points())
    assert [line for line in points if not line.startswith("v ")] == ["o ball"]
    cloud = trimesh.load(tmp_path / "f_ball.obj")
    np.testing.assert_allclose(np.sort(cloud.vertices, 0), np.sort(ball_points() + shift(1), 0), atol=1e-6)
    assert "wrote frame 1 to 4 files" in out


Y_TO_Z = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # row vectors: (x, y, z) -> (x, -z, y)


def test_ply_points_and_stl_mesh_and_last_frame_default(cache, tmp_path):
    assert run_cli([cache, "--out", tmp_path / "p.ply", "--up", "y"])[0] == 0  # default: the last frame (2)
    cloud = trimesh.load(tmp_path / "p_ball.ply")
    np.testing.assert_allclose(np.sort(cloud.vertices, axis=0), np.sort(ball_points() + shift(2), axis=0), atol=1e-6)
    code, _, err = run_cli([cache, "--frame", 0, "--out", tmp_path / "s.stl", "--surface", "--device", "cpu"])
    assert code == 0 and err.strip() == ("note: left out curves hair (.stl holds triangles only; write .obj, .ply "
                                         "or .glb for them)"), err
    assert sorted(p.name for p in tmp_path.glob("s*.stl")) == ["s_ball.stl", "s_box.stl", "s_tet.stl"]
    guides = tmp_path / "g.usda"
    write_cache(guides, with_guide_only=True)
    assert run_cli([guides, "--out", tmp_path / "walls.stl", "--guides"])[0] == 0
    walls = trimesh.load(tmp_path / "walls.stl")
    assert walls.volume == pytest.approx(1.0, rel=1e-6)  # the unit box, outward


def test_glb_merge_holds_every_prim(cache, tmp_path):
    code, out, err = run_cli([cache, "--frame", 2, "--out", tmp_path / "all.glb", "--merge"])
    assert code == 0, err
    scene = trimesh.load(tmp_path / "all.glb")
    assert set(scene.geometry) >= {"tet", "ball", "box"}
    tet = scene.geometry["tet"]
    np.testing.assert_allclose(np.sort(tet.vertices, 0), np.sort(TET_POINTS + shift(2), 0), atol=1e-6)


def test_surface_encloses_the_particle_ball(cache, tmp_path):
    code, _, err = run_cli([cache, "--frame", 1, "--out", tmp_path / "m.obj", "--surface", "--device", "cpu"])
    assert code == 0, err
    text = (tmp_path / "m_ball.obj").read_text()
    assert "\np " not in text  # no point cloud left
    ball = trimesh.load(tmp_path / "m_ball.obj", process=False)
    assert ball.is_watertight
    volume = 4.0 / 3.0 * np.pi * 0.1 ** 3  # particles fill a ball of radius 0.1 m on a 1 cm lattice
    assert abs(ball.volume) == pytest.approx(volume, rel=0.05)  # measured: equivalent radius 0.1002 m
    np.testing.assert_allclose(ball.vertices.mean(0), shift(1), atol=0.01)


def test_z_up_is_the_y_up_file_turned_and_the_default_for_ply_and_stl(cache, tmp_path):
    """Blender reads .ply and .stl as they are (Z-up): a Z-up file is the cache's Y-up geometry turned
    +90 degrees about x, winding kept (the volume stays positive); .obj and .glb stay Y-up."""
    files = {}
    for name, extra in [("y.ply", ["--up", "y"]), ("z.ply", ["--up", "z"]), ("d.ply", []), ("z.stl", []),
                        ("d.obj", []), ("y.obj", ["--up", "y"])]:
        code, _, err = run_cli([cache, "--frame", 1, "--out", tmp_path / name, "--prims", "tet", *extra])
        assert code == 0, err
        files[name] = (tmp_path / name).read_bytes()
    y, z = (trimesh.load(tmp_path / n, process=False) for n in ("y.ply", "z.ply"))
    np.testing.assert_allclose(y.vertices, TET_POINTS + shift(1), atol=1e-6)
    np.testing.assert_allclose(z.vertices, (TET_POINTS + shift(1)) @ Y_TO_Z, atol=1e-6)
    assert z.vertices[:, 2].min() == pytest.approx(0.5)  # the cache's height is the file's z
    assert files["d.ply"] == files["z.ply"] and files["d.obj"] == files["y.obj"]
    stl = trimesh.load(tmp_path / "z.stl")
    assert stl.volume == pytest.approx(1.0 / 6.0, rel=1e-6)  # outward winding kept by the rotation


def test_prims_choose_what_goes_into_one_stl(cache, tmp_path):
    """The teapot case: a mesh with spring curves into one .stl (--merge): curves left out with a
    one-line note, the chosen meshes merged; an unknown name is one line listing the prims."""
    code, out, err = run_cli([cache, "--out", tmp_path / "m.stl", "--merge", "--prims", "tet,box,hair"])
    assert code == 0 and err.count("\n") == 1 and "left out curves hair" in err, err
    merged = trimesh.load(tmp_path / "m.stl")
    assert merged.volume == pytest.approx(1.0 / 6.0 + 6.0, rel=1e-6) and "wrote frame 2 to" in out
    code, _, err = run_cli([cache, "--out", tmp_path / "n.stl", "--prims", "tet,nosuch"])
    assert code == 2 and "--prims nosuch: frame 2 has no drawn prim of that name; its prims: tet, ball, hair, box" in err
    code, _, err = run_cli([cache, "--out", tmp_path / "h.stl", "--prims", "hair"])
    assert code == 2 and "prim 'hair' is curves and .stl holds triangles only" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.stl"]


@pytest.mark.parametrize("argv, says", [
    (["--frame", 7, "--out", "x.obj"], "--frame 7: cache"),
    (["--frame", -1, "--out", "x.obj"], "has frames 0..2"),
    (["--out", "x.fbx"], "unknown suffix '.fbx'"),
    (["--out", "x.stl"], "holds triangles only; pass --surface"),
    (["--out", "x.ply", "--merge"], "one kind; choose prims of one kind with --prims"),
    (["--out", "x.obj", "--merge"], "--merge into .obj: points 'ball' with curves and mesh"),
    (["--out", "x.obj", "--up", "x"], "argument --up: invalid choice: 'x'"),
    (["--out", "x.obj", "--prims", "tet,"], "--prims 'tet,': an empty name"),
])
def test_mistakes_are_one_line_and_write_nothing(cache, tmp_path, argv, says):
    argv = [str(tmp_path / a) if str(a).startswith("x.") else a for a in argv]
    code, out, err = run_cli([cache, *argv])
    assert code == 2 and says in err and len(err.strip().splitlines()) == 1, err
    assert not list(tmp_path.iterdir())


def test_empty_cache_is_one_line(tmp_path):
    path = tmp_path / "g.usda"
    write_cache(path, with_guide_only=True)
    code, _, err = run_cli([path, "--out", tmp_path / "g.obj"])
    assert code == 2 and "holds nothing to export at frame 2" in err and "--guides" in err
    assert run_cli([path, "--out", tmp_path / "g.obj", "--guides"])[0] == 0  # the guide box, when asked
    code, _, err = run_cli([tmp_path / "none.usda", "--out", tmp_path / "n.obj"])
    assert code == 2 and "does not exist" in err


def glb_json(path):
    """The JSON chunk of a .glb file (its materials and meshes as written)."""
    import json
    import struct

    data = open(path, "rb").read()
    length = struct.unpack("<I", data[12:16])[0]
    return json.loads(data[20:20 + length])


def test_see_through_walls_keep_their_opacity_in_glb_and_ply(tmp_path):
    """A container's ``displayOpacity`` (the teapot's walls) becomes a .glb material of that alpha
    in BLEND mode, its colour the material's (what Blender's glTF importer shows see-through, in
    its Solid view too), and the .ply vertices' alpha; opaque prims stay opaque."""
    from pxr import Usd, UsdGeom

    cache = tmp_path / "teapot.usda"
    assert cli.main(["run", "teapot", "--frames", "1", "--no-progress", "--device", "cpu", "--out", str(cache)],
                    io.StringIO(), io.StringIO()) == 0
    stage = Usd.Stage.Open(str(cache))
    walls = UsdGeom.PrimvarsAPI(stage.GetPrimAtPath("/World/walls"))
    opacity = float(walls.GetPrimvar("displayOpacity").Get()[0])
    color = np.asarray(walls.GetPrimvar("displayColor").Get()[0], np.float64)
    assert opacity < 1.0
    code, out, err = run_cli([cache, "--out", tmp_path / "all.glb", "--merge"])
    assert code == 0, err
    gltf = glb_json(tmp_path / "all.glb")
    materials = {m["name"]: gltf["materials"][m["primitives"][0]["material"]] for m in gltf["meshes"]
                 if "material" in m["primitives"][0]}
    walls_material = materials["walls"]
    assert walls_material["alphaMode"] == "BLEND" and walls_material["doubleSided"]
    assert np.allclose(walls_material["pbrMetallicRoughness"]["baseColorFactor"], [*color, opacity], atol=1 / 255)
    assert "COLOR_0" not in next(m for m in gltf["meshes"] if m["name"] == "walls")["primitives"][0]["attributes"]
    assert all(m.get("alphaMode", "OPAQUE") == "OPAQUE" for name, m in materials.items() if name != "walls")
    assert trimesh.load(tmp_path / "all.glb").geometry["walls"].visual.material.alphaMode == "BLEND"
    code, out, err = run_cli([cache, "--out", tmp_path / "w.ply", "--prims", "walls,floor"])
    assert code == 0, err
    alpha = {name: trimesh.load(tmp_path / f"w_{name}.ply").visual.vertex_colors[:, 3] for name in ("walls", "floor")}
    assert np.all(alpha["walls"] == round(opacity * 255)) and np.all(alpha["floor"] == 255)


def file_vertices(path):
    """Vertex count a .ply (its header) or .obj (its v lines) holds."""
    text = open(path, "rb").read()
    if str(path).endswith(".ply"):
        return int(text.split(b"element vertex ")[1].split()[0])
    return sum(line.startswith(b"v ") for line in text.splitlines())


def test_the_vertex_count_printed_is_the_files(tmp_path):
    """A sweep's springs (stored as the particles' points and the segments between them) export
    as line sets; the vertex count ``export`` prints is the one each file holds (.ply: both ends of
    every segment; .obj: the points), so it agrees with what another tool reports."""
    root = tmp_path / "s.usda"
    code = cli.main(["sweep", "springs", "--worlds", "2", "--vary", "stiffness=30:60", "--frames", "2",
                     "--no-progress", "--no-thumbnails", "--device", "cpu", "--out", str(root)], io.StringIO(),
                    io.StringIO())
    assert code == 0
    for suffix in (".ply", ".obj"):
        out_file = tmp_path / f"springs{suffix}"
        code, out, err = run_cli([root, "--out", out_file, "--prims", "springs"])
        assert code == 0, err
        printed = int(out.split("springs: curves, ")[1].split()[0])
        assert printed == file_vertices(out_file), out
