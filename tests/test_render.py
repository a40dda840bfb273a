"""The preview renderer (warpsim.render, kernels/render.py) and ``warpsim render`` on the CPU.

Analytic checks: a sphere's silhouette against its perspective projection, Beer-Lambert
transmission through a uniform smoke slab, an empty scene against the sky formula; behaviour:
GIF frame counts, clear errors (exit 2) for bad cameras, sizes and frame ranges, and the teapot
seen through its box of walls as other USD tools show it (walls are translucent render geometry)."""

import math

import numpy as np
import pytest

from warpsim.cli import main
from warpsim.render import Camera, GeometryBuilder, Renderer
from warpsim.render.cache import render_cache
from warpsim.render.renderer import to_srgb8
from warpsim.usd.writer import UsdCacheWriter

W = H = 160


def _run(*argv):
    import io

    out, err = io.StringIO(), io.StringIO()
    return main(list(argv), out, err), out.getvalue(), err.getvalue()


def _red_mask(img):
    """Pixels of a pure red object (sRGB uint8 or linear float) against the blue-white sky/ground."""
    img = img.astype(np.float64)
    return img[..., 0] - img[..., 1] > 0.2 * (255.0 if img.max() > 1.5 else 1.0)


def _sphere_area_px(radius, dist, fov, height):
    """Analytic silhouette area [px] of a sphere centred on the optical axis: a disc of image-plane
    radius tan(asin(r / d)) = r / sqrt(d^2 - r^2) at unit focal distance."""
    rho = radius / math.sqrt(dist * dist - radius * radius)
    px = rho / math.tan(math.radians(0.5 * fov)) * 0.5 * height
    return math.pi * px * px


@pytest.mark.parametrize("radius, dist", [(0.5, 2.0), (0.3, 1.0)])
def test_sphere_silhouette_matches_its_projection(radius, dist):
    g = GeometryBuilder()
    g.add_spheres([[0.0, 0.0, 0.0]], radius, (1.0, 0.0, 0.0))
    cam = Camera((0.0, 0.0, dist), (0.0, 0.0, 0.0), fov=40.0)
    img = Renderer(W, H, device="cpu").render(g.build(), cam, ground_y=False, linear=True)
    area = _red_mask(img).sum()
    expected = _sphere_area_px(radius, dist, 40.0, H)
    assert abs(area - expected) / expected < 0.02, (area, expected)


def test_sphere_prim_of_a_cache_projects_where_the_camera_says(tmp_path):
    """A USD Sphere (translated) and a Points sphere through render_cache: each silhouette's area and
    centre match the projection of the camera (an off-axis sphere projects to an ellipse whose
    centre is near the projected centre)."""
    path = str(tmp_path / "s.usda")
    with UsdCacheWriter(path, fps=10) as w:
        w.add_sphere("ball", (0.0, 0.4, 0.0), 0.4, color=(1.0, 0.0, 0.0))
        w.add_points("p", radius=0.2, color=(0.0, 1.0, 0.0), velocities=False)
        w.write_frame(0, {"p": {"points": [[0.7, 0.2, 0.0]]}})
    cam = Camera((0.0, 0.4, 3.0), (0.0, 0.4, 0.0), fov=40.0)
    out = str(tmp_path / "s.png")
    render_cache(path, out, size=(W, H), camera=cam, device="cpu")
    from PIL import Image

    img = np.asarray(Image.open(out))
    red = _red_mask(img)
    expected = _sphere_area_px(0.4, 3.0, 40.0, H)
    assert abs(red.sum() - expected) / expected < 0.02
    rows, cols = np.nonzero(red)
    assert abs(cols.mean() - W / 2) < 1.0 and abs(rows.mean() - H / 2) < 1.0
    img = img.astype(int)
    green = (img[..., 1] - img[..., 0] > 60) & (img[..., 1] - img[..., 2] > 60)
    cx, cy = cam.project([[0.7, 0.2, 0.0]], W, H)[0][0]
    rows, cols = np.nonzero(green)
    assert green.sum() > 100 and abs(cols.mean() - cx) < 2.0 and abs(rows.mean() - cy) < 2.0


