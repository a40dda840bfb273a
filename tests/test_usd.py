"""USD cache writer: exact round trips through value clips, schemas and conventions, validation,
crash safety under SIGKILL, resume and flatten."""
import os
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

pxr = pytest.importorskip("pxr")
from pxr import Sdf, Usd, UsdGeom

from warpsim.usd.chunk_index import file_digest, read_index
from warpsim.usd.writer import UsdCacheWriter
from warpsim.usd.validate import cache_info, validate_cache


def frame_points(f, n=7):
    """Deterministic, frame-dependent (n, 3) float32 positions (not round numbers)."""
    rng = np.random.default_rng(1000 + f)
    return (rng.standard_normal((n, 3)) * 0.37 + f * 0.013).astype(np.float32)


def get(stage, path, attr, t):
    value = stage.GetPrimAtPath(path).GetAttribute(attr).Get(t)
    return None if value is None else np.asarray(value)


def write_particles(path, frames, chunk_size, radius=0.05, **kw):
    with UsdCacheWriter(path, fps=24, chunk_size=chunk_size, **kw) as w:
        w.add_points("particles", radius=radius, color=(0.2, 0.4, 1.0))
        w.add_attribute("particles", "warpsim:energy", "double")
        for f in frames:
            p = frame_points(f)
            w.write_frame(f, {"particles": {"points": p, "velocities": -2.0 * p, "warpsim:energy": 0.1 * f + 1 / 3}})
    return w


def test_round_trip_through_chunks_is_exact(tmp_path):
    root = tmp_path / "run.usda"
    w = write_particles(root, range(11), chunk_size=4, radius=0.05)
    assert w.close() == str(root)
    files = sorted(os.listdir(tmp_path))
    assert files == ["run.chunk000000.usdc", "run.chunk000004.usdc", "run.chunk000008.usdc",
                     "run.chunks.jsonl", "run.manifest.usda", "run.usda"]
    stage = Usd.Stage.Open(str(root))
    assert stage.GetStartTimeCode() == 0 and stage.GetEndTimeCode() == 10
    assert stage.GetTimeCodesPerSecond() == 24 and stage.GetFramesPerSecond() == 24
    assert UsdGeom.GetStageUpAxis(stage) == "Y" and UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert stage.GetDefaultPrim().GetPath() == Sdf.Path("/World")
    pts = UsdGeom.Points(stage.GetPrimAtPath("/World/particles"))
    assert list(pts.GetWidthsAttr().Get()) == [pytest.approx(0.1)]  # diameters
    assert pts.GetWidthsInterpolation() == "constant"
    assert pts.GetPointsAttr().GetTimeSamples() == list(map(float, range(11)))
    for f in range(11):
        p = frame_points(f)
        assert np.array_equal(get(stage, "/World/particles", "points", f), p)
        assert np.array_equal(get(stage, "/World/particles", "velocities", f), -2.0 * p)
        assert get(stage, "/World/particles", "warpsim:energy", f) == 0.1 * f + 1 / 3
        ext = get(stage, "/World/particles", "extent", f)
        np.testing.assert_allclose(ext, [p.min(0) - 0.05, p.max(0) + 0.05], rtol=0, atol=1e-6)
    assert validate_cache(stage) == []
    info = cache_info(str(root))
    assert (info["start"], info["end"], info["frames"]) == (0, 10, 11)
    (entry,) = [e for e in info["prims"] if e["path"] == "/World/particles"]
    assert entry["count"] == (7, 7)
    allp = np.concatenate([frame_points(f) for f in range(11)])
    np.testing.assert_allclose(entry["bounds"], [allp.min(0) - 0.05, allp.max(0) + 0.05], atol=1e-6)


def test_memory_layout_chunk_holds_only_its_frames(tmp_path):
    write_particles(tmp_path / "a.usdc", range(10), chunk_size=4)
    layer = Sdf.Layer.OpenAsAnonymous(str(tmp_path / "a.chunk000004.usdc"))
    assert layer.ListTimeSamplesForPath("/World/particles.points") == [4.0, 5.0, 6.0, 7.0]
    root = Sdf.Layer.OpenAsAnonymous(str(tmp_path / "a.usdc"))
    assert root.ListAllTimeSamples() == []  # the root holds declarations only
    assert root.GetFileFormat().formatId == "usdc"


