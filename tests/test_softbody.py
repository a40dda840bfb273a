"""Soft bodies (warpsim.bodies.softbody), the Utah teapot (warpsim.bodies.teapot), dragging (warpsim.bodies.drag,
kernels/interaction.py) and the ``teapot`` scene, on the "cpu" device.

Oracles: watertightness and Euler characteristics of the welded teapot, its body volume
against Gauss-Legendre quadrature of the Bezier patches (second-order convergence), bending
springs = interior edges counted independently, mass totals, the drag spring's force law and
its equilibrium, NumPy ray distances, and blow-up reporting.
"""
import math

import numpy as np
import pytest
import warp as wp

import warpsim as ws
from warpsim.bodies import meshtools
from warpsim.bodies.drag import DragSpring, parse_drag_spec, pick_particle, scripted_drag
from warpsim.bodies.softbody import add_soft_body, load_mesh, load_usd_mesh
from warpsim.bodies.teapot import COMPONENTS, PARTS, bernstein, control_points, teapot_mesh

DEVICE = "cpu"


def icosphere(subdivisions=1, radius=0.1):
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return np.asarray(m.vertices), np.asarray(m.faces)


def grid_sheet(n=4):
    """An open (n+1)^2-vertex square sheet, 2 n^2 triangles."""
    x, z = np.meshgrid(np.linspace(0, 1, n + 1), np.linspace(0, 1, n + 1), indexing="ij")
    pts = np.stack([x.ravel(), np.zeros(x.size), z.ravel()], 1)
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    a = (i * (n + 1) + j).ravel()
    faces = np.concatenate([np.stack([a, a + 1, a + n + 2], 1), np.stack([a, a + n + 2, a + n + 1], 1)])
    return pts, faces


# ---------------------------------------------------------------- the teapot mesh


def exact_body_volume(scale=0.1):
    """(1/3) sum over the body patches of the integral of S . (S_v x S_u) du dv, exact with
    6-point Gauss-Legendre (the integrand has degree 8 in u and v)."""
    x, w = np.polynomial.legendre.leggauss(6)
    x, w = 0.5 * (x + 1), 0.5 * w
    b = bernstein(x)
    s = 1 - x
    db = np.stack([-3 * s * s, 3 * s * s - 6 * x * s, 6 * x * s - 3 * x * x, 3 * x * x], -1)
    ctrl = control_points()
    total = 0.0
    for p in [p for part in COMPONENTS["body"] for p in PARTS[part]]:
        S = np.einsum("ui,vj,ijk->uvk", b, b, ctrl[p])
        Su = np.einsum("ui,vj,ijk->uvk", db, b, ctrl[p])
        Sv = np.einsum("ui,vj,ijk->uvk", b, db, ctrl[p])
        total += np.einsum("u,v,uv->", w, w, np.einsum("uvk,uvk->uv", S, np.cross(Sv, Su))) / 3.0
    return total * scale**3


def test_teapot_data_and_low_res_counts():
    m = teapot_mesh("low")
    assert m.resolution == 4 and m.points.shape == (518, 3) and m.faces.shape == (1024, 3)
    assert teapot_mesh("high").points.shape == (4614, 3)
    lo, hi = m.points.min(0), m.points.max(0)
    np.testing.assert_allclose([lo[1], hi[1]], [0.0, 0.315], atol=1e-12)  # bottom at 0, knob at 3.15 units
    np.testing.assert_allclose([lo[0], lo[2], hi[2]], [-0.3, -0.2, 0.2], atol=1e-12)  # handle, body radius 2


@pytest.mark.parametrize("n", [2, 4, 7])
def test_teapot_is_watertight_per_component(n):
    m = teapot_mesh(n)
    f = m.faces
    assert meshtools.is_closed(f)  # every edge in exactly two faces, traversed oppositely
    assert np.all((f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 2] != f[:, 0]))
    assert meshtools.euler_characteristic(f) == 6
    labels = meshtools.connected_components(f, len(m.points))
    assert labels.max() == 2
    for k, name in enumerate(m.component_names):
        cf = m.component_faces(name)
        assert meshtools.euler_characteristic(cf) == 2  # each a sphere topologically
        assert len(np.unique(labels[cf])) == 1
        assert meshtools.signed_volume(m.points, cf) > 0.0  # outward
    # the lid knob and the bottom centre are welded poles of valence 4 n
    edges, _, _ = meshtools.edge_topology(f)
    valence = np.bincount(edges.ravel(), minlength=len(m.points))
    body = np.unique(m.component_faces("body"))
    for y in (0.0, 0.315):
        pole = body[np.argmin(np.abs(m.points[body, 1] - y) + np.hypot(m.points[body, 0], m.points[body, 2]))]
        assert np.allclose(m.points[pole], [0.0, y, 0.0], atol=1e-12)
        assert valence[pole] == 4 * n


