"""Marching cubes (warpsim.meshing.marching_cubes, kernels/marching_cubes.py) on "cpu" (and CUDA when present).

Oracles: analytic sphere area/volume and their second-order convergence, Euler characteristics
of known topologies, combinatorial watertightness, NumPy counts of crossed grid edges, and
scikit-image's marching cubes.
"""
import os
import subprocess
import sys
import warnings

import numpy as np
import pytest
import warp as wp
from warpsim.kernels import marching_cubes as mck
from warpsim.kernels.implicit_fields import gyroid_ball, metaball_density

from warpsim.meshing.marching_cubes import MarchingCubes, marching_cubes, topology_changed

# ---------------------------------------------------------------- helpers


def grid(n, lo=-1.0, hi=1.0):
    """Node coordinates of an n^3 grid over [lo, hi]^3 (indexing ij) and the spacing."""
    x = np.linspace(lo, hi, n)
    return np.meshgrid(x, x, x, indexing="ij"), x[1] - x[0]


def sphere_sdf(n, radius=0.7, center=(0.0, 0.0, 0.0)):
    (X, Y, Z), h = grid(n)
    f = np.sqrt((X - center[0]) ** 2 + (Y - center[1]) ** 2 + (Z - center[2]) ** 2) - radius
    return f.astype(np.float32), h


def torus_sdf(X, Y, Z, major=0.55, minor=0.25, cx=0.0):
    q = np.sqrt((X - cx) ** 2 + Y**2) - major
    return np.sqrt(q**2 + Z**2) - minor


def mesh(field, h, device, **kw):
    return marching_cubes(field, spacing=h, origin=(-1.0, -1.0, -1.0), device=device, **kw).numpy()


def area_volume(v, f):
    p = v[f].astype(np.float64)
    cross = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    area = 0.5 * np.linalg.norm(cross, axis=1).sum()
    volume = np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2])).sum() / 6.0
    return area, volume


def undirected_edge_counts(f):
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    e.sort(axis=1)
    _, counts = np.unique(e, axis=0, return_counts=True)
    return counts


def directed_edge_counts(f):
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    _, counts = np.unique(e, axis=0, return_counts=True)
    return counts


def euler_characteristic(v, f):
    return len(v) - len(undirected_edge_counts(f)) + len(f)


def crossed_edge_count(field, iso=0.0, close_boundary=False):
    """NumPy oracle: grid edges whose nodes differ in inside (< iso) / outside (>= iso)."""
    inside = np.asarray(field, dtype=np.float32) < np.float32(iso)
    if close_boundary:
        inside = np.pad(inside, 1, constant_values=False)
    return sum(int((np.diff(inside.astype(np.int8), axis=a) != 0).sum()) for a in range(3))


def assert_closed_welded(v, f, field, iso=0.0, close_boundary=False):
    assert len(f) > 0
    counts = undirected_edge_counts(f)
    assert counts.min() == 2 and counts.max() == 2, "every edge must be shared by exactly two faces"
    assert directed_edge_counts(f).max() == 1, "neighbouring faces must be oriented consistently"
    assert len(np.unique(v, axis=0)) == len(v), "two vertices share one position"
    assert len(v) == crossed_edge_count(field, iso, close_boundary)
    assert np.unique(f).size == len(v), "every vertex is used"


# ---------------------------------------------------------------- tables


def test_tables_match_corner_classification():
    for case in range(256):
        inside = [(case >> c) & 1 for c in range(8)]
        crossed = 0
        for e, (a, b) in enumerate(mck.EDGE_CORNERS):
            if inside[a] != inside[b]:
                crossed |= 1 << e
        assert mck.EDGE_TABLE[case] == crossed, case
        used = 0
        row = [e for e in mck.TRI_TABLE[case] if e >= 0]
        assert len(row) % 3 == 0 and len(row) // 3 <= mck.MAX_CASE_TRIANGLES
        for e in row:
            used |= 1 << e
        assert used == crossed, f"case {case} must use exactly its crossed edges"
        assert all(e == -1 for e in mck.TRI_TABLE[case][len(row):])


# ---------------------------------------------------------------- accuracy


