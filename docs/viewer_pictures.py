"""The README's pictures of the browser viewer, made in headless Chromium (never by hand):

- ``viewer_teapot.png``: ``warpsim view teapot`` paused at frame 45, the teapot on the floor;
- ``viewer_gallery.png``: ``warpsim view`` on a 4-teapot height sweep, at its first view (world 0
  with the query box and its two corner gizmos, paused at frame 0).

Run ``python docs/viewer_pictures.py`` (``--out FOLDER``, default: this folder) after changing
the viewer; ``tests/test_readme_pictures.py`` runs it and fails while a committed picture's panel
differs from the one made now (labels, units, ranges), so they cannot drift. Needs the test
extra's Playwright and Debian's Chromium (``apt-get install chromium``).
"""
from __future__ import annotations

import argparse
import io
import os
import sys
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
CHROMIUM = "/usr/bin/chromium"
ARGS = ["--no-sandbox", "--headless=new", "--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
        "--disable-background-networking", "--disable-component-update", "--disable-sync", "--no-first-run"]
SIZE = (1000, 640)
PICTURES = ("viewer_teapot.png", "viewer_gallery.png")
PANEL = (665, 15, 985, 625)
"""(x0, y0, x1, y1) of viser's control panel in a picture [px]: what a drift check compares."""
TEAPOT_FRAME = 45
"""The teapot's frame in its picture (landed, bouncing off the floor)."""
TIMEOUT = 300.0
"""Seconds any one wait may take at most (a bound: nothing waits longer than its condition)."""


def _until(cond, what, timeout=TIMEOUT):
    t0 = time.time()
    while not cond():
        if time.time() - t0 > timeout:
            raise TimeoutError(f"viewer_pictures: timed out after {timeout:g} s waiting for {what}")
        time.sleep(0.05)


def _save(png, path):
    from PIL import Image

    Image.open(io.BytesIO(png)).convert("RGB").quantize(64).save(path, optimize=True)


def _page(browser, url):
    page = browser.new_page(viewport={"width": SIZE[0], "height": SIZE[1]})
    page.set_default_timeout(1e3 * TIMEOUT)
    page.goto(url)
    page.wait_for_selector("canvas")
    close = page.locator(".mantine-Notification-closeButton")  # viser's "software WebGL" notice
    try:
        close.first.wait_for(state="visible", timeout=10_000)
        close.first.click()
        close.first.wait_for(state="detached")
    except Exception:  # noqa: BLE001  (no notice shown: nothing to close)
        pass
    return page


def _still(page):
    """The screenshot once two in a row are alike (a paused scene drawn in full)."""
    from PIL import Image

    last = None
    t0 = time.time()
    while time.time() - t0 < TIMEOUT:
        png = page.screenshot()
        now = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), np.int16)
        if last is not None and np.abs(now - last).sum(axis=2).max() <= 40:
            return png
        last = now
        time.sleep(0.1)
    raise TimeoutError("viewer_pictures: the view never held still")


def teapot(browser, path):
    """``warpsim view teapot`` at frame :data:`TEAPOT_FRAME` (paused), written to ``path``."""
    from warpsim.viewer.server import Viewer

    viewer = Viewer("teapot", device="cpu", port=_free_port(), paused=True).start()
    try:
        page = _page(browser, viewer.url)
        page.get_by_text("restitution (live)").wait_for()
        for _ in range(TEAPOT_FRAME):
            viewer.session.step_once()
        viewer.redraw()
        viewer.controls.refresh()
        page.get_by_text(f"frame {TEAPOT_FRAME} ", exact=False).first.wait_for()
        _save(_still(page), path)
        page.close()
    finally:
        viewer.stop()


def gallery(browser, path):
    """The first view of a 4-teapot height sweep's gallery (the query box on world 0), to ``path``."""
    from warpsim.browse.gallery import GalleryViewer
    from warpsim.cli import main

    with tempfile.TemporaryDirectory(prefix="warpsim_pictures_") as folder, _inside(folder):
        root = "teapot_sweep.usda"  # the panel names it: the same words in every picture made
        code = main(["sweep", "teapot", "--worlds", "4", "--vary", "height=0.1:0.9", "--frames", "21",
                     "--no-progress", "--no-thumbnails", "--device", "cpu", "--out", root],
                    out=io.StringIO(), err=io.StringIO())
        if code != 0:
            raise RuntimeError(f"viewer_pictures: the sweep failed (exit {code})")
        viewer = GalleryViewer(root, port=_free_port(), thumbnails=False).start()
        try:
            viewer.playing = False
            viewer.timeline.value = 0  # frame 0, as the page opens
            page = _page(browser, viewer.url)
            page.get_by_text(f"{len(viewer.query.matches)} of 4 worlds", exact=False).first.wait_for()
            page.get_by_text(os.path.basename(root), exact=False).first.wait_for()
            _save(_still(page), path)
            page.close()
        finally:
            viewer.stop()


class _inside:
    """Context: the working folder is ``folder`` meanwhile."""

    def __init__(self, folder):
        self.folder, self.before = folder, None

    def __enter__(self):
        self.before = os.getcwd()
        os.chdir(self.folder)

    def __exit__(self, *exc):
        os.chdir(self.before)


def _free_port():
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def make(out=HERE):
    """Write :data:`PICTURES` into ``out``; returns their paths."""
    import playwright.sync_api as playwright

    os.makedirs(out, exist_ok=True)
    paths = [os.path.join(out, name) for name in PICTURES]
    with playwright.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
        try:
            teapot(browser, paths[0])
            gallery(browser, paths[1])
        finally:
            browser.close()
    return paths


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=HERE, help="folder to write the pictures into (default: docs/)")
    args = parser.parse_args(argv)
    for path in make(args.out):
        print(f"wrote {os.path.relpath(path)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