def test_teapot_volume_converges_to_bezier_quadrature():
    exact = exact_body_volume()
    errors = []
    for n in (2, 4, 8):
        m = teapot_mesh(n)
        errors.append(exact - meshtools.signed_volume(m.points, m.component_faces("body")))
    assert exact == pytest.approx(25.3149728e-3, rel=1e-6)
    assert all(e > 0 for e in errors)  # inscribed polyhedra
    assert errors[2] / exact < 0.01
    for coarse, fine in zip(errors, errors[1:]):
        assert coarse / fine == pytest.approx(4.0, rel=0.1)  # second order in 1/n


def test_teapot_bad_resolution():
    for bad in (1, 0, "medium", 2.5):
        with pytest.raises(ValueError, match="resolution"):
            teapot_mesh(bad)


# ---------------------------------------------------------------- springs from meshes


def count_interior_edges(faces):
    count = {}
    for f in faces:
        for a, b in ((f[0], f[1]), (f[1], f[2]), (f[2], f[0])):
            key = (min(a, b), max(a, b))
            count[key] = count.get(key, 0) + 1
    return sum(1 for c in count.values() if c == 2), len(count)


@pytest.mark.parametrize("mesh", ["sheet", "teapot"])
def test_bending_springs_equal_interior_edges(mesh):
    if mesh == "sheet":
        pts, faces = grid_sheet(4)
    else:
        pot = teapot_mesh(2)
        pts, faces = pot.points, pot.faces
    b = ws.ModelBuilder()
    body = add_soft_body(b, pts, faces, interior="none", stiffness=10.0, bend_stiffness=3.0)
    interior, edges = count_interior_edges(faces)
    assert body.bend_count == interior and body.edge_count == edges
    assert b.spring_count == body.spring_count == edges + interior
    # each bending spring joins the vertices opposite a shared edge
    idx = np.array(b.spring_indices)[list(body.spring_range("bend"))]
    for (i, j) in idx:
        shared = [f for f in faces if i in f or j in f]
        tri_i = [set(f) for f in shared if i in f and j not in f]
        tri_j = [set(f) for f in shared if j in f and i not in f]
        assert any(len((ti - {i}) & (tj - {j})) == 2 for ti in tri_i for tj in tri_j)
    assert np.all(np.array(b.spring_stiffness)[list(body.spring_range("bend"))] == 3.0)
    pairs, q = np.array(b.spring_indices), np.array(b.particle_q)
    np.testing.assert_allclose(b.spring_rest_length, np.linalg.norm(q[pairs[:, 0]] - q[pairs[:, 1]], axis=1))


def test_interior_lattice_ties_every_vertex_and_masses_add_up():
    pts, faces = icosphere(2, radius=0.2)
    b = ws.ModelBuilder()
    body = add_soft_body(b, pts, faces, total_mass=3.0, interior_mass_fraction=0.2, lattice_cells=5, ties=3)
    q = np.array(b.particle_q)
    m = np.array(b.particle_mass)
    assert body.interior_count > 8
    assert np.all(np.linalg.norm(q[body.interior_indices], axis=1) < 0.2)  # lattice inside the sphere
    assert m.sum() == pytest.approx(3.0, rel=1e-12)
    assert m[body.interior_indices].sum() == pytest.approx(0.6, rel=1e-12)
    areas = meshtools.vertex_areas(pts, faces)
    np.testing.assert_allclose(m[body.surface_indices], 2.4 * areas / areas.sum(), rtol=1e-12)
    ties = np.array(b.spring_indices)[list(body.spring_range("tie"))]
    assert body.tie_count == 3 * len(pts)
    assert np.all(np.bincount(ties[:, 0], minlength=len(pts)) == 3)
    assert np.all(ties[:, 1] >= body.surface_count)
    uni = ws.ModelBuilder()
    add_soft_body(uni, pts, faces, total_mass=3.0, mass_distribution="uniform", interior="none")
    np.testing.assert_allclose(uni.particle_mass, 3.0 / len(pts))