def test_changing_counts_with_ids(tmp_path):
    root = tmp_path / "emit.usda"
    counts = [0, 3, 5, 5, 2, 6, 1]
    with UsdCacheWriter(root, fps=30, chunk_size=3) as w:
        w.add_points("spray", count_changes=True, dynamic_widths=True)
        for f, n in enumerate(counts):
            p = frame_points(f, n)
            w.write_frame(f, {"spray": {"points": p, "velocities": p * 3, "ids": np.arange(n) + 10 * f,
                                        "widths": np.linspace(0.01, 0.02, n)}})
    stage = Usd.Stage.Open(str(root))
    for f, n in enumerate(counts):
        p = frame_points(f, n)
        assert np.array_equal(get(stage, "/World/spray", "points", f).reshape(-1, 3), p)
        assert np.array_equal(get(stage, "/World/spray", "ids", f), np.arange(n) + 10 * f)
        assert len(get(stage, "/World/spray", "velocities", f)) == n
        if n:
            r = np.linspace(0.01, 0.02, n, dtype=np.float32) / 2
            np.testing.assert_allclose(get(stage, "/World/spray", "extent", f),
                                       [(p - r[:, None]).min(0), (p + r[:, None]).max(0)], atol=1e-7)
    assert validate_cache(stage) == []