def test_empty_scene_is_background_only(tmp_path):
    path = str(tmp_path / "empty.usda")
    with UsdCacheWriter(path, fps=10) as w:
        w.add_points("p", count_changes=True, velocities=False)
        for f in range(3):
            w.write_frame(f, {"p": {"points": np.zeros((0, 3)), "ids": np.zeros(0, np.int64)}})
    out = str(tmp_path / "empty.png")
    cam = Camera((1.0, 2.0, 3.0), (0.0, 0.0, 0.0))
    render_cache(path, out, size=(64, 48), camera=cam, device="cpu")
    from PIL import Image

    img = np.asarray(Image.open(out)).astype(int)
    r = Renderer(64, 48, device="cpu")
    f, right, up = cam.basis()
    tx, ty = cam.tangents(64, 48)
    j, i = np.meshgrid(np.arange(64), np.arange(48))
    d = (f + ((2 * (j + 0.5) / 64 - 1) * tx)[..., None] * right + ((1 - 2 * (i + 0.5) / 48) * ty)[..., None] * up)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    s = np.clip(0.5 + 0.5 * d[..., 1:2], 0, 1)
    sky = (1 - s) * np.asarray(r.background[0]) + s * np.asarray(r.background[1])
    assert np.abs(img - to_srgb8(sky).astype(int)).max() <= 1


def test_smoke_slab_transmits_beer_lambert():
    """Black smoke of uniform density rho over L metres in front of the sky: the pixel is the sky
    times exp(-sigma rho L) (sigma: the renderer's extinction per unit density)."""
    rho, n, dx = 0.05, 8, 0.1
    g = GeometryBuilder()
    g.set_volume(np.full((n, n, n), rho), (-0.4, -0.4, -0.4), dx, color=(0.0, 0.0, 0.0))
    cam = Camera((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), fov=20.0)
    r = Renderer(33, 33, device="cpu")
    with_smoke = r.render(g.build(), cam, ground_y=False, linear=True)[16, 16]
    sky = r.render(GeometryBuilder().build(), cam, ground_y=False, linear=True)[16, 16]
    expected = math.exp(-r.smoke_extinction * rho * n * dx)
    assert 0.05 < expected < 0.5
    assert with_smoke / sky == pytest.approx([expected] * 3, rel=0.02)


def _write_frames(path, frames):
    with UsdCacheWriter(path, fps=12, chunk_size=4) as w:
        w.add_points("p", radius=0.1, color=(1.0, 0.0, 0.0), velocities=False)
        w.add_plane("floor", size=2.0)
        for f in range(frames):
            w.write_frame(f, {"p": {"points": [[0.15 * f, 0.1 + 0.1 * f, 0.0]]}})  # every frame differs


def test_gif_has_the_asked_frames(tmp_path):
    from PIL import Image

    path = str(tmp_path / "c.usda")
    _write_frames(path, 9)
    for spec, count in (("0:4", 5), ("2:8:3", 3), (None, 9)):
        out = str(tmp_path / f"c{count}.gif")
        code, _, err = _run("render", path, "--out", out, "--size", "40x30", "--device", "cpu",
                               "--no-progress", *(["--frames", spec] if spec else []))
        assert code == 0, err
        with Image.open(out) as im:
            assert im.n_frames == count
            durations = []
            for k in range(count):
                im.seek(k)
                durations.append(im.info["duration"])
            assert durations == [80] * count  # 12 fps in the GIF's 1/100 s steps


def test_mp4_has_the_asked_frames(tmp_path):
    import imageio.v2 as iio

    path = str(tmp_path / "c.usda")
    _write_frames(path, 6)
    out = str(tmp_path / "c.mp4")
    assert _run("render", path, "--out", out, "--size", "41x31", "--no-progress", "--device", "cpu")[0] == 0
    with iio.get_reader(out) as reader:
        assert reader.count_frames() == 6