def test_sphere_area_volume_second_order(device):
    exact_area = 4.0 * np.pi * 0.7**2
    exact_volume = 4.0 / 3.0 * np.pi * 0.7**3
    err_a, err_v = [], []
    for n in (17, 33, 65):
        field, h = sphere_sdf(n)
        v, f, _ = mesh(field, h, device)
        area, volume = area_volume(v, f)
        err_a.append(area / exact_area - 1.0)
        err_v.append(volume / exact_volume - 1.0)
    # Published figures at 33 nodes per side: about -2.5e-3 (area), -4.7e-3 (volume).
    assert err_a[1] == pytest.approx(-2.5e-3, rel=0.3)
    assert err_v[1] == pytest.approx(-4.7e-3, rel=0.3)
    for errs in (err_a, err_v):
        for coarse, fine in zip(errs, errs[1:]):
            order = np.log2(coarse / fine)
            assert 1.7 < order < 2.5, (errs, order)


@pytest.mark.parametrize("seed", [0, 1])
def test_area_matches_scikit_image(seed, device):
    measure = pytest.importorskip("skimage.measure")
    rng = np.random.default_rng(seed)
    shape = (40, 33, 29)
    spacing = (0.05, 0.06, 0.07)
    origin = (-1.0, -0.9, -1.0)
    axes = [origin[a] + spacing[a] * np.arange(shape[a]) for a in range(3)]
    X, Y, Z = np.meshgrid(*axes, indexing="ij")
    density = np.zeros(shape)
    for c, r in zip(rng.uniform(-0.4, 0.4, (4, 3)), rng.uniform(0.25, 0.4, 4)):
        density += r**2 / ((X - c[0]) ** 2 + (Y - c[1]) ** 2 + (Z - c[2]) ** 2 + 1e-3)
    field = density.astype(np.float32)
    iso = 1.0
    res = marching_cubes(field, spacing=spacing, origin=origin, iso=iso, device=device, inside="above")
    v, f, _ = res.numpy()
    sv, sf, _, _ = measure.marching_cubes(field, iso, spacing=spacing)
    sk_area = measure.mesh_surface_area(sv, sf)
    area, volume = area_volume(v, f)
    assert area == pytest.approx(sk_area, rel=1e-3)
    _, sk_volume = area_volume(sv + np.array(origin), sf)
    assert volume == pytest.approx(abs(sk_volume), rel=1e-3) and volume > 0
    np.testing.assert_allclose(v.min(0), sv.min(0) + origin, atol=1e-3 * max(spacing))
    np.testing.assert_allclose(v.max(0), sv.max(0) + origin, atol=1e-3 * max(spacing))


# ---------------------------------------------------------------- watertight and welded


def test_sphere_closed_welded_oriented(device):
    field, h = sphere_sdf(24, radius=0.63, center=(0.05, -0.02, 0.03))
    v, f, nrm = mesh(field, h, device)
    assert_closed_welded(v, f, field)
    assert euler_characteristic(v, f) == 2
    _, volume = area_volume(v, f)
    assert volume > 0.0
    # Gradient normals are unit and radial; face normals agree with them.
    np.testing.assert_allclose(np.linalg.norm(nrm, axis=1), 1.0, atol=1e-5)
    radial = v - np.array([0.05, -0.02, 0.03])
    radial /= np.linalg.norm(radial, axis=1, keepdims=True)
    assert np.einsum("ij,ij->i", nrm, radial).min() > 0.99
    p = v[f]
    face_n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    assert np.einsum("ij,ij->i", face_n, nrm[f].sum(axis=1)).min() > 0.0


def test_usd_frame_is_the_mesh():
    """usd_frame(): USD Mesh data of the same triangles (3 vertices per face, indices in face
    order, the same points and, on request, normals)."""
    field, h = sphere_sdf(12, radius=0.6)
    result = marching_cubes(field, spacing=h, origin=(-1.0, -1.0, -1.0), device="cpu")
    v, f, nrm = result.numpy()
    data = result.usd_frame(normals=True)
    assert data["faceVertexCounts"].tolist() == [3] * len(f)
    np.testing.assert_array_equal(data["faceVertexIndices"], f.reshape(-1))
    np.testing.assert_array_equal(data["points"].numpy(), v)
    np.testing.assert_array_equal(data["normals"].numpy(), nrm)
    assert "normals" not in result.usd_frame()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_noise_field_closed_with_boundary_option(seed, device):
    rng = np.random.default_rng(seed)
    field = rng.standard_normal((11, 9, 13)).astype(np.float32)
    v, f, nrm = marching_cubes(field, spacing=0.1, device=device, close_boundary=True).numpy()
    assert_closed_welded(v, f, field, close_boundary=True)
    assert np.isfinite(nrm).all()
    np.testing.assert_allclose(np.linalg.norm(nrm, axis=1), 1.0, atol=1e-5)
    # Without the option the cut surface is open at the domain boundary ...
    _, f2, _ = marching_cubes(field, spacing=0.1, device=device).numpy()
    assert undirected_edge_counts(f2).min() == 1
    # ... and a user-padded outside layer closes it the same way (no cracks anywhere inside).
    padded = np.pad(field, 1, constant_values=1.0)
    v3, f3, _ = marching_cubes(padded, spacing=0.1, device=device).numpy()
    assert_closed_welded(v3, f3, padded)
    assert len(v3) == len(v) and len(f3) == len(f)