def tri_grid(nx):
    """Triangulated (nx x nx)-vertex grid: counts, indices."""
    quads = [(j * nx + i, j * nx + i + 1, (j + 1) * nx + i + 1, (j + 1) * nx + i)
             for j in range(nx - 1) for i in range(nx - 1)]
    idx = [v for a, b, c, d in quads for v in (a, b, c, a, c, d)]
    return np.full(len(idx) // 3, 3), np.array(idx)


def test_fixed_topology_mesh_written_once(tmp_path):
    counts, idx = tri_grid(4)
    root = tmp_path / "cloth.usd"
    with UsdCacheWriter(root, chunk_size=2) as w:
        w.add_mesh("cloth", counts, idx, double_sided=True)
        for f in range(5):
            p = frame_points(f, 16)
            w.write_frame(f, {"cloth": {"points": p, "velocities": p}})
    stage = Usd.Stage.Open(str(root))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/cloth"))
    assert mesh.GetSubdivisionSchemeAttr().Get() == "none"
    assert mesh.GetFaceVertexIndicesAttr().GetTimeSamples() == []  # topology written once
    assert np.array_equal(np.asarray(mesh.GetFaceVertexIndicesAttr().Get()), idx)
    for f in range(5):
        assert np.array_equal(np.asarray(mesh.GetPointsAttr().Get(f)), frame_points(f, 16))
    assert validate_cache(stage) == []


def test_changing_topology_sampled_only_on_change(tmp_path):
    topologies = {2: tri_grid(2), 3: tri_grid(3)}
    sizes = [2, 2, 3, 3, 3, 3, 2, 3, 3]  # grid size per frame
    root = tmp_path / "surface.usda"
    with UsdCacheWriter(root, chunk_size=4) as w:
        w.add_mesh("surface", topology_changes=True, velocities=False)
        for f, s in enumerate(sizes):
            c, i = topologies[s]
            w.write_frame(f, {"surface": {"points": frame_points(f, s * s), "faceVertexCounts": c,
                                          "faceVertexIndices": i}})
    stage = Usd.Stage.Open(str(root))
    for f, s in enumerate(sizes):
        c, i = topologies[s]
        assert np.array_equal(get(stage, "/World/surface", "faceVertexIndices", f), i)
        assert np.array_equal(get(stage, "/World/surface", "faceVertexCounts", f), c)
        assert np.array_equal(get(stage, "/World/surface", "points", f), frame_points(f, s * s))
    # samples only where the topology changes (2, 6, 7) or a chunk starts (0, 4, 8)
    chunk_samples = []
    for start in (0, 4, 8):
        layer = Sdf.Layer.OpenAsAnonymous(str(tmp_path / f"surface.chunk{start:06d}.usdc"))
        chunk_samples += layer.ListTimeSamplesForPath("/World/surface.faceVertexIndices")
    assert chunk_samples == [0.0, 2.0, 4.0, 6.0, 7.0, 8.0]
    assert validate_cache(stage) == []


def test_instancer_agents_with_state_primvar(tmp_path):
    root = tmp_path / "flock.usda"
    n = 6
    rng = np.random.default_rng(3)
    frames = []
    with UsdCacheWriter(root, chunk_size=2) as w:
        w.add_instancer("boids", [("cone", {"radius": 0.05, "height": 0.2, "axis": "Z"}), ("sphere", {"radius": 0.1})],
                        count_changes=False, primvars={"state": "int[]"})
        for f in range(5):
            q = rng.standard_normal((n, 4))
            q /= np.linalg.norm(q, axis=1, keepdims=True)
            d = {"positions": frame_points(f, n), "orientations": q, "protoIndices": np.arange(n) % 2,
                 "velocities": frame_points(f + 9, n), "state": (np.arange(n) + f) % 3}
            frames.append(d)
            w.write_frame(f, {"boids": d})
    stage = Usd.Stage.Open(str(root))
    inst = UsdGeom.PointInstancer(stage.GetPrimAtPath("/World/boids"))
    assert [str(t) for t in inst.GetPrototypesRel().GetTargets()] == ["/World/boids/Prototypes/proto0",
                                                                      "/World/boids/Prototypes/proto1"]
    for f, d in enumerate(frames):
        assert np.array_equal(np.asarray(inst.GetPositionsAttr().Get(f)), d["positions"])
        got_q = np.array([[*q.GetImaginary(), q.GetReal()] for q in inst.GetOrientationsAttr().Get(f)])
        assert np.array_equal(got_q, d["orientations"].astype(np.float16).astype(np.float64))
        assert np.array_equal(np.asarray(inst.GetProtoIndicesAttr().Get(f)), d["protoIndices"])
        assert np.array_equal(np.asarray(inst.GetIdsAttr().Get(f)), np.arange(n))
        assert np.array_equal(get(stage, "/World/boids", "primvars:state", f), d["state"])
        # extent holds every instance: positions padded by the farthest prototype extent corner
        ext = np.asarray(inst.GetExtentAttr().Get(f))
        pad = max(0.1 * 3 ** 0.5, (2 * 0.05 ** 2 + 0.1 ** 2) ** 0.5)
        np.testing.assert_allclose(ext, [d["positions"].min(0) - pad, d["positions"].max(0) + pad], atol=1e-6)
    # the composed extent really bounds the instances (USD computes it from the prototypes)
    for f in range(5):
        bounds = inst.ComputeExtentAtTime(f, f)
        ext = np.asarray(inst.GetExtentAttr().Get(f))
        assert (np.asarray(bounds[0]) >= ext[0] - 1e-6).all() and (np.asarray(bounds[1]) <= ext[1] + 1e-6).all()
    assert validate_cache(stage) == []


def face_normals(mesh):
    pts = np.asarray(mesh.GetPointsAttr().Get(), np.float64)
    counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get())
    idx = np.asarray(mesh.GetFaceVertexIndicesAttr().Get())
    out, k = [], 0
    for c in counts:
        f = pts[idx[k:k + c]]
        out.append(np.cross(f[1] - f[0], f[2] - f[1]))
        k += c
    return pts, np.array(out), counts, idx