@pytest.mark.parametrize("args, words", [
    (["--camera", "1,1,1,1,1,1"], "same point"),
    (["--camera", "1,2,3"], "six numbers"),
    (["--size", "0x10"], "width 0"),
    (["--size", "big"], "WIDTHxHEIGHT"),
    (["--frames", "3:20"], "outside the cache's frames 0..5"),
    (["--frames", "4:2"], "outside"),
    (["--frame", "9"], "outside the cache's frames 0..5"),
    (["--frames", "a:b"], "A:B"),
    (["--out", "x.jpg"], ".png (one frame), .gif or .mp4"),
    (["--out", "x.png", "--frames", "0:2"], "a .png holds one frame"),
    (["--fps", "0"], "--fps"),
])
def test_bad_input_is_a_clear_usage_error(tmp_path, args, words):
    path = str(tmp_path / "c.usda")
    _write_frames(path, 6)
    out = ["--out", str(tmp_path / "x.gif")] if "--out" not in args else []
    code, _, err = _run("render", path, "--device", "cpu", "--no-progress", *out,
                           *[str(tmp_path / a) if a.startswith("x.") else a for a in args])
    assert code == 2
    lines = [ln for ln in err.splitlines() if ln.startswith("warpsim: error:")]
    assert len(lines) == 1 and words in lines[0], err
    assert not list(tmp_path.glob("x.*"))  # nothing written


def test_missing_cache_is_a_usage_error(tmp_path):
    code, _, err = _run("render", str(tmp_path / "none.usda"), "--device", "cpu")
    assert code == 2 and "does not exist" in err


def test_teapot_is_seen_through_its_box(tmp_path):
    """The teapot scene's walls are translucent render geometry (displayOpacity 0.2) on an opaque
    floor: a default render from a camera outside the box draws the walls and the teapot still
    shows through them."""
    from PIL import Image

    cache = str(tmp_path / "teapot.usda")
    code, _, err = _run("run", "teapot", "--frames", "2", "--out", cache, "--device", "cpu", "--no-progress",
                        "--set", "resolution=3", "--set", "springs=false")
    assert code == 0, err
    cam = Camera((0.9, 0.9, 1.3), (0.0, 0.4, 0.0))  # outside the box of walls [-0.7, 0.7]^2 x [0, 1.4]
    assert np.abs(cam.eye[[0, 2]]).max() > 0.7

    def render(name, **kw):
        out = str(tmp_path / f"{name}.png")
        render_cache(cache, out, size=(120, 90), camera=cam, device="cpu", frame=2, **kw)
        return np.asarray(Image.open(out)).astype(int)

    from warpsim.render.usd_scene import CacheScene

    r = Renderer(120, 90, device="cpu")
    geom = CacheScene(cache, only=["teapot"]).geometry(2)
    alone = to_srgb8(r.render(geom, cam, ground_y=False, linear=True)).astype(int)
    geom.face_colors[:] = (1.0, 0.0, 0.0)
    teapot = _red_mask(r.render(geom, cam, ground_y=False, linear=True))  # the teapot's own pixels
    assert teapot.sum() > 300
    default = render("default")
    container = render("container", only=["walls", "floor"])
    seen = np.abs(default - container).max(-1) > 8
    assert seen[teapot].mean() > 0.8  # the teapot shows through its walls (measured 0.88: its shaded side
    # is close to the grey floor behind it)
    assert np.abs(alone - container).max(-1)[teapot].mean() > 8  # (and the container alone looks different)
    no_walls = render("no_walls", only=["teapot", "floor"])
    # the walls are drawn by default: they change the picture around the teapot
    assert (np.abs(no_walls - default).max(-1) > 8)[~teapot].mean() > 0.2


def test_run_preview_writes_the_animation_beside_the_cache(tmp_path):
    from PIL import Image

    cache = tmp_path / "sub" / "b.usda"
    code, _, err = _run("run", "pendulum", "--frames", "4", "--out", str(cache), "--preview",  # alone: beside it
                        "--device", "cpu", "--no-progress")
    assert code == 0, err
    with Image.open(tmp_path / "sub" / "b.gif") as im:
        assert im.n_frames == 5
    assert _run("run", "pendulum", "--frames", "1", "--out", str(cache), "--preview", str(tmp_path / "b.jpg"))[0] == 2


