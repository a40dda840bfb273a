"""The gallery's query box as a person meets it, in Chromium (``warpsim view SWEEP.usda`` on a
4-teapot sweep, whose worlds stand in see-through walls, and on a 1,000-ball sweep):

- at first view the box (its edges) and both corner gizmos are drawn, framed on world 0: hiding
  each node changes the screenshot where it projects (the walls' near face once hid them all);
- dragging a gizmo's arrow with the mouse moves the box and the page's answer ("N of M worlds IN
  the box") changes to the record's answer for the new box;
- choosing a world in the menu and going back to ``all worlds`` frames the whole gallery again
  (not empty white: the client's camera had kept its orientation and looked past every world);
- clicking a world isolates it: the other worlds' nodes are hidden and the box follows it.
"""
from __future__ import annotations

import io

import numpy as np
import playwright.sync_api as playwright  # the test extra installs it; CI must run this test, never skip it
import pytest
from browser_page import (ARGS, CHROMIUM, HEIGHT, PATIENCE, VIEW_RIGHT, WIDTH, dismiss_notice,
                          drawn_where_projected, free_port, pixel_box, pixels, project, wait, wait_still)

from warpsim.browse.gallery import ALL, GalleryViewer
from warpsim.browse.query import Region, answer_region
from warpsim.cli import main


def _sweep(folder, *args):
    path = folder / "sweep.usda"
    code = main(["sweep", *args, "--no-progress", "--no-thumbnails", "--device", "cpu", "--out", str(path)],
                out=io.StringIO(), err=io.StringIO())
    assert code == 0
    return path


@pytest.fixture(scope="module")
def teapots(tmp_path_factory):
    return _sweep(tmp_path_factory.mktemp("teapots"), "teapot", "--worlds", "4", "--vary", "height=0.1:0.9",
                  "--frames", "21")


@pytest.fixture(scope="module")
def balls(tmp_path_factory):
    return _sweep(tmp_path_factory.mktemp("balls"), "bounce", "--worlds", "1000", "--vary", "height=0.2:1.0",
                  "--vary", "restitution=0:0.9", "--sample", "lhs", "--set", "display_radius=0.03", "--fps", "10",
                  "--substeps", "20", "--frames", "4")


def _count(query, lo, hi):
    """Worlds the record puts IN the box lo..hi [m] during the panel's window."""
    lo, hi = np.minimum(lo, hi), np.maximum(lo, hi)
    t0, t1 = (float(v) for v in query.window.value)
    region = Region(True, tuple(lo), tuple(hi), t0, t1, "drag")
    return int(answer_region(query.record, region, query.positions).match.sum())


def _drag_that_changes(query):
    """(gizmo, metres along +y) of a drag of one gizmo's y arrow after which the record's answer
    differs from now, the same for a drag 0.05 m shorter or longer (the mouse lands near, not on,
    the asked point)."""
    now = _count(query, query.lo, query.hi)
    extent = float(np.ptp(np.asarray(query.record.occupied_bounds()), axis=0).max())
    for d in extent * np.array([0.3, -0.3, 0.2, -0.2, 0.4, -0.4, 0.15, -0.15]):
        for gizmo, corner in ((query.gizmo_hi, "hi"), (query.gizmo_lo, "lo")):
            counts = set()
            for dd in (d - 0.05, d, d + 0.05):
                lo, hi = query.lo.copy(), query.hi.copy()
                (hi if corner == "hi" else lo)[1] += dd
                counts.add(_count(query, lo, hi))
            if len(counts) == 1 and now not in counts:
                return gizmo, float(d)
    raise AssertionError("no drag of a gizmo's y arrow changes this sweep's answer")


def _summary(query):
    return f"{len(query.matches)} of {query.record.world_count} worlds"