def test_lattice_keeps_a_closed_shape_from_collapsing():
    """A soft ball resting on the floor: without interior springs it flattens far more."""
    pts, faces = icosphere(1, radius=0.1)
    ratios = {}
    for interior in ("lattice", "none"):
        b = ws.ModelBuilder()
        add_soft_body(b, pts, faces, position=(0, 0.11, 0), total_mass=0.5, stiffness=40.0, damping=0.2,
                      bend_stiffness=0.5, interior=interior, lattice_cells=4, mass_distribution="uniform")
        model = b.finalize(DEVICE)
        sim = ws.Simulator(model, colliders=[ws.Plane(restitution=0.0, friction=0.5)], check_every=50)
        for _ in range(600):
            sim.step(1.0 / 600)
        x = sim.state.positions.numpy()[: len(pts)]
        ratios[interior] = meshtools.signed_volume(x, faces) / meshtools.signed_volume(pts, faces)
    assert ratios["lattice"] > 0.85
    assert ratios["none"] < ratios["lattice"] - 0.2


def test_soft_body_bad_input_names_the_item():
    pts, faces = icosphere(1)
    with pytest.raises(ValueError, match="empty"):
        add_soft_body(ws.ModelBuilder(), np.zeros((0, 3)), np.zeros((0, 3), int))
    fin = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0, -1, 0]], float)
    with pytest.raises(ValueError, match=r"non-manifold: edge \(0, 1\) is shared by 3 faces"):
        add_soft_body(ws.ModelBuilder(), fin, [[0, 1, 2], [0, 1, 3], [1, 0, 4]], interior="none")
    with pytest.raises(ValueError, match="stiffness is -5"):
        add_soft_body(ws.ModelBuilder(), pts, faces, stiffness=-5.0)
    with pytest.raises(ValueError, match="bend_damping"):
        add_soft_body(ws.ModelBuilder(), pts, faces, bend_damping=float("nan"))
    with pytest.raises(ValueError, match="interior 'tetra' is unknown"):
        add_soft_body(ws.ModelBuilder(), pts, faces, interior="tetra")
    sheet_pts, sheet_faces = grid_sheet(3)
    with pytest.raises(ValueError, match="interior='none'"):
        add_soft_body(ws.ModelBuilder(), sheet_pts, sheet_faces)
    with pytest.raises(ValueError, match="face 0 .* repeats a vertex"):
        add_soft_body(ws.ModelBuilder(), pts, [[0, 0, 1]])
    with pytest.raises(ValueError, match="total_mass"):
        add_soft_body(ws.ModelBuilder(), pts, faces, total_mass=0.0)


def test_load_mesh_formats_and_usd(tmp_path):
    import trimesh

    pts, faces = icosphere(1, radius=0.5)
    mesh = trimesh.Trimesh(pts, faces, process=False)
    volume = meshtools.signed_volume(pts, faces)
    for ext in ("obj", "stl", "ply", "glb", "off"):
        path = tmp_path / f"ball.{ext}"
        mesh.export(path)
        p, f = load_mesh(path)
        assert len(p) == len(pts) and len(f) == len(faces), ext  # STL stores no shared vertices: welded
        assert meshtools.is_closed(f), ext
        assert meshtools.signed_volume(p, f) == pytest.approx(volume, rel=1e-5), ext
    from pxr import Gf, Usd, UsdGeom

    stage = Usd.Stage.CreateNew(str(tmp_path / "quad.usda"))
    xf = UsdGeom.Xform.Define(stage, "/World")
    xf.AddTranslateOp().Set(Gf.Vec3d(1.0, 2.0, 3.0))
    usd_mesh = UsdGeom.Mesh.Define(stage, "/World/quad")
    usd_mesh.GetPointsAttr().Set([(0, 0, 0), (1, 0, 0), (1, 0, 1), (0, 0, 1)])
    usd_mesh.GetFaceVertexCountsAttr().Set([4])
    usd_mesh.GetFaceVertexIndicesAttr().Set([0, 3, 2, 1])
    stage.Save()
    p, f = load_usd_mesh(tmp_path / "quad.usda")
    np.testing.assert_allclose(p, [[1, 2, 3], [2, 2, 3], [2, 2, 4], [1, 2, 4]])
    np.testing.assert_array_equal(f, [[0, 3, 2], [0, 2, 1]])
    with pytest.raises(ValueError, match="unknown extension"):
        (tmp_path / "x.xyz").write_text("")
        load_mesh(tmp_path / "x.xyz")


