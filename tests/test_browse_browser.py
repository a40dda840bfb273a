"""Browsing a sweep by where things go, in a real browser (Debian's Chromium, headless, driven by
Playwright; WebGL through SwiftShader): ``warpsim view`` on a sweep root with an occupancy record
shows the query box; dragging the box's corner gizmo with the mouse moves the box, and on release
the listed worlds change to those the record says are inside it (the same as
:func:`warpsim.browse.query.answer_region`), each listed world a button that plays it alone.
Without a browser: the panel ranks by first entry or time inside, NOT IN gives the complement,
and "show matches only" hides the rest."""
from __future__ import annotations

import argparse
import io
import os

import numpy as np
import playwright.sync_api as playwright  # the test extra installs it; CI must run this test, never skip it
import pytest
from browser_page import ARGS, CHROMIUM, HEIGHT, LONG, WIDTH, dismiss_notice, wait_still
from browser_page import free_port as _free_port, project as _project, wait as _wait

from warpsim.cli import main
from warpsim.viewer.command import add_parser, build
from warpsim.browse.gallery import GalleryViewer
from warpsim.browse.query import answer_region

HEIGHTS = "0.2:1.0"


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    path = tmp_path_factory.mktemp("browse") / "drop.usda"
    code = main(["sweep", "bounce", "--worlds", "9", "--vary", f"height={HEIGHTS}", "--set", "restitution=0",
                 "--set", "display_radius=0.03", "--fps", "50", "--substeps", "10", "--frames", "40",
                 "--no-progress", "--device", "cpu", "--out", str(path)], out=io.StringIO(), err=io.StringIO())
    assert code == 0
    return path