@pytest.mark.parametrize("sweep", ["teapots", "balls"])
def test_the_box_is_drawn_dragged_and_a_world_clicked(sweep, request, tmp_path):
    root = request.getfixturevalue(sweep)
    viewer = GalleryViewer(str(root), port=free_port(), thumbnails=False).start()
    try:
        viewer.playing = False  # the scene holds still while screenshots are compared
        query = viewer.query
        worlds = query.record.world_count
        with playwright.sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
            page = browser.new_page(viewport={"width": WIDTH, "height": HEIGHT})
            page.goto(viewer.url)
            page.wait_for_selector("canvas", timeout=120_000 * PATIENCE)
            page.get_by_text(_summary(query), exact=False).first.wait_for(timeout=120_000 * PATIENCE)
            client = wait(lambda: next(iter(viewer.server.get_clients().values()), None), what="the client")
            first = viewer.server.initial_camera
            wait(lambda: np.allclose(client.camera.look_at, first.look_at, atol=1e-4)
                 and np.allclose(client.camera.position, first.position, atol=1e-4), 60,
                 lambda: f"the first framing (the client at {client.camera.position} looking at "
                         f"{client.camera.look_at}; asked {first.position}, {first.look_at})")
            dismiss_notice(page)
            cam = client.camera

            # 1. first view, framed on world 0: the box's edges and both gizmos are drawn where they project
            assert np.allclose(query.origin, viewer.reader.offsets[viewer.reader.worlds[0]])
            corners = np.array([query.origin + query.lo, query.origin + query.hi])
            nodes = [(query.edges, np.array([[a[0], b[1], c[2]] for a in corners for b in corners for c in corners]))]
            for gizmo in (query.gizmo_lo, query.gizmo_hi):
                at = np.asarray(gizmo.position, float)
                nodes.append((gizmo, np.vstack([at, at + query.gizmo_scale * np.eye(3)])))
            for handle, points in nodes:
                box = pixel_box(cam, points)
                assert box is not None and box[2] - box[0] > 8, (handle.name, box)  # on screen, not a speck
                assert drawn_where_projected(page, handle, box), handle.name
            page.screenshot(path=str(tmp_path / "first_view.png"))

            # 2. dragging a gizmo's y arrow with the mouse moves the box; the answer follows on release
            before, shown_before = (query.lo.copy(), query.hi.copy()), _summary(query)
            gizmo, d = _drag_that_changes(query)
            at = np.asarray(gizmo.position, float)
            grip = at + np.array([0.0, 0.75 * query.gizmo_scale, 0.0])
            (x0, y0), (x1, y1) = project(cam, grip), project(cam, grip + np.array([0.0, d, 0.0]))
            assert 0 < x0 < VIEW_RIGHT and 0 < y0 < HEIGHT and 0 < y1 < HEIGHT, (x0, y0, x1, y1)
            page.mouse.move(x0, y0)
            page.mouse.down()
            page.mouse.move(x1, y1, steps=25)
            page.mouse.up()
            wait(lambda: not (np.allclose(query.lo, before[0]) and np.allclose(query.hi, before[1])), 60,
                 "the released gizmo to move the box")
            assert abs(np.asarray(gizmo.position, float)[1] - (at[1] + d)) < 0.25 * abs(d)  # where it was dragged
            # the answer follows on release, after the box has moved (a loaded CI machine read it between)
            wait(lambda: _summary(query) != shown_before, 60, "the answer to follow the released box")
            page.get_by_text(_summary(query), exact=False).first.wait_for(timeout=30_000 * PATIENCE)
            assert len(query.matches) == _count(query, query.lo, query.hi)

            # 3. a world from the menu, then all worlds again: the whole gallery framed, not empty
            def choose(option):
                page.get_by_label("world", exact=True).first.click()
                page.get_by_role("option", name=option, exact=True).click(timeout=30_000 * PATIENCE)

            shown = [w for w in viewer.reader.worlds if w not in query.hidden]
            other = next(w for w in reversed(shown) if w != viewer.reader.worlds[0])
            choose(other)
            pose = viewer.world_pose(other)
            wait(lambda: np.allclose(client.camera.look_at, pose[1], atol=1e-3), 60, "the menu's world framed")
            choose(ALL)
            wait(lambda: viewer.isolated is None, 60, "all worlds")
            wait(lambda: np.allclose(client.camera.look_at, viewer.gallery_pose[1], atol=1e-3)
                 and np.allclose(client.camera.position, viewer.gallery_pose[0], atol=1e-3), 60,
                 "the gallery framed again")
            view = wait(lambda: (lambda img: img if img[:, :VIEW_RIGHT].std() > 8 else None)(pixels(page)), 60,
                        "the gallery drawn (not empty white)")
            assert view[:, :VIEW_RIGHT].std() > 8

            # 4. a click on a shown world isolates it: every other world's nodes hidden, the box in its frame
            lo, hi = viewer.reader.world_bounds(other)
            x, y = project(client.camera, 0.5 * (lo + hi))
            assert 0 < x < VIEW_RIGHT and 0 < y < HEIGHT
            page.mouse.click(x, y)
            wait(lambda: viewer.isolated == other and np.allclose(query.origin, viewer.reader.offsets[other])
                 and {w for w, h, _ in viewer.drawn_nodes() if h.visible} == {other}, 60,
                 lambda: f"the click to isolate {other} (isolated: {viewer.isolated}, the box in the frame at "
                         f"{query.origin})")
            pose = viewer.world_pose(other)
            wait(lambda: np.allclose(client.camera.look_at, pose[1], atol=1e-3), 60, "the clicked world framed")
            wait_still(page)
            page.screenshot(path=str(tmp_path / "isolated.png"))  # for a person to look at
            browser.close()
        assert worlds == len(viewer.reader.worlds)
    finally:
        viewer.stop()
