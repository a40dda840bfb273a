"""The sweep gallery in a real browser (Debian's Chromium, headless, driven by Playwright; WebGL
through SwiftShader): ``warpsim view`` on a sweep root shows every world side by side; a mouse
click on one world's teapot isolates it (the other worlds' nodes are hidden) and frames the camera
on it, a second click shows them all again, framed as at first; the reader places each world's
samples at its grid offset."""
from __future__ import annotations

import numpy as np
import playwright.sync_api as playwright  # the test extra installs it; CI must run this test, never skip it
import pytest
from browser_page import ARGS, CHROMIUM, HEIGHT, LONG, WIDTH, dismiss_notice, wait_still
from browser_page import free_port as _free_port, project as _project, wait as _wait

from warpsim.viewer.command import add_parser
from warpsim.sweeps import run_batch, sample_worlds, write_sweep_root
from warpsim.browse.gallery import GalleryReader, GalleryViewer, is_sweep_root


@pytest.fixture(scope="module")
def sweep(tmp_path_factory):
    folder = tmp_path_factory.mktemp("gallery")
    worlds = sample_worlds("teapot", {"resolution": "3"}, ["stiffness=20:60"], 4)
    run_batch("teapot", worlds, frames=6, device="cpu", layer_path=folder / "b.usdc")
    return write_sweep_root(folder / "sweep.usda", [folder / "b.usdc"], 4), folder / "b.usdc"


def test_reader_places_each_world_on_the_grid(sweep):
    root, layer = sweep
    assert is_sweep_root(root) and not is_sweep_root(layer)
    reader = GalleryReader(root)
    assert reader.worlds == [f"world_{g:06d}" for g in range(4)]
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(layer))
    items = reader.items(len(reader) - 1)
    spacing = None
    for g, world in enumerate(reader.worlds):
        own = np.array(UsdGeom.Mesh(stage.GetPrimAtPath(f"/Worlds/{world}/teapot")).GetPointsAttr().Get(6))
        offset = items[f"{world}/teapot"].points - own
        assert np.allclose(offset, offset[0], atol=1e-5)  # a pure translation of the world's own samples
        spacing = spacing or max(abs(offset[0][0]), abs(offset[0][2]))
        assert np.allclose(offset[0], [(g % 2) * spacing, 0.0, (g // 2) * spacing], atol=1e-5)
    assert f"{reader.worlds[3]}/walls" in reader.static


def test_click_isolates_a_world_in_the_browser(sweep):
    import argparse

    root, _ = sweep
    sub = argparse.ArgumentParser().add_subparsers()
    add_parser(sub)  # warpsim view picks the gallery for a sweep root
    from warpsim.viewer.command import build

    args = sub.choices["view"].parse_args([str(root), "--port", str(_free_port())])
    viewer = build(args)
    assert isinstance(viewer, GalleryViewer)
    viewer.start()
    try:
        with playwright.sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
            page = browser.new_page(viewport={"width": WIDTH, "height": HEIGHT})
            page.goto(viewer.url)
            page.wait_for_selector("canvas", timeout=LONG)
            page.get_by_text("world", exact=True).first.wait_for(timeout=LONG)
            client = _wait(lambda: next(iter(viewer.server.get_clients().values()), None), what="the client")
            viewer.playing = False
            items = viewer.reader.items(viewer.index)
            target = items["world_000002/teapot"].points
            center = target.mean(axis=0)
            client.camera.position = tuple(center + np.array([0.0, 1.2, 1.6]))
            client.camera.look_at = tuple(center)
            _wait(lambda: np.allclose(client.camera.look_at, center, atol=1e-3), what="the camera")
            dismiss_notice(page)  # viser's "software WebGL" notice
            wait_still(page)  # the page has drawn the moved camera
            x, y = _project(client.camera, center)
            assert 0 < x < WIDTH and 0 < y < HEIGHT
            page.mouse.click(x, y)
            _wait(lambda: viewer.isolated == "world_000002", timeout=30, what="the click to isolate world 2")
            shown = {w for w, h, _ in viewer.drawn_nodes() if getattr(h, "visible", True)}
            assert shown == {"world_000002"}
            _wait(lambda: viewer.menu.value == "world_000002", what="the menu to follow the isolated world")
            # the camera frames the selected world: its teapot over the run fills the middle of the view
            lo, hi = viewer.reader.world_bounds("world_000002")
            assert lo[0] <= center[0] <= hi[0] and lo[2] <= center[2] <= hi[2]
            _wait(lambda: np.allclose(client.camera.look_at, 0.5 * (lo + hi), atol=1e-3), what="the world's framing")
            corners = np.array([_project(client.camera, (a, b, c)) for a in (lo[0], hi[0]) for b in (lo[1], hi[1])
                                for c in (lo[2], hi[2])])
            assert (corners > 0).all() and (corners[:, 0] < WIDTH).all() and (corners[:, 1] < HEIGHT).all()
            assert np.ptp(corners[:, 1]) > 0.3 * HEIGHT  # framed, not a speck
            wait_still(page)
            x, y = _project(client.camera, center)
            page.mouse.click(x, y)
            _wait(lambda: viewer.isolated is None, timeout=30, what="a second click to show every world")
            assert {w for w, h, _ in viewer.drawn_nodes() if getattr(h, "visible", True)} == set(viewer.reader.worlds)
            _wait(lambda: np.allclose(client.camera.look_at, viewer.gallery_pose[1], atol=1e-3),
                  what="the gallery's framing again")
            browser.close()
    finally:
        viewer.stop()