# ---------------------------------------------------------------- dragging


def test_drag_spring_force_law_and_keyframes(device):
    b = ws.ModelBuilder()
    b.add_particle((0.0, 0.0, 0.0), vel=(1.0, 0.0, 0.0), mass=2.0)
    b.add_particle((1.0, 0.0, 0.0), mass=1.0)
    model = b.finalize(device)
    path = [(1.0, (0.0, 1.0, 0.0)), (3.0, (2.0, 1.0, 0.0))]
    drag = DragSpring(50.0, 3.0, particle=0, path=path, release=4.0)
    drag.bind(model)
    q = model.particle_q
    qd = model.particle_qd
    f = wp.zeros(2, dtype=wp.vec3, device=device)
    for t, expect_active in ((0.5, False), (1.0, True), (2.0, True), (3.5, True), (4.5, False)):
        f.zero_()
        drag.eval(q, qd, wp.array([t], dtype=float, device=device), 0.0, f)
        target = drag.target_at(t)
        v_target = np.array([1.0, 0.0, 0.0]) if 1.0 < t < 3.0 else np.zeros(3)
        expect = -50.0 * (np.zeros(3) - target) - 3.0 * (np.array([1.0, 0, 0]) - v_target)
        np.testing.assert_allclose(f.numpy()[0], expect if expect_active else 0.0, atol=1e-5)
        np.testing.assert_allclose(f.numpy()[1], 0.0)
        assert drag.active_at(t) == expect_active
    np.testing.assert_allclose(drag.target_at(2.0), [1.0, 1.0, 0.0])


def test_drag_pulls_a_vertex_to_the_target(device):
    """With gravity off, the drag spring and a light air drag are the only external forces: the
    body ends at rest with the dragged vertex on the target (zero net force), whatever the
    springs do."""
    pts, faces = icosphere(1, radius=0.1)
    b = ws.ModelBuilder()
    add_soft_body(b, pts, faces, total_mass=0.2, stiffness=50.0, damping=0.02, interior="lattice", lattice_cells=3)
    model = b.finalize(device)
    target = np.array([0.3, 0.2, -0.1])
    drag = DragSpring(stiffness=20.0, damping=1.0)
    sim = ws.Simulator(model, integrator="semi_implicit_euler", forces=[drag, ws.Drag(linear=0.02)],
                       check_every=100)
    vertex = drag.grab_ray(sim.state.positions, origin=(0.0, 1.0, 0.0), direction=(0.0, -1.0, 0.0))
    assert vertex == int(np.argmax(pts[:, 1]))
    drag.set_target(target)
    for _ in range(3000):
        sim.step(1.0 / 1000)
    x = sim.state.positions.numpy()
    assert np.linalg.norm(x[vertex] - target) < 2e-3
    assert np.abs(sim.state.velocities.numpy()).max() < 0.02
    drag.release()
    f = wp.zeros(model.particle_count, dtype=wp.vec3, device=device)
    drag.eval(sim.state.positions, sim.state.velocities, sim._time, 0.0, f)
    assert not np.any(f.numpy())


def test_pick_particle_matches_numpy_ray_distance():
    rng = np.random.default_rng(4)
    pts = rng.uniform(-1, 1, (300, 3))
    origin, direction = np.array([0.2, -3.0, 0.1]), np.array([0.1, 1.0, -0.05])
    d = direction / np.linalg.norm(direction)
    t = np.maximum(0.0, (pts - origin) @ d)
    dist = np.linalg.norm(pts - origin - t[:, None] * d, axis=1)
    assert pick_particle(pts, origin, direction, device=DEVICE) == int(np.argmin(dist))
    assert pick_particle(pts, origin, direction, max_distance=0.5 * dist.min(), device=DEVICE) == -1
    with pytest.raises(ValueError, match="zero vector"):
        pick_particle(pts, origin, (0, 0, 0), device=DEVICE)


def test_drag_spec_parsing():
    items = parse_drag_spec("spout:0.3,0.6,0@0.5-1.5; 12:0,0.4,0>0.2,0.4,0@2-3")
    assert [(w, t0, t1) for w, _, t0, t1 in items] == [("spout", 0.5, 1.5), ("12", 2.0, 3.0)]
    np.testing.assert_allclose(items[1][1], [[0, 0.4, 0], [0.2, 0.4, 0]])
    for bad in ("spout@1-2", "spout:1,2@1-2", "spout:1,2,3@2-1", "3:1,2,3@5"):
        with pytest.raises(ValueError, match="drag item 0"):
            parse_drag_spec(bad)
    with pytest.raises(ValueError, match="stiffness"):
        scripted_drag(0, [[0, 0, 0]], 0.0, 1.0, stiffness=-1.0)