def test_static_colliders_face_outward(tmp_path):
    root = tmp_path / "scene.usda"
    with UsdCacheWriter(root) as w:
        w.add_plane("floor", normal=(0, 1, 0), offset=0.0)
        w.add_plane("ramp", normal=(1, 1, 0), offset=0.5)
        w.add_box("walls", (-1, 0, -2), (1, 3, 2))
        w.add_sphere("ball", (0.5, 1.0, 0.0), 0.25)
    stage = Usd.Stage.Open(str(root))
    _, nf, _, _ = face_normals(UsdGeom.Mesh(stage.GetPrimAtPath("/World/floor")))
    assert nf[0] / np.linalg.norm(nf[0]) == pytest.approx([0, 1, 0])
    pts, nr, _, _ = face_normals(UsdGeom.Mesh(stage.GetPrimAtPath("/World/ramp")))
    np.testing.assert_allclose(nr[0] / np.linalg.norm(nr[0]), [2 ** -0.5, 2 ** -0.5, 0], atol=1e-7)
    np.testing.assert_allclose(pts @ np.array([1, 1, 0]) / 2 ** 0.5, 0.5, atol=1e-6)  # on the plane
    pts, nb, _, idx = face_normals(UsdGeom.Mesh(stage.GetPrimAtPath("/World/walls")))
    centre = pts.mean(0)
    for face, n in enumerate(nb):
        face_centre = pts[idx[4 * face:4 * face + 4]].mean(0)
        assert np.dot(n, face_centre - centre) > 0  # outward
    ball = stage.GetPrimAtPath("/World/ball")
    assert UsdGeom.Sphere(ball).GetRadiusAttr().Get() == 0.25
    box = UsdGeom.Boundable(ball).ComputeWorldBound(0, "default").ComputeAlignedRange()
    np.testing.assert_allclose([box.GetMin(), box.GetMax()], [[0.25, 0.75, -0.25], [0.75, 1.25, 0.25]])
    assert validate_cache(stage) == []


def test_curves_gather_spring_end_points(tmp_path):
    root = tmp_path / "springs.usda"
    springs = np.array([0, 1, 1, 2, 2, 3, 0, 3])
    with UsdCacheWriter(root, chunk_size=2) as w:
        w.add_points("masses", radius=0.02)
        w.add_curves("springs", springs, width=0.01)
        for f in range(3):
            p = frame_points(f, 4)
            w.write_frame(f, {"masses": {"points": p, "velocities": p}, "springs": {"points": p}})
    stage = Usd.Stage.Open(str(root))
    curves = UsdGeom.BasisCurves(stage.GetPrimAtPath("/World/springs"))
    assert curves.GetTypeAttr().Get() == "linear"
    assert list(curves.GetCurveVertexCountsAttr().Get()) == [2, 2, 2, 2]
    for f in range(3):
        assert np.array_equal(np.asarray(curves.GetPointsAttr().Get(f)), frame_points(f, 4)[springs])
    assert validate_cache(stage) == []


def test_validation_reports_broken_caches(tmp_path):
    stage = Usd.Stage.CreateNew(str(tmp_path / "bad.usda"))
    mesh = UsdGeom.Mesh.Define(stage, "/bad")
    mesh.CreatePointsAttr([(0, 0, 0), (1, 0, 0), (0, 1, 0)])
    mesh.CreateFaceVertexCountsAttr([3])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 7])  # index out of range
    mesh.CreateExtentAttr([(0, 0, 0), (1, 1, 0)])
    errors = validate_cache(stage)
    assert any("topology" in e for e in errors)
    assert any("defaultPrim" in e or "DefaultPrim" in e for e in errors)
    assert any("upAxis" in e or "UpAxis" in e for e in errors)


