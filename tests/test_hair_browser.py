"""Hair in a real browser at the default strand count (2,000 strands x 16 segments, 32,000 free
vertices: far more than the viewer draws as clickable spheres): a mouse drag on the drawn curves
grabs the strand vertex nearest the pointer's ray and pulls it toward the pointer (Debian's
Chromium, headless, driven by Playwright as in ``test_viewer_browser``; sag-free off to keep the
start-up short: it does not change what is drawn or picked)."""
from __future__ import annotations

import numpy as np
import pytest

from browser_page import HEIGHT, LONG, WIDTH, dismiss_notice
from browser_page import free_port as _free_port, project as _project, wait as _wait
from test_viewer_browser import browser  # noqa: F401  (fixture)
from warpsim.scenes import get_scene
from warpsim.viewer.server import PICKABLE_POINTS, Viewer


@pytest.fixture(scope="module")
def viewer():
    v = Viewer("hair", params={"sag_free": False, "motion": "still"}, device="cpu", port=_free_port(), draw_fps=4.0).start()
    yield v
    v.stop()


def test_hair_is_draggable_at_the_default_strand_count(viewer, browser):  # noqa: F811
    s = viewer.session
    hair = s.scene.hair
    assert hair.strand_count == get_scene("hair").params["strands"].default
    assert len(s.scene.drag_map()["hair_vertices"]) > PICKABLE_POINTS  # no clickable spheres for these
    page = browser.new_page(viewport={"width": WIDTH, "height": HEIGHT})
    page.goto(viewer.url)
    page.wait_for_selector("canvas", timeout=LONG)
    page.get_by_text("friction (live)").wait_for(timeout=2 * LONG)
    client = _wait(lambda: next(iter(viewer.server.get_clients().values()), None), what="the client")
    # every strand drawn and clickable, however far the page lags (the pick below is chosen among all
    # strands; thinning while a page lags has its own test, test_viewer_pace)
    viewer.pace.stop()
    _wait(lambda: s.frame > 1, timeout=60.0, what="the simulation to run")
    dismiss_notice(page)
    cam = client.camera
    with s.lock:
        ends = s.items["hair"].points.reshape(-1, 3).copy()
    particles = np.asarray(s.drag_map["hair"])
    free = (particles - hair.first) % hair.stride >= 3  # away from the pinned root
    eye = np.asarray(cam.position, float)
    dist = np.where(free, np.linalg.norm(ends - eye, axis=1), np.inf)
    for front in np.argsort(dist)[:200]:  # nearest the camera (no strand in front of it), off the GUI panel
        sx, sy = _project(cam, ends[front])
        if 20 < sx < 640 and 20 < sy < HEIGHT - 20:
            break
    page.mouse.move(sx, sy)
    page.mouse.down()
    page.mouse.move(sx, sy - 80, steps=4)
    grabbed = _wait(lambda: s.status()["grabbed"], timeout=30.0, what="the grab")
    assert grabbed["prim"] == "hair"
    strand, local = hair.strand_of(grabbed["particle"])
    assert local >= 2  # a free strand vertex
    gx, gy = _project(cam, grabbed["start"])
    assert abs(gx - sx) < 15 and abs(gy - sy) < 15  # the vertex under the pointer
    def under_pointer():  # the pointer moves in 4 steps, each an update: wait for the last (CI read the first)
        tx, ty = _project(cam, s.status()["grabbed"]["target"])
        return abs(tx - sx) < 12 and abs(ty - (sy - 80)) < 12

    _wait(under_pointer, timeout=30.0, what="the target to lie under the pointer")  # within 12 px of it
    target = s.status()["grabbed"]["target"]
    assert np.linalg.norm(target - grabbed["start"]) > 0.03  # the target moved with the pointer
    start = grabbed["start"]
    _wait(lambda: np.linalg.norm(s.grabbed_position() - target) < 0.6 * np.linalg.norm(start - target),
          timeout=60.0, what="the strand vertex to follow the pointer")
    page.mouse.up()
    _wait(lambda: s.status()["grabbed"] is None, what="the release")
    page.close()