# ---------------------------------------------------------------- the teapot in a box


def test_named_anchors_are_the_knob_bottom_spout_and_handle_of_the_tilted_teapot():
    """The scene tilts the teapot 20 degrees, which lifts the spout's tip above the knob: the
    anchors are still named on the teapot as modelled, so ``knob`` is the lid's pole on the axis
    at the top (3.15 units x 0.1 m), ``bottom`` the bottom's pole, ``spout`` and ``handle`` the two
    ends in x, and each names a different particle."""
    from warpsim.scenes import get_scene
    from warpsim.scenes.teapot import ANCHORS

    scene = get_scene("teapot")({"resolution": 3, "springs": False}, device="cpu")
    rest = scene.rest_points
    index = {name: scene.anchor_particle(name) for name in ANCHORS}
    assert len(set(index.values())) == 4
    np.testing.assert_allclose(rest[index["knob"]], [0.0, 0.315, 0.0], atol=1e-6)
    np.testing.assert_allclose(rest[index["bottom"]], [0.0, 0.0, 0.0], atol=1e-6)
    assert rest[index["spout"], 0] == rest[:, 0].max() and rest[index["handle"], 0] == rest[:, 0].min()
    tilted = scene.model.particle_q.numpy()
    assert tilted[index["spout"], 1] > tilted[index["knob"], 1]  # why the tilted points cannot name the knob


def test_teapot_dropped_in_box_comes_to_rest_inside(device):
    """The scene's teapot, lifted by its knob for a moment, bounces off floor and walls and
    settles on the floor, never leaving the box."""
    from warpsim.scenes import get_scene

    scene = get_scene("teapot")({"friction": 0.6, "restitution": 0.2, "springs": False,
                                 "drag": "knob:0,0.9,0@0.2-0.5", "drag_stiffness": 60.0}, device=device)
    scene.sim.check_every = 50
    lo, hi = np.array(scene.lower), np.array(scene.upper)
    m = scene.model.particle_mass.numpy()
    energy = []
    for frame in range(1, 241):  # lifted by the knob (on the axis), it rocks on its round bottom until ~4 s
        scene.advance(1.0 / 60, 10)
        x = scene.sim.state.positions.numpy()
        v = scene.sim.state.velocities.numpy()
        assert np.all(x >= lo - 1e-6) and np.all(x <= hi + 1e-6), frame
        energy.append(0.5 * (m[:, None] * v**2).sum())
        if frame == 30:  # held up by the knob at t = 0.5 s
            assert x[scene.drag_vertices[0], 1] > 0.45
    assert x[:, 1].min() < 1e-3  # on the floor
    assert energy[-1] < 0.01 * max(energy)  # at rest, up to a faint jiggle
    assert np.linalg.norm(v, axis=1).mean() < 0.1
    data = scene.frame_data()
    assert data["teapot"]["points"].shape == (518, 3)


def test_small_mass_explodes_with_a_report_and_implicit_euler_stays_stable():
    """The lecture's 'reduce the mass and it explodes': semi-implicit Euler blows up and the
    error names the frame, the particle and the remedy; implicit Euler with the same settings
    stays finite and bounded."""
    m = teapot_mesh("low")
    results = {}
    for integrator in ("semi_implicit_euler", ws.ImplicitEuler(newton_iterations=1, cg_tol=1e-4)):
        b = ws.ModelBuilder()
        add_soft_body(b, m.points, m.faces, position=(0, 0.3, 0), total_mass=0.02, stiffness=40.0, damping=0.05,
                      mass_distribution="uniform", lattice_cells=4)
        sim = ws.Simulator(b.finalize(DEVICE), integrator=integrator, colliders=[ws.Box((-1, 0, -1), (1, 2, 1))])
        try:
            sim.run(frames=2, frame_dt=1.0 / 60, substeps=8)
            results[sim.integrator.name] = sim.state.positions.numpy()
        except ws.SimulationError as err:
            results[sim.integrator.name] = err
    err = results["semi_implicit_euler"]
    assert isinstance(err, ws.SimulationError) and err.frame == 1 and 0 <= err.particle < 538
    assert "frame 1" in str(err) and f"particle {err.particle}" in str(err) and "implicit_euler" in str(err)
    x = results["implicit_euler"]
    assert np.all(np.isfinite(x)) and np.abs(x).max() < 1.0