def test_the_sweep_draws_every_world_s_picture_as_the_gallery_would(root, tmp_path):
    from PIL import Image

    from warpsim.browse.panel import thumbnail, thumbnail_camera, thumbnails_folder
    from warpsim.browse.occupancy import OccupancyRecord, occupancy_path

    folder = thumbnails_folder(root)
    made = {name: np.asarray(Image.open(f"{folder}/{name}")) for name in sorted(os.listdir(folder))}
    assert sorted(made) == [f"world_{w:06d}.png" for w in range(9)]
    assert all(m.shape == (96, 128, 3) and m.std() > 5 for m in made.values())  # the ball and floor are drawn
    # the picture the gallery draws on first show, for a root whose sweep drew none
    copy = tmp_path / "drop.usda"
    copy.write_text(root.read_text().replace("@./", f"@{root.parent}/"))
    record = OccupancyRecord.load(occupancy_path(root))
    for w in (0, 8):
        drawn = np.asarray(Image.open(thumbnail(copy, w, camera=thumbnail_camera(record), device="cpu")))
        assert np.array_equal(drawn, made[f"world_{w:06d}.png"])
    code = main(["sweep", "bounce", "--worlds", "2", "--frames", "3", "--no-progress", "--device", "cpu",
                 "--out", str(tmp_path / "off.usda"), "--no-thumbnails"], out=io.StringIO(), err=io.StringIO())
    assert code == 0 and not os.path.exists(thumbnails_folder(tmp_path / "off.usda"))


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
            page.wait_for_selector("canvas", timeout=LONG)
            page.get_by_text(f"{len(before)} of 9 worlds", exact=False).first.wait_for(timeout=LONG)
            client = _wait(lambda: next(iter(viewer.server.get_clients().values()), None), what="the client")
            viewer.playing = False
            # the first framing: world 0, where the box is drawn: both corners and their gizmos' arrows
            # are on screen, each arrow at least 4 % of the view's height long
            _wait(lambda: np.allclose(client.camera.look_at, viewer.server.initial_camera.look_at, atol=1e-4),
                  what="the first framing")
            for gizmo in (query.gizmo_lo, query.gizmo_hi):
                at = np.asarray(gizmo.position, float)
                (x0, y0), (x1, y1) = (_project(client.camera, at + np.array([0.0, k * query.gizmo_scale, 0.0]))
                                      for k in (0.0, 1.0))
                assert 0 < x0 < WIDTH and 0 < y0 < HEIGHT and 0 < y1 < HEIGHT
                assert np.hypot(x1 - x0, y1 - y0) > 0.04 * HEIGHT, (x0, y0, x1, y1)
            corner = np.asarray(query.gizmo_hi.position, float)
            client.camera.position = tuple(corner + np.array([0.0, 0.0, 1.6]))
            client.camera.look_at = tuple(corner)
            _wait(lambda: np.allclose(client.camera.look_at, corner, atol=1e-3), what="the camera")
            dismiss_notice(page)  # viser's "software WebGL" notice
            wait_still(page)  # the page has drawn the moved camera
            # the gizmo's y arrow: press on it, drag upward, release
            scale = query.gizmo_scale
            x0, y0 = _project(client.camera, corner + np.array([0.0, 0.7 * scale, 0.0]))
            x1, y1 = _project(client.camera, corner + np.array([0.0, 0.7 * scale + 0.5, 0.0]))
            assert 0 < x0 < WIDTH and 0 < y1 < y0 < HEIGHT
            page.mouse.move(x0, y0)
            page.mouse.down()
            page.mouse.move(x1, y1, steps=20)
            page.mouse.up()
            _wait(lambda: query.matches != before, timeout=30, what="the released gizmo to change the list")
            after = list(query.matches)
            assert query.hi[1] > 0.3 and set(before) < set(after)  # the box grew upward: more balls pass
            assert after == [int(w) for w in np.flatnonzero(answer_region(query.record, query.region()).match)]
            assert query.answer_seconds < 1.0
            page.get_by_text(f"{len(after)} of 9 worlds", exact=False).first.wait_for(timeout=LONG)
            # a listed world's button plays it alone, framed, and the play button says "Pause"
            page.get_by_role("button", name="Play", exact=True).wait_for(timeout=LONG)
            page.get_by_role("button", name=f"#1 world {after[0]}", exact=False).first.click()
            world = f"world_{after[0]:06d}"
            _wait(lambda: viewer.isolated == world, timeout=30, what="the click to play a world")
            page.get_by_role("button", name="Pause", exact=True).wait_for(timeout=LONG)
            lo, hi = viewer.reader.world_bounds(world)
            _wait(lambda: np.allclose(client.camera.look_at, 0.5 * (lo + hi), atol=1e-3), what="the world's framing")
            for corner in (lo, hi):
                x, y = _project(client.camera, corner)
                assert 0 < x < WIDTH and 0 < y < HEIGHT
            page.get_by_role("button", name="Pause", exact=True).click()  # pressing it pauses, as it says
            _wait(lambda: not viewer.playing, timeout=30, what="the pause")
            page.get_by_role("button", name="Play", exact=True).wait_for(timeout=LONG)
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
        buttons = [slot["button"] for slot in query._slots]
        # paused first: the playback loop refreshes the worlds' visibility with every frame it draws
        # (counted here, it failed the check below on a loaded machine); its last frame drawn and shown
        viewer.playing = False
        _wait(lambda: viewer._shown == viewer.index, what="the paused frame drawn")
        with viewer._lock:  # (GalleryViewer.show draws and refreshes under this lock)
            pass
        refreshed = []
        refresh = viewer._refresh
        viewer._refresh = lambda *a, **k: (refreshed.append(1), refresh(*a, **k))
        query.rank.value = "time inside"
        assert query.matches == sorted(inside, key=lambda w: (-answer.time[w], w))
        # re-ranking sends no world's visibility and keeps the list's buttons, relabelled in place
        assert not refreshed and [slot["button"] for slot in query._slots] == buttons
        assert [slot["button"].label.split(":")[0] for slot in query._slots] == \
            [f"#{k + 1} world {w}" for k, w in enumerate(query.matches)]
        viewer._refresh = refresh
        assert query.hidden == {f"world_{w:06d}" for w in range(1, 9) if w not in inside}  # world 0 holds the box
        query.mode.value = "NOT IN"
        assert sorted(query.matches) == [w for w in range(9) if w not in inside]
        query.matches_only.value = False
        assert query.hidden == set()
        viewer.playing = False
        viewer.index = 30
        assert viewer.play.label == "Play"
        query.play(query.matches[0])
        # from frame 0 (the playback thread may have advanced a frame or two since)
        assert viewer.isolated == f"world_{query.matches[0]:06d}" and viewer.playing and viewer.index < 10
        assert viewer.play.label == "Pause"
    finally:
        viewer.stop()