def test_instances_curves_and_cubes_land_where_they_are(tmp_path):
    """A PointInstancer (a red sphere and a green Y capsule prototype, per-instance colours) and a
    blue curve as a tube: each colour's pixels are centred on the projection of its shape."""
    path = str(tmp_path / "i.usda")
    with UsdCacheWriter(path, fps=10) as w:
        w.add_instancer("agents", [("sphere", {"radius": 0.15}), ("capsule", {"radius": 0.1, "height": 0.4,
                                                                              "axis": "Y"})],
                        count_changes=False, primvars={"displayColor": "color3f[]"})
        w.add_curves("line", curve_vertex_counts=[3], width=0.08, color=(0.0, 0.0, 1.0))
        w.write_frame(0, {"agents": {"positions": [[-0.6, 0.3, 0.0], [0.6, 0.3, 0.0]],
                                     "orientations": [[0, 0, 0, 1], [0, 0, 0, 1]], "protoIndices": [0, 1],
                                     "velocities": np.zeros((2, 3)), "displayColor": [[1, 0, 0], [0, 1, 0]]},
                          "line": {"points": [[-0.6, -0.4, 0.0], [0.0, -0.4, 0.0], [0.6, -0.4, 0.0]]}})
    cam = Camera((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), fov=40.0)
    out = str(tmp_path / "i.png")
    render_cache(path, out, size=(W, H), camera=cam, device="cpu")
    from PIL import Image

    img = np.asarray(Image.open(out)).astype(int)
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    masks = {"red": (r - g > 80) & (r - b > 80), "green": (g - r > 80) & (g - b > 80),
             "blue": (b - r > 80) & (b - g > 80)}
    centres = {"red": [-0.6, 0.3, 0.0], "green": [0.6, 0.3, 0.0], "blue": [0.0, -0.4, 0.0]}
    for name, mask in masks.items():
        rows, cols = np.nonzero(mask)
        cx, cy = cam.project([centres[name]], W, H)[0][0]
        assert mask.sum() > 50 and abs(cols.mean() - cx) < 2.5 and abs(rows.mean() - cy) < 2.5, name
    # the capsule stands along Y: taller than wide (0.6 m by 0.2 m); the tube lies along X
    rows, cols = np.nonzero(masks["green"])
    assert np.ptp(rows) > 2.2 * np.ptp(cols)
    rows, cols = np.nonzero(masks["blue"])
    assert np.ptp(cols) > 8 * np.ptp(rows)


def test_gallery_makes_a_small_preview(tmp_path):
    from PIL import Image

    from warpsim.render import gallery

    assert gallery.main(["--out", str(tmp_path), "--scenes", "bounce"]) == 0
    with Image.open(tmp_path / "bounce.gif") as im:
        assert im.size == gallery.SIZE and 2 <= im.n_frames <= gallery.MAX_FRAMES + 1


def test_smoke_cache_carries_its_density(tmp_path):
    """The smoke scene writes each smoky cell as a point sized and faded by its density (widths,
    per-point displayOpacity, a density primvar) with warpsim:cellSize; the renderer rebuilds
    the grid from it exactly (every written cell's density at its cell)."""
    from pxr import Usd, UsdGeom

    from warpsim.render.usd_scene import CacheScene
    from warpsim.scenes import get_scene

    scene = get_scene("smoke")({"resolution": 8}, device="cpu")
    path = str(tmp_path / "smoke.usda")
    with UsdCacheWriter(path, fps=24) as w:
        scene.declare(w)
        for f in range(4):
            if f:
                scene.advance(1 / 24, 1)
            w.write_frame(f, scene.frame_data())
    rho = scene.solver.density.numpy()
    stage = Usd.Stage.Open(path)
    prim = stage.GetPrimAtPath("/World/smoke")
    api = UsdGeom.PrimvarsAPI(prim)
    dens = np.asarray(api.GetPrimvar("density").Get(3))
    widths = np.asarray(UsdGeom.Points(prim).GetWidthsAttr().Get(3))
    opacity = np.asarray(api.GetPrimvar("displayOpacity").Get(3))
    assert api.GetPrimvar("displayOpacity").GetInterpolation() == "vertex"
    dx = prim.GetAttribute("warpsim:cellSize").Get()
    assert dx == pytest.approx(1 / 8) and len(dens) == (rho > scene.params["threshold"]).sum() > 0
    order = np.argsort(dens)
    assert np.all(np.diff(widths[order]) >= -1e-7) and np.all(np.diff(opacity[order]) >= -1e-7)  # grow with it
    assert widths.max() <= dx + 1e-6 and opacity.max() <= 0.8 + 1e-6 and opacity.min() >= 0
    vol = CacheScene(path).geometry(3).volume
    assert vol is not None and vol["dx"] == pytest.approx(dx)
    ijk = np.argwhere(rho > scene.params["threshold"])
    lo = ijk.min(0)
    np.testing.assert_allclose(vol["density"][tuple((ijk - lo).T)], rho[tuple(ijk.T)], rtol=1e-6)
    assert vol["density"].sum() == pytest.approx(rho[rho > scene.params["threshold"]].sum(), rel=1e-5)
    centre = np.asarray(vol["origin"]) + 0.5 * dx  # the rebuilt grid's first cell is the solver's cell lo
    np.testing.assert_allclose(centre, scene.grid.positions("center")[tuple(lo)], atol=1e-5)