def test_teapot_scene_writes_mesh_springs_and_drag(tmp_path):
    from pxr import Usd, UsdGeom

    from warpsim.scenes import get_scene
    from warpsim.usd.writer import UsdCacheWriter

    scene = get_scene("teapot")({"resolution": "3", "drag": "spout:0.3,0.5,0@0-0.1", "obstacle": "paddle"},
                                device=DEVICE)
    path = tmp_path / "teapot.usda"
    with UsdCacheWriter(str(path), fps=60) as writer:
        scene.declare(writer)
        writer.write_frame(0, scene.frame_data())
        for frame in (1, 2):
            scene.advance(1.0 / 60, 10)
            writer.write_frame(frame, scene.frame_data())
    stage = Usd.Stage.Open(str(path))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/teapot"))
    assert len(mesh.GetFaceVertexCountsAttr().Get()) == len(scene.body.faces)
    pts = np.array(mesh.GetPointsAttr().Get(2))
    np.testing.assert_allclose(pts, scene.sim.state.positions.numpy()[: scene.body.surface_count], atol=1e-6)
    curves = UsdGeom.BasisCurves(stage.GetPrimAtPath("/World/springs"))
    assert len(curves.GetCurveVertexCountsAttr().Get()) == scene.model.spring_count
    drag = np.array(UsdGeom.BasisCurves(stage.GetPrimAtPath("/World/drag")).GetPointsAttr().Get(1))
    np.testing.assert_allclose(drag[1], [0.3, 0.5, 0.0], atol=1e-6)
    paddle = [np.array(UsdGeom.Mesh(stage.GetPrimAtPath("/World/obstacle")).GetPointsAttr().Get(f)) for f in (1, 2)]
    assert not np.allclose(paddle[0], paddle[1])  # the kinematic paddle moves
    with pytest.raises(ValueError, match="drag target 'lid'"):
        get_scene("teapot")({"drag": "lid:0,1,0@0-1"}, device=DEVICE)
    assert math.isclose(scene.sim.time, 2.0 / 60)


def test_jiggly_teapot_example_runs(tmp_path):
    """examples/teapot.py as a user runs it: the spout is picked with a ray at 0.6 s."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    script = Path(__file__).resolve().parents[1] / "examples" / "teapot.py"
    out = subprocess.run([sys.executable, str(script), "--frames", "40", "--out", "t.usda"], cwd=tmp_path,
                         env=dict(os.environ, WARP_QUIET="1"), capture_output=True, text=True, timeout=600, check=False)
    assert out.returncode == 0, out.stderr[-3000:]
    assert "picked particle" in out.stdout and (tmp_path / "t.usda").exists()


def test_soft_body_springs_equal_add_spring_one_at_a_time():
    """add_soft_body adds its springs at once (add_springs): the same pairs, coefficients and rest
    lengths, bit for bit, as add_spring one spring at a time, and its rotated vertices as
    quat_rotate one vertex at a time (issue 50)."""
    m = teapot_mesh(3, scale=0.3)
    rotation = (0.0, 0.0, math.sin(0.3), math.cos(0.3))
    bulk = ws.ModelBuilder()
    body = add_soft_body(bulk, m.points, m.faces, position=(0.1, 0.7, -0.2), rotation=rotation, stiffness=37.0,
                         damping=0.3, interior_stiffness=55.0, lattice_cells=4)
    from warpsim.bodies.colliders import parse_pose, quat_rotate

    pos, rot = parse_pose((0.1, 0.7, -0.2), rotation, "teapot")
    world = pos + np.array([quat_rotate(rot, 1.0 * p) for p in m.points])
    assert np.asarray(bulk.particle_q)[:body.surface_count].tobytes() == world.tobytes()
    one = ws.ModelBuilder()
    one.add_particles(np.asarray(bulk.particle_q))
    for (i, j), k, c in zip(bulk.spring_indices, bulk.spring_stiffness, bulk.spring_damping):
        one.add_spring(i, j, k, c)
    assert one.spring_indices == bulk.spring_indices
    for name in ("spring_rest_length", "spring_stiffness", "spring_damping"):
        assert np.asarray(getattr(one, name)).tobytes() == np.asarray(getattr(bulk, name)).tobytes(), name
    assert set(bulk.spring_stiffness) == {37.0, 55.0} and bulk.spring_count == body.spring_count