def test_flatten_equals_clipped_cache(tmp_path):
    sizes = [2, 2, 3, 3, 2]
    tops = {2: tri_grid(2), 3: tri_grid(3)}
    kept = tmp_path / "clips" / "c.usda"
    flat = tmp_path / "flat" / "c.usda"
    for path, flatten in ((kept, False), (flat, True)):
        with UsdCacheWriter(path, chunk_size=2, flatten=flatten) as w:
            w.add_points("particles", radius=0.01)
            w.add_mesh("surface", topology_changes=True, velocities=False)
            w.add_plane("floor")
            for f, s in enumerate(sizes):
                c, i = tops[s]
                p = frame_points(f)
                w.write_frame(f, {"particles": {"points": p, "velocities": p},
                                  "surface": {"points": frame_points(f, s * s), "faceVertexCounts": c,
                                              "faceVertexIndices": i}})
    assert w.output_path == str(tmp_path / "flat" / "c.usdc")
    assert os.listdir(tmp_path / "flat") == ["c.usdc"]  # one self-contained file
    a = Usd.Stage.Open(str(kept))
    b = Usd.Stage.Open(w.output_path)
    assert b.GetRootLayer().GetFileFormat().formatId == "usdc"
    assert not b.GetPrimAtPath("/World").HasMetadata("clips")
    assert (b.GetStartTimeCode(), b.GetEndTimeCode()) == (0, 4)
    for prim in a.Traverse():
        for attr in prim.GetAttributes():
            for f in range(len(sizes)):
                va, vb = attr.Get(f), b.GetPrimAtPath(prim.GetPath()).GetAttribute(attr.GetName()).Get(f)
                assert (va is None) == (vb is None)
                if va is not None:
                    assert np.array_equal(np.asarray(va), np.asarray(vb)), (attr.GetPath(), f)
    idx_samples = b.GetPrimAtPath("/World/surface").GetAttribute("faceVertexIndices").GetTimeSamples()
    assert idx_samples == [0.0, 2.0, 4.0]  # only where the topology changes
    assert validate_cache(b) == []


def test_resume_keeps_earlier_frames_and_rewrites_later_ones(tmp_path):
    root = tmp_path / "r.usda"
    write_particles(root, range(10), chunk_size=4)
    # resume at frame 6 (inside chunk 4..7): frames 0..5 kept, 6.. rewritten with new data
    with UsdCacheWriter(root, fps=24, chunk_size=4, resume_frame=6) as w:
        w.add_points("particles", radius=0.05, color=(0.2, 0.4, 1.0))
        w.add_attribute("particles", "warpsim:energy", "double")
        with pytest.raises(ValueError, match="frames must increase"):
            w.write_frame(5, {})
        for f in range(6, 13):
            p = frame_points(f) + 100
            w.write_frame(f, {"particles": {"points": p, "velocities": p, "warpsim:energy": -1.0}})
    stage = Usd.Stage.Open(str(root))
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (0, 12)
    for f in range(13):
        expected = frame_points(f) if f < 6 else frame_points(f) + 100
        assert np.array_equal(get(stage, "/World/particles", "points", f), expected), f
    assert sorted(x for x in os.listdir(tmp_path) if ".chunk0" in x) == [
        "r.chunk000000.usdc", "r.chunk000004.usdc", "r.chunk000006.usdc", "r.chunk000008.usdc",
        "r.chunk000012.usdc"]
    index = read_index(str(tmp_path / "r.chunks.jsonl"))  # the resume rewrote the truncated chunk's record
    assert sorted(index) == sorted(x for x in os.listdir(tmp_path) if ".chunk0" in x)
    assert [(index[f]["start"], index[f]["end"]) for f in sorted(index)] == [(0, 3), (4, 5), (6, 7), (8, 11), (12, 12)]
    for f, rec in index.items():
        assert (rec["bytes"], rec["crc32"]) == file_digest(str(tmp_path / f))
        assert rec["prims"]["particles"]["count"] == [len(frame_points(rec["start"]))] * 2
    truncated = Sdf.Layer.OpenAsAnonymous(str(tmp_path / "r.chunk000004.usdc"))
    assert truncated.ListTimeSamplesForPath("/World/particles.points") == [4.0, 5.0]
    assert validate_cache(stage) == []
    with pytest.raises(ValueError, match="holds frames up to 12"):
        UsdCacheWriter(root, chunk_size=4, resume_frame=20).close()


def test_flush_completes_a_partial_chunk(tmp_path):
    root = tmp_path / "f.usda"
    w = UsdCacheWriter(root, chunk_size=10)
    w.add_points("particles")
    for f in range(3):
        w.write_frame(f, {"particles": {"points": frame_points(f), "velocities": frame_points(f)}})
    assert w.flush() == 2
    stage = Usd.Stage.Open(str(root))
    assert stage.GetEndTimeCode() == 2
    assert np.array_equal(get(stage, "/World/particles", "points", 2), frame_points(2))
    del stage
    for f in range(3, 5):  # the next frames go to a new chunk starting at 3
        w.write_frame(f, {"particles": {"points": frame_points(f), "velocities": frame_points(f)}})
    w.close()
    stage = Usd.Stage.Open(str(root))
    assert np.array_equal(get(stage, "/World/particles", "points", 4), frame_points(4))
    assert np.array_equal(get(stage, "/World/particles", "points", 1), frame_points(1))