@pytest.mark.parametrize("block_size", [1, 2, 3, 5])
def test_block_size_does_not_change_the_mesh(block_size, device):
    rng = np.random.default_rng(11)
    field = rng.standard_normal((12, 7, 10)).astype(np.float32)
    ref = MarchingCubes(field.shape, 0.1, device=device, close_boundary=True, block_size=8).mesh(field).numpy()
    v, f, n = MarchingCubes(field.shape, 0.1, device=device, close_boundary=True, block_size=block_size).mesh(
        field
    ).numpy()
    assert_closed_welded(v, f, field, close_boundary=True)
    order, ref_order = np.lexsort(v.T), np.lexsort(ref[0].T)
    np.testing.assert_array_equal(v[order], ref[0][ref_order])
    np.testing.assert_array_equal(n[order], ref[2][ref_order])
    # Same triangles, as sets of vertex positions.
    def tri_keys(faces, order):
        rank = np.empty(len(order), np.int64)
        rank[order] = np.arange(len(order))
        keys = np.sort(rank[faces], axis=1)
        return keys[np.lexsort(keys.T[::-1])]

    np.testing.assert_array_equal(tri_keys(f, order), tri_keys(ref[1], ref_order))


def test_sphere_cut_by_boundary_is_capped(device):
    field, h = sphere_sdf(21, radius=1.2)
    v, f, _ = mesh(field, h, device, close_boundary=True)
    assert_closed_welded(v, f, field, close_boundary=True)
    assert euler_characteristic(v, f) == 2
    _, volume = area_volume(v, f)
    # The cap lies EDGE_T_MIN * h outside the cube faces: the volume is the sphere-cube intersection.
    (X, Y, Z), _ = grid(201)
    exact = 8.0 * np.mean(np.sqrt(X**2 + Y**2 + Z**2) < 1.2)
    assert volume == pytest.approx(exact, rel=0.02)
    assert np.abs(v).max() <= 1.0 + 1.01 * mck.EDGE_T_MIN * h


def test_nodes_exactly_at_iso_give_no_degenerate_triangles(device):
    i = np.arange(-7, 8, dtype=np.float32)
    X, Y, Z = np.meshgrid(i, i, i, indexing="ij")
    # Integer sphere r^2 = 25 passes exactly through nodes such as (5,0,0), (3,4,0), (0,3,4).
    sphere = X**2 + Y**2 + Z**2 - 25.0
    rng = np.random.default_rng(7)
    ternary = rng.integers(-1, 2, size=(9, 10, 8)).astype(np.float32)  # a third of the nodes at iso
    plane = X - 2.0  # a whole grid plane at iso
    for field, close in ((sphere, False), (ternary, True), (plane, False)):
        assert np.any(field == 0.0)
        v, f, _ = marching_cubes(field, device=device, close_boundary=close).numpy()
        assert len(np.unique(v, axis=0)) == len(v), "vertices of edges meeting at an iso node coincide"
        p = v[f].astype(np.float64)
        areas = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
        # Smallest possible: three vertices EDGE_T_MIN from one node, (sqrt(3)/2) * EDGE_T_MIN^2.
        assert areas.min() > 0.5 * mck.EDGE_T_MIN**2
        if field is not plane:
            assert_closed_welded(v, f, field, close_boundary=close)
    # The plane x = 2 is meshed just below its iso nodes, within EDGE_T_MIN of a cell.
    v, f, n = marching_cubes(plane, origin=(-7, -7, -7), device=device).numpy()
    assert len(v) == 15 * 15 and np.abs(v[:, 0] - 2.0).max() <= 1.01 * mck.EDGE_T_MIN
    np.testing.assert_allclose(n, np.tile([1.0, 0.0, 0.0], (len(n), 1)), atol=1e-6)


# ---------------------------------------------------------------- topology


