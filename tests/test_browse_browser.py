"""Browsing a sweep by where things go, in a real browser (Debian's Chromium, headless, driven by
Playwright; WebGL through SwiftShader): ``warpsim view`` on a sweep root with an occupancy record
shows the query box; dragging the box's corner gizmo with the mouse moves the box, and on release
the listed worlds change to those the record says are inside it (the same as
:func:`warpsim.worlds.query.answer_region`), each listed world a button that plays it alone.
Without a browser: the panel ranks by first entry or time inside, NOT IN gives the complement,
and "show matches only" hides the rest."""
from __future__ import annotations

import argparse
import io

import numpy as np
import playwright.sync_api as playwright  # the test extra installs it; CI must run this test, never skip it
import pytest
from test_viewer_browser import ARGS, CHROMIUM, HEIGHT, WIDTH, _free_port, _project, _wait

from warpsim.cli import main
from warpsim.viewer.command import add_parser, build
from warpsim.worlds.gallery import GalleryViewer
from warpsim.worlds.query import answer_region

HEIGHTS = "0.2:1.0"


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    path = tmp_path_factory.mktemp("browse") / "drop.usda"
    code = main(["sweep", "bounce", "--worlds", "9", "--vary", f"height={HEIGHTS}", "--set", "restitution=0",
                 "--set", "display_radius=0.03", "--fps", "50", "--substeps", "10", "--frames", "40",
                 "--no-progress", "--device", "cpu", "--out", str(path)], out=io.StringIO(), err=io.StringIO())
    assert code == 0
    return path


def test_dragging_the_box_changes_the_list(root):
    sub = argparse.ArgumentParser().add_subparsers()
    add_parser(sub)
    viewer = build(sub.choices["view"].parse_args([str(root), "--port", str(_free_port())]))
    assert isinstance(viewer, GalleryViewer)
    viewer.start()
    try:
        query = viewer.query
        assert query is not None
        query.thumbnails = False  # pictures are rendered in a thread; not what this test looks at
        query.rank.value = "world"
        # a thin slab low down: during the whole run every ball passes through it
        query.set_box((-0.1, 0.05, -0.1), (0.1, 0.15, 0.1))
        query.window.value = (0.1, 0.3)  # early: only the lowest balls have reached the slab
        before = list(query.matches)
        assert before == [int(w) for w in np.flatnonzero(answer_region(query.record, query.region()).match)]
        with playwright.sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
            page = browser.new_page(viewport={"width": WIDTH, "height": HEIGHT})
            page.goto(viewer.url)
            page.wait_for_selector("canvas", timeout=30_000)
            page.get_by_text(f"{len(before)} of 9 worlds", exact=False).first.wait_for(timeout=30_000)
            client = _wait(lambda: next(iter(viewer.server.get_clients().values()), None), what="the client")
            viewer.playing = False
            corner = np.asarray(query.gizmo_hi.position, float)
            client.camera.position = tuple(corner + np.array([0.0, 0.0, 1.6]))
            client.camera.look_at = tuple(corner)
            _wait(lambda: np.allclose(client.camera.look_at, corner, atol=1e-3), what="the camera")
            close = page.locator(".mantine-Notification-closeButton")  # viser's "software WebGL" notice
            if close.count():
                close.first.click()
            page.wait_for_timeout(1500)
            # the gizmo's y arrow: press on it, drag upward, release
            scale = query.gizmo_scale
            x0, y0 = _project(client.camera, corner + np.array([0.0, 0.7 * scale, 0.0]))
            x1, y1 = _project(client.camera, corner + np.array([0.0, 0.7 * scale + 0.5, 0.0]))
            assert 0 < x0 < WIDTH and 0 < y1 < y0 < HEIGHT
            page.mouse.move(x0, y0)
            page.mouse.down()
            for k in range(1, 21):
                page.mouse.move(x0 + (x1 - x0) * k / 20, y0 + (y1 - y0) * k / 20)
                page.wait_for_timeout(30)
            page.mouse.up()
            _wait(lambda: query.matches != before, timeout=30, what="the released gizmo to change the list")
            after = list(query.matches)
            assert query.hi[1] > 0.3 and set(before) < set(after)  # the box grew upward: more balls pass
            assert after == [int(w) for w in np.flatnonzero(answer_region(query.record, query.region()).match)]
            assert query.answer_seconds < 1.0
            page.get_by_text(f"{len(after)} of 9 worlds", exact=False).first.wait_for(timeout=30_000)
            # a listed world's button plays it alone
            page.get_by_role("button", name=f"#1 world {after[0]}", exact=False).first.click()
            _wait(lambda: viewer.isolated == f"world_{after[0]:06d}", timeout=30, what="the click to play a world")
            browser.close()
    finally:
        viewer.stop()


def test_panel_ranks_negates_and_hides(root):
    viewer = GalleryViewer(str(root), port=_free_port(), thumbnails=False).start()
    try:
        query = viewer.query
        query.window.value = (0.1, 0.5)
        query.set_box((-0.1, 0.3, -0.1), (0.1, 0.6, 0.1))
        answer = answer_region(query.record, query.region())
        inside = [int(w) for w in np.flatnonzero(answer.match)]
        assert 0 < len(inside) < 9
        assert query.matches == sorted(inside, key=lambda w: (answer.entry[w], w))  # first entry first
        query.rank.value = "time inside"
        assert query.matches == sorted(inside, key=lambda w: (-answer.time[w], w))
        assert query.hidden == {f"world_{w:06d}" for w in range(1, 9) if w not in inside}  # world 0 holds the box
        query.mode.value = "NOT IN"
        assert sorted(query.matches) == [w for w in range(9) if w not in inside]
        query.matches_only.value = False
        assert query.hidden == set()
        query.play(query.matches[0])
        assert viewer.isolated == f"world_{query.matches[0]:06d}" and viewer.playing and viewer.index == 0
    finally:
        viewer.stop()