def test_write_state_hook_accepts_warp_arrays(tmp_path):
    wp = pytest.importorskip("warp")

    class State:
        def __init__(self, p, v):
            self.positions = wp.array(p, dtype=wp.vec3, device="cpu")
            self.velocities = wp.array(v, dtype=wp.vec3, device="cpu")

    root = tmp_path / "s.usda"
    with UsdCacheWriter(root, chunk_size=2) as w:
        for f in range(3):
            w.write(f, State(frame_points(f), -frame_points(f)))
    stage = Usd.Stage.Open(str(root))
    for f in range(3):
        assert np.array_equal(get(stage, "/World/particles", "points", f), frame_points(f))
        assert np.array_equal(get(stage, "/World/particles", "velocities", f), -frame_points(f))


def test_simulator_run_streams_through_the_writer(tmp_path):
    ws = pytest.importorskip("warpsim")
    b = ws.ModelBuilder()
    b.add_particle((0.0, 0.04, 0.0), mass=1.0)
    sim = ws.Simulator(b.finalize("cpu"), forces=[ws.Gravity()], colliders=[ws.Plane()])
    root = tmp_path / "ball.usda"
    with UsdCacheWriter(root, fps=25, chunk_size=2) as w:
        w.add_points("particles", radius=0.004, from_state=True)
        w.add_plane("floor", size=0.2)
        sim.run(3, 0.04, writer=w)
    stage = Usd.Stage.Open(str(root))
    assert stage.GetEndTimeCode() == 3
    y1 = get(stage, "/World/particles", "points", 1)[0, 1]
    assert y1 == pytest.approx(0.024304, rel=1e-6)  # the seed's first step
    assert np.array_equal(get(stage, "/World/particles", "points", 3), sim.state.positions.numpy())
    assert validate_cache(stage) == []


def test_bad_input_raises_value_error_naming_the_item(tmp_path):
    with pytest.raises(ValueError, match=r"must end in one of"):
        UsdCacheWriter(tmp_path / "x.abc")
    w = UsdCacheWriter(tmp_path / "x.usda")
    w.add_points("particles")
    with pytest.raises(ValueError, match="declared twice"):
        w.add_points("particles")
    with pytest.raises(ValueError, match="not a valid USD identifier"):
        w.add_points("2bad name")
    with pytest.raises(ValueError, match="Did you mean 'particles'"):
        w.write_frame(0, {"particle": {}})
    with pytest.raises(ValueError, match=r"'particles' at frame 0: missing 'velocities'"):
        w.write_frame(0, {"particles": {"points": np.zeros((3, 3))}})
    with pytest.raises(ValueError, match=r"expected shape \(n, 3\)"):
        w.write_frame(0, {"particles": {"points": np.zeros((3, 2)), "velocities": np.zeros((3, 2))}})
    with pytest.raises(ValueError, match="same length"):
        w.write_frame(0, {"particles": {"points": np.zeros((3, 3)), "velocities": np.zeros((2, 3))}})
    with pytest.raises(ValueError, match="NaN or infinite"):
        w.write_frame(0, {"particles": {"points": np.full((3, 3), np.nan), "velocities": np.zeros((3, 3))}})
    with pytest.raises(ValueError, match="unknown key 'velocity'.*Did you mean 'velocities'"):
        w.write_frame(0, {"particles": {"points": np.zeros((3, 3)), "velocity": np.zeros((3, 3))}})
    w.write_frame(0, {"particles": {"points": np.zeros((3, 3)), "velocities": np.zeros((3, 3))}})
    with pytest.raises(ValueError, match="fixed count of 3"):
        w.write_frame(1, {"particles": {"points": np.zeros((4, 3)), "velocities": np.zeros((4, 3))}})
    with pytest.raises(ValueError, match="before the first frame"):
        w.add_points("late")
    w.close()
    with pytest.raises(ValueError, match="face 0 has 2 vertices"):
        UsdCacheWriter(tmp_path / "y.usda").add_mesh("m", [2], [0, 1])