MANY = 1000


@pytest.fixture(scope="module")
def many(tmp_path_factory):
    """A sweep of MANY bouncing balls, few frames (the gallery's cost is its world count)."""
    path = tmp_path_factory.mktemp("many") / "drop.usda"
    code = main(["sweep", "bounce", "--worlds", str(MANY), "--vary", "height=0.2:1.0", "--vary", "restitution=0:0.9",
                 "--sample", "lhs", "--set", "display_radius=0.03", "--fps", "10", "--substeps", "20", "--frames", "4",
                 "--no-progress", "--no-thumbnails", "--device", "cpu", "--out", str(path)],
                out=io.StringIO(), err=io.StringIO())
    assert code == 0
    return path


def _choose(page, label, option):
    """Open the drop-down ``label`` in the page and return the locator of its ``option``."""
    page.get_by_label(label, exact=True).first.click()
    choice = page.get_by_role("option", name=option, exact=True)
    choice.wait_for(timeout=LONG)
    return choice


def test_the_answer_shows_within_a_second_of_a_control_change_at_many_worlds(many):
    """In Chromium, with MANY worlds in the page (paused, as while browsing): from the click on a
    drop-down's option to the new answer in the page (the ranked list, the summary) takes under a
    second, for a re-rank and for IN -> NOT IN (which also shows and hides most worlds)."""
    import time

    viewer = GalleryViewer(str(many), port=_free_port(), thumbnails=False).start()
    try:
        viewer.playing = False
        query = viewer.query
        for y0 in np.linspace(0.1, 0.8, 8):  # a box whose first world differs by the two rankings
            query.set_box((-0.1, y0, -0.1), (0.1, y0 + 0.2, 0.1))
            answer = answer_region(query.record, query.region())
            inside = np.flatnonzero(answer.match)
            longest = max(inside, key=lambda w: (answer.time[w], -w)) if len(inside) else None
            if 0 < len(inside) < MANY and longest != query.matches[0]:
                break
        assert 0 < len(inside) < MANY and longest != query.matches[0]  # ranked by first entry now
        query.settle()
        with playwright.sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
            page = browser.new_page(viewport={"width": WIDTH, "height": HEIGHT})
            page.goto(viewer.url)
            page.wait_for_selector("canvas", timeout=2 * LONG)
            page.get_by_text(f"{len(inside)} of {MANY} worlds", exact=False).first.wait_for(timeout=2 * LONG)
            wait_still(page, timeout=120)  # the first frame of every world drawn
            option = _choose(page, "rank by", "time inside")
            start = time.perf_counter()
            option.click()
            page.get_by_role("button", name=f"#1 world {longest}:", exact=False).first.wait_for(timeout=LONG)
            rerank = time.perf_counter() - start
            option = _choose(page, "mode", "NOT IN")
            start = time.perf_counter()
            option.click()
            page.get_by_text("NOT IN the box", exact=False).first.wait_for(timeout=LONG)
            negate = time.perf_counter() - start
            browser.close()
        assert rerank < 1.0 and negate < 1.0, (rerank, negate)
        assert query.matches and len(query.matches) == MANY - len(inside)
        query.settle()
        assert query.hidden == {f"world_{w:06d}" for w in inside if w != 0}
    finally:
        viewer.stop()