def test_euler_characteristics(device):
    (X, Y, Z), h = grid(41, -1.2, 1.2)
    origin = (-1.2, -1.2, -1.2)

    def chi(field, **kw):
        v, f, _ = marching_cubes(field.astype(np.float32), spacing=h, origin=origin, device=device, **kw).numpy()
        assert undirected_edge_counts(f).max() == 2 and undirected_edge_counts(f).min() == 2
        return euler_characteristic(v, f)

    torus = torus_sdf(X, Y, Z)
    assert chi(torus) == 0
    two_spheres = np.minimum(
        np.sqrt((X - 0.5) ** 2 + Y**2 + Z**2) - 0.35, np.sqrt((X + 0.5) ** 2 + Y**2 + Z**2) - 0.35
    )
    assert chi(two_spheres) == 4
    genus2 = np.minimum(torus_sdf(X, Y, Z, 0.45, 0.2, -0.5), torus_sdf(X, Y, Z, 0.45, 0.2, 0.5))
    assert chi(genus2) == -2

    def blobs(d):
        return sum(0.16 / ((X - c) ** 2 + Y**2 + Z**2 + 1e-6) for c in (-d, d))

    assert chi(blobs(0.25), iso=1.0, inside="above") == 2  # overlapping: one merged blob
    assert chi(blobs(0.6), iso=1.0, inside="above") == 4  # apart: two blobs


def test_inside_above_is_the_negated_field(device):
    field, h = sphere_sdf(19)
    a = marching_cubes(field, spacing=h, iso=0.1, device=device).numpy()
    b = marching_cubes(-field, spacing=h, iso=-0.1, device=device, inside="above").numpy()
    for x, y in zip(a, b):
        np.testing.assert_allclose(x, y, atol=1e-6)


# ---------------------------------------------------------------- API


def test_reusable_mesher_keeps_buffers_and_grows(device):
    field, h = sphere_sdf(25, radius=0.4)
    wp_field = wp.array(field, dtype=wp.float32, device=device)
    mesher = MarchingCubes(field.shape, h, (-1, -1, -1), device, max_vertices=20000, max_triangles=40000)
    first = mesher.mesh(wp_field)
    ptrs = (first.vertices.ptr, first.faces.ptr, first.normals.ptr)
    ref = marching_cubes(field, spacing=h, origin=(-1, -1, -1), device=device).numpy()
    for x, y in zip(first.numpy(), ref):
        np.testing.assert_array_equal(x, y)
    smaller, _ = sphere_sdf(25, radius=0.3)
    second = mesher.mesh(smaller)
    assert (second.vertices.ptr, second.faces.ptr, second.normals.ptr) == ptrs
    assert second.vertex_count < first.vertex_count and mesher.reallocation_count == 0
    assert topology_changed(first.numpy()[1], second)
    again = mesher.mesh(smaller)
    assert not topology_changed(second.numpy()[1], again)
    assert topology_changed(None, again)

    tiny = MarchingCubes(field.shape, h, (-1, -1, -1), device, max_vertices=10, max_triangles=10)
    with pytest.warns(RuntimeWarning, match="max_vertices"):
        grown = tiny.mesh(wp_field)
    assert tiny.reallocation_count == 1 and tiny.vertex_capacity >= grown.vertex_count
    for x, y in zip(grown.numpy(), ref):
        np.testing.assert_array_equal(x, y)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        tiny.mesh(wp_field)  # fits now: no growth, no warning


