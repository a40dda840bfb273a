"""The viewer's first view frames the subject over its motion: a live scene's camera sees the
subject at its first frame and where it can go (its see-through container, down to the floor), and
cache playback's camera sees the subject in every frame while the motion fills the view (not a
speck). Checked geometrically: every point lies inside the camera's view cone."""

import io

import numpy as np
import pytest

from warpsim import cli
from warpsim.scenes import get_scene
from warpsim.viewer.framing import camera_pose, live_bounds, playback_bounds, robust_bounds
from warpsim.viewer.playback import CacheReader
from warpsim.viewer.session import Session

FOV = 50.0


def inside_view(points, position, look_at, fov=FOV):
    """Whether every point lies within the camera's cone of half-angle fov / 2."""
    axis = (look_at - position) / np.linalg.norm(look_at - position)
    rays = np.asarray(points, np.float64).reshape(-1, 3) - position
    cos = rays @ axis / np.linalg.norm(rays, axis=1)
    return bool(np.all(cos >= np.cos(np.radians(0.5 * fov))))


def test_robust_bounds_ignore_outliers():
    rng = np.random.default_rng(0)
    cloud = rng.uniform(-1.0, 1.0, (2000, 3))
    far = np.vstack([cloud, [[60.0, 0.0, 0.0]] * 5])  # debris flung far away
    b = robust_bounds([far])
    assert b[1][0] < 1.2 and b[0][0] > -1.2


def test_live_teapot_view_holds_the_teapot_and_its_box():
    cls = get_scene("teapot")
    s = Session(cls, {"resolution": 3, "springs": False}, device="cpu")
    position, look_at = camera_pose(live_bounds(s.items, s.static))
    teapot = s.items["teapot"].points
    walls = s.static["walls"].points
    assert inside_view(teapot, position, look_at)
    assert inside_view(walls, position, look_at)  # the whole box, floor corners included: where it falls
    # the teapot is not a speck: its size over the camera distance
    size = np.linalg.norm(np.ptp(teapot, axis=0))
    assert size / np.linalg.norm(look_at - position) > 0.15
    s.close()


def test_playback_bounce_frames_the_ball_over_its_motion(tmp_path):
    cache = tmp_path / "b.usda"
    code = cli.main(["run", "bounce", "--frames", "30", "--out", str(cache), "--device", "cpu", "--no-progress",
                     "--set", "height=0.12", "--set", "dt=0.02", "--set", "restitution=0.8"],
                    io.StringIO(), io.StringIO())
    assert code == 0
    reader = CacheReader(str(cache))
    position, look_at = camera_pose(playback_bounds(reader))
    balls = np.concatenate([item.points.reshape(-1, 3) for k in range(len(reader))
                            for item in reader.items(k).values()])
    assert inside_view(balls, position, look_at)
    travel = np.ptp(balls[:, 1])
    assert travel > 0.05
    assert travel / np.linalg.norm(look_at - position) > 0.2  # the bounce fills the view, not a speck
    floor = reader.static["floor"].points  # 0.6 m wide: the old framing of everything drawn
    assert np.ptp(floor[:, 0]) / np.linalg.norm(look_at - position) > 0.5


@pytest.mark.parametrize("scene", ["bounce", "cloth"])
def test_live_view_reaches_the_floor(scene):
    cls = get_scene(scene)
    s = Session(cls, cls.smoke_params, device="cpu")
    b = live_bounds(s.items, s.static)
    assert b[0][1] == pytest.approx(0.0, abs=1e-6)  # extended down to the floor the subject falls onto
    position, look_at = camera_pose(b)
    for item in s.items.values():
        assert inside_view(item.points, position, look_at)
    s.close()