def test_import_warpsim_usd_does_not_import_pxr():
    code = "import sys, warpsim, warpsim.usd.writer, warpsim.usd.validate, warpsim.usd.prims; assert 'pxr' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True)


KILL_SCRIPT = textwrap.dedent("""
    import sys, time
    import numpy as np
    sys.path.insert(0, {tests!r})
    from test_usd import frame_points
    from warpsim.usd.writer import UsdCacheWriter
    w = UsdCacheWriter(sys.argv[1], chunk_size=3, durable=False)
    w.add_points("particles", radius=0.01)
    done = 0
    for f in range(10**6):
        p = frame_points(f % 50, 2000)
        w.write_frame(f, {{"particles": {{"points": p, "velocities": p}}}})
        if len(w.chunks) != done:
            done = len(w.chunks)
            print("chunk", done, "done", flush=True)
        time.sleep(float(sys.argv[2]))
""")


def check_killed_cache(root, min_chunks):
    stage = Usd.Stage.Open(str(root))  # opens: the root layer is never half written
    layer = Sdf.Layer.OpenAsAnonymous(str(root))
    chunks = layer.GetPrimAtPath("/World").GetInfo("clips")["default"]["assetPaths"]
    assert len(chunks) >= min_chunks
    end = int(stage.GetEndTimeCode())
    assert end == 3 * len(chunks) - 1  # every completed chunk is listed, frames 0..end
    for f in range(end + 1):
        p = frame_points(f % 50, 2000)
        assert np.array_equal(get(stage, "/World/particles", "points", f), p), f
    return end


def test_sigkill_mid_run_leaves_every_completed_chunk(tmp_path):
    script = tmp_path / "writer.py"
    script.write_text(KILL_SCRIPT.format(tests=os.path.dirname(__file__)))
    root = tmp_path / "killed.usda"
    proc = subprocess.Popen([sys.executable, str(script), str(root), "0.02"], stdout=subprocess.PIPE, text=True)
    for line in proc.stdout:
        if line.strip() == "chunk 3 done":
            time.sleep(0.03)  # now in the middle of chunk 4
            break
    proc.kill()  # SIGKILL
    proc.wait()
    assert proc.returncode == -9
    assert check_killed_cache(root, 3) >= 8
    # kills at arbitrary moments (during chunk saves, renames and root rewrites)
    for delay in (0.9, 1.4):
        root = tmp_path / f"k{delay}.usda"
        proc = subprocess.Popen([sys.executable, str(script), str(root), "0"], stdout=subprocess.PIPE, text=True)
        assert proc.stdout.readline().strip() == "chunk 1 done"
        time.sleep(delay - 0.8)
        proc.kill()
        proc.wait()
        check_killed_cache(root, 1)
    # a later run to the same path cleans up the temporary files of the killed one
    write_particles(root, range(2), chunk_size=4)
    assert not [f for f in os.listdir(tmp_path) if f.startswith(root.stem + ".") and "tmp-" in f]


def test_next_run_removes_every_kind_of_leftover_temporary(tmp_path):
    """A kill can leave our "<name>.tmp-PID.usdc" files and, when it lands inside usd-core's own
    save, usd-core's "<name>.tmp-PID.XXXXXX" temporaries; the next run to the path removes both
    and nothing else."""
    root = tmp_path / "again.usda"
    planted = ["again.chunk000004.tmp-999.usdc", "again.chunk000477.tmp-24744.gaJPWt", "again.tmp-999.usda"]
    for name in planted:
        (tmp_path / name).write_text("partial")
    (tmp_path / "other.chunk000000.tmp-1.gaJPWt").write_text("not ours")
    write_particles(root, range(3), chunk_size=2)
    left = sorted(os.listdir(tmp_path))
    assert not [f for f in left if f in planted]
    assert "other.chunk000000.tmp-1.gaJPWt" in left