@pytest.mark.parametrize("shape", [(1, 1), (96, 128), (7, 13)])
def test_png_encoder_round_trips_through_a_png_reader(shape):
    """warpsim.render.png writes a PNG that Pillow (an independent reader) decodes to the same
    pixels and size, CRCs checked; anything but (H, W, 3) uint8 is refused by name."""
    import io

    from PIL import Image

    from warpsim.render.png import encode_png

    rng = np.random.default_rng(3)
    rgb = rng.integers(0, 256, (*shape, 3), dtype=np.uint8)
    rgb[: shape[0] // 2] = (200, 210, 230)  # a flat sky above noise, as a picture has
    data = encode_png(rgb)
    with Image.open(io.BytesIO(data)) as img:
        img.load()
        assert img.mode == "RGB" and img.size == (shape[1], shape[0])
        assert np.array_equal(np.asarray(img), rgb)
    for bad in (rgb.astype(np.float32), rgb[..., :2], rgb[0], np.zeros((0, 4, 3), np.uint8)):
        with pytest.raises(ValueError, match="uint8 array"):
            encode_png(bad)


def test_render_many_draws_each_picture_as_render_does():
    """Renderer.render_many (one launch over several pictures, a sweep's thumbnails) gives each
    picture the bits Renderer.render gives it alone: pictures with different counts of opaque
    faces, glass faces and capsules (each picture's entries offset in the joined arrays), with and
    without a ground, an empty one; again in another order on the same renderer (its per-picture
    meshes and BVHs refitted to other geometry)."""
    from warpsim.render.geometry import cube_mesh

    def picture(k):
        g = GeometryBuilder()
        pts, counts, idx = cube_mesh(0.3 + 0.1 * k)
        if k % 3 != 1:
            g.add_mesh(pts + [0.2 * k, 0.15, 0.0], counts, idx, (0.9, 0.2 + 0.1 * k, 0.1))
        if k % 2 == 0:
            g.add_mesh(2.0 * pts + [0.0, 0.3, -0.6], counts, idx, (0.3, 0.5, 0.9), opacity=0.3)
        centres = np.array([[0.1 * i - 0.3, 0.5, 0.2] for i in range(k + 1)])
        g.add_capsules(centres, centres + [0.05, 0.1 * k, 0.0], 0.04, (0.2, 0.8, 0.3))
        return g.build()

    cam = Camera((0.4, 1.2, 2.5), (0.0, 0.3, 0.0), fov=45.0)
    items = [(picture(k), [None, 0.0, False][k % 3]) for k in range(5)] + [(GeometryBuilder().build(), None)]
    alone = [Renderer(64, 48, device="cpu").render(g, cam, ground_y=ground) for g, ground in items]
    many = Renderer(64, 48, device="cpu")
    for order in (list(range(len(items))), list(range(len(items)))[::-1]):
        pictures = many.render_many([items[k] for k in order], cam)
        for k, pic in zip(order, pictures):
            assert pic.dtype == np.uint8 and pic.shape == (48, 64, 3)
            assert np.array_equal(pic, alone[k]), k
    assert len({a.tobytes() for a in alone}) == len(alone)  # (the pictures differ: offsets matter)
    assert many.render_many([], cam) == []


def test_pictures_are_encoded_on_the_device_as_the_srgb_curve():
    """The renderer's 8-bit pictures are encoded by ``kernels.render.encode_srgb8`` on its device:
    within one code of the NumPy sRGB curve (``to_srgb8``) over a fine ramp of linear values, below 0
    and above 1 included (clamped), and ``render`` equals that curve applied to its linear picture."""
    import warp as wp

    from warpsim.kernels import render as K

    x = np.linspace(-0.1, 1.1, 200_001).astype(np.float32)
    linear = wp.array(np.repeat(x[:, None], 3, 1), dtype=wp.vec3, device="cpu")
    codes = wp.empty(3 * len(x), dtype=wp.uint8, device="cpu")
    wp.launch(K.encode_srgb8, len(x), inputs=[linear], outputs=[codes], device="cpu")
    got = codes.numpy().reshape(-1, 3).astype(int)
    want = to_srgb8(x).astype(int)
    assert (got == want[:, None]).all(axis=1).mean() > 0.999 and np.abs(got - want[:, None]).max() <= 1
    assert got[0].tolist() == [0, 0, 0] and got[-1].tolist() == [255, 255, 255]
    g = GeometryBuilder()
    g.add_spheres([[0.0, 0.0, 0.0]], 0.5, (0.8, 0.3, 0.1))
    r = Renderer(48, 36, device="cpu")
    cam = Camera((0.0, 0.5, 2.0), (0.0, 0.0, 0.0), fov=40.0)
    srgb = r.render(g.build(), cam).astype(int)
    assert np.abs(srgb - to_srgb8(r.render(g.build(), cam, linear=True))).max() <= 1


def test_capsule_boxes_are_numpys_float32_boxes():
    """The pictures' capsule BVH boxes, made on the device, carry the bits of NumPy's float32 min/max -/+ r."""
    import warp as wp

    from warpsim.kernels import render as K

    rng = np.random.default_rng(3)
    a, b = rng.normal(size=(2, 257, 3)).astype(np.float32)
    r = rng.uniform(0.001, 0.1, 257).astype(np.float32)
    lo, hi = wp.empty(257, dtype=wp.vec3, device="cpu"), wp.empty(257, dtype=wp.vec3, device="cpu")
    wp.launch(K.capsule_boxes, dim=257, inputs=[wp.array(a, dtype=wp.vec3, device="cpu"),
                                               wp.array(b, dtype=wp.vec3, device="cpu"),
                                               wp.array(r, dtype=float, device="cpu")], outputs=[lo, hi], device="cpu")
    assert lo.numpy().tobytes() == (np.minimum(a, b) - r[:, None]).tobytes()
    assert hi.numpy().tobytes() == (np.maximum(a, b) + r[:, None]).tobytes()


def test_pictures_share_one_upload_and_refit_in_place():
    """render_many's meshes and capsule BVHs are views of the pictures' joined buffers: a second call with as
    many pictures of the same topology refits them in place (no new mesh, no new BVH) and draws what a fresh
    renderer draws; a smaller last slice keeps its places (refitted too)."""
    def geom(shift):
        g = GeometryBuilder()
        g.add_mesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32) + shift,
                   [3, 3, 3, 3], [0, 2, 1, 0, 1, 3, 0, 3, 2, 1, 2, 3], (0.8, 0.3, 0.2))
        g.add_capsules([[shift, 0, 1]], [[shift + 1, 0, 1]], 0.05, (0.2, 0.2, 0.9))
        return g.build()

    cam = Camera(eye=(0.5, 1.5, 4.0), target=(0.5, 0.3, 0.0))
    r = Renderer(40, 30, device="cpu")
    r.render_many([(geom(0.0), None), (geom(0.1), None), (geom(0.2), None)], cam)
    made = {k: id(v[1] if isinstance(v, tuple) else v) for k, v in r._meshes.items()}
    second = [(geom(0.3), None), (geom(0.4), None)]
    pictures = r.render_many(second, cam)
    assert {k: id(v[1] if isinstance(v, tuple) else v) for k, v in r._meshes.items()} == made  # refitted, not rebuilt
    fresh = Renderer(40, 30, device="cpu").render_many(second, cam)
    assert all(np.array_equal(p, q) for p, q in zip(pictures, fresh))