def test_empty_and_nan_fields(device):
    res = marching_cubes(np.ones((4, 5, 6), np.float32), device=device)
    assert res.vertex_count == 0 and res.face_count == 0 and res.faces.shape == (0, 3)
    field, h = sphere_sdf(12)
    field[6, 5, 7] = np.nan  # meshing around it would add a bubble: an error naming the node instead
    for given in (field, wp.array(field, dtype=wp.float32, device=device)):  # host and device checks
        with pytest.raises(ValueError, match=r"field node \[6, 5, 7\] .* is nan \(1 of 1728 nodes"):
            marching_cubes(given, spacing=h, device=device)
    field[6, 5, 7] = np.inf
    with pytest.raises(ValueError, match=r"node \[6, 5, 7\] .* is inf"):
        MarchingCubes(field.shape, h, device=device).mesh(wp.array(field, dtype=wp.float32, device=device))
    with pytest.raises(ValueError, match=r"node \[0, 0, 0\] .* \(64 of 64 nodes are not finite\)"):
        marching_cubes(np.full((4, 4, 4), np.nan, np.float32), device=device)  # all-NaN: not an empty mesh
    field[6, 5, 7] = 0.01
    v, f, n = marching_cubes(field, spacing=h, device=device).numpy()
    assert np.isfinite(v).all() and np.isfinite(n).all()
    assert_closed_welded(v, f, field)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"field": np.zeros((4, 4))}, "3D"),
        ({"field": np.zeros((4, 1, 4))}, "at least 2 nodes"),
        ({"spacing": 0.0}, "spacing"),
        ({"spacing": (0.1, -0.1, 0.1)}, "spacing"),
        ({"spacing": (0.1, 0.1)}, "spacing"),
        ({"iso": float("nan")}, "iso"),
        ({"origin": (0.0, 0.0)}, "origin"),
        ({"inside": "outside"}, "inside"),
        ({"field": wp.zeros((3, 3, 3), dtype=wp.float64, device="cpu")}, "float32"),
    ],
)
def test_bad_input_raises(kwargs, match):
    args = {"field": np.zeros((4, 4, 4), np.float32), "device": "cpu"}
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        marching_cubes(**args)


def test_mesher_rejects_wrong_shape(device):
    mesher = MarchingCubes((4, 4, 4), device=device)
    with pytest.raises(ValueError, match="shape"):
        mesher.mesh(np.zeros((4, 4, 5), np.float32))


# ---------------------------------------------------------------- metaballs


def test_metaball_density_matches_numpy(device):
    rng = np.random.default_rng(4)
    centers = rng.uniform(-0.5, 0.5, (3, 3)).astype(np.float32)
    radii = np.array([0.5, 0.7, 0.9], np.float32)
    lower, spacing = (-1.0, -0.8, -0.9), (0.1, 0.12, 0.09)
    out = wp.zeros((21, 14, 20), dtype=wp.float32, device=device)
    metaball_density(
        wp.array(centers, dtype=wp.vec3, device=device), wp.array(radii, device=device), out, lower, spacing
    )
    axes = [lower[a] + spacing[a] * np.arange(out.shape[a]) for a in range(3)]
    p = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
    q = ((p[..., None, :] - centers) ** 2).sum(-1) / radii**2
    expected = np.where(q < 1.0, (1.0 - q) ** 3, 0.0).sum(-1)
    np.testing.assert_allclose(out.numpy(), expected, atol=1e-5)


def test_metaballs_example_writes_changing_topology(tmp_path):
    Usd = pytest.importorskip("pxr.Usd")
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    out = tmp_path / "metaballs.usda"
    cmd = [sys.executable, os.path.join(root, "examples", "metaballs.py"), "--device", "cpu", "--frames", "4",
           "--resolution", "20", "--out", str(out)]
    run = subprocess.run(cmd, check=False, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    stage = Usd.Stage.Open(str(out))
    prim = stage.GetPrimAtPath("/World/blobs")
    times = prim.GetAttribute("points").GetTimeSamples()
    assert times == [0.0, 1.0, 2.0, 3.0]
    for t in times:
        points = np.asarray(prim.GetAttribute("points").Get(t))
        indices = np.asarray(prim.GetAttribute("faceVertexIndices").Get(t)).reshape(-1, 3)
        assert len(indices) > 0 and indices.max() < len(points)
        assert undirected_edge_counts(indices).min() == 2 and undirected_edge_counts(indices).max() == 2
        assert len(prim.GetAttribute("primvars:normals").Get(t)) == len(points)


def test_gyroid_ball_field_matches_numpy_and_meshes_closed(device):
    n = 40
    (X, Y, Z), h = grid(n)
    out = wp.zeros((n, n, n), dtype=wp.float32, device=device)
    gyroid_ball(out, (-1.0, -1.0, -1.0), (h, h, h), period=0.8, thickness=0.08, radius=0.9)
    w = 2.0 * np.pi / 0.8
    g = np.sin(w * X) * np.cos(w * Y) + np.sin(w * Y) * np.cos(w * Z) + np.sin(w * Z) * np.cos(w * X)
    expected = np.maximum(np.abs(g) / w - 0.04, np.sqrt(X**2 + Y**2 + Z**2) - 0.9)
    np.testing.assert_allclose(out.numpy(), expected, atol=2e-6)
    v, f, _ = mesh(out, h, device)
    assert_closed_welded(v, f, out.numpy())
    assert area_volume(v, f)[1] > 0.0
