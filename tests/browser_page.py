"""What the browser tests share: Debian's Chromium, headless, driven by Playwright (WebGL through
SwiftShader), a free port, waiting for a condition (never for a fixed time: a loaded machine takes
longer, never differently), where a point lands on screen, and whether a scene node is drawn where
it projects (the pixels there change when it is hidden, and come back when it is shown)."""
from __future__ import annotations

import io
import os
import socket
import time

import numpy as np

CHROMIUM = "/usr/bin/chromium"
ARGS = ["--no-sandbox", "--headless=new", "--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
        "--disable-background-networking", "--disable-component-update", "--disable-sync", "--no-first-run"]
WIDTH, HEIGHT = 1000, 640
VIEW_RIGHT = 660
"""Pixels left of this are the 3D view (viser's panel covers the right of a WIDTH-wide page)."""
PATIENCE = float(os.environ.get("WARPSIM_BROWSER_PATIENCE", "1"))
"""Every wait's time-out is multiplied by this (a slower machine: raise it; nothing waits longer
than its condition needs)."""


def free_port():
    """A TCP port on 127.0.0.1 that nothing listens on now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait(cond, timeout=20.0, what="condition", every=0.05):
    """``cond()``'s first true value (an array counts as true), polled every ``every`` s;
    AssertionError naming ``what`` (text, or a function giving it then) after ``timeout`` x
    :data:`PATIENCE` seconds."""
    t0 = time.time()
    while True:
        value = cond()
        if value is not None if isinstance(value, np.ndarray) else value:
            return value
        if time.time() - t0 > timeout * PATIENCE:
            raise AssertionError(f"timed out after {timeout * PATIENCE:g} s waiting for {what() if callable(what) else what}")
        time.sleep(every)


def project(cam, point, width=WIDTH, height=HEIGHT):
    """Pixel (x, y) of world ``point`` seen by a viser client camera (OpenCV convention: the
    camera's +z looks forward, +y down; ``fov`` is vertical)."""
    w, x, y, z = np.asarray(cam.wxyz, float)
    rot = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                    [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                    [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    p = rot.T @ (np.asarray(point, float) - np.asarray(cam.position, float))
    f = (height / 2) / np.tan(cam.fov / 2)
    return width / 2 + f * p[0] / p[2], height / 2 + f * p[1] / p[2]


def pixels(page) -> np.ndarray:
    """A screenshot of ``page`` as an (H, W, 3) float array."""
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(page.screenshot())).convert("RGB"), np.float64)


def dismiss_notice(page, timeout=5.0):
    """Close viser's "software WebGL" notification when it shows (it covers the view's top left). The
    click is dispatched to the button (a page drawing hair on a loaded CPU paints so rarely that the
    button never looks "stable" to a pointer click: CI timed out after 30 s waiting for that)."""
    close = page.locator(".mantine-Notification-closeButton")
    try:
        close.first.wait_for(state="visible", timeout=1e3 * timeout * PATIENCE)
    except Exception:  # noqa: BLE001  (no notice: nothing to close)
        return
    close.first.dispatch_event("click")
    try:
        close.first.wait_for(state="detached", timeout=1e3 * timeout * PATIENCE)
    except Exception:  # noqa: BLE001  (a page that paints rarely may not finish the notice's exit animation:
        # CI waited 5 s for it; the notice is hidden and lets clicks through instead)
        page.evaluate("document.querySelectorAll('.mantine-Notification-root').forEach("
                      "e => { e.style.visibility = 'hidden'; e.style.pointerEvents = 'none'; })")


def pixel_box(cam, points, pad=6):
    """(x0, y0, x1, y1) of the screen rectangle holding ``points`` [m] (padded by ``pad`` px),
    clipped to the 3D view; None when it falls outside it."""
    px = np.array([project(cam, p) for p in np.asarray(points, float).reshape(-1, 3)])
    x0, y0 = np.floor(px.min(0) - pad).astype(int)
    x1, y1 = np.ceil(px.max(0) + pad).astype(int)
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, VIEW_RIGHT), min(y1, HEIGHT)
    return (x0, y0, x1, y1) if x1 - x0 > 2 and y1 - y0 > 2 else None


def changed(a, b, box, level=40.0):
    """Pixels inside ``box`` whose colour differs by more than ``level`` (sum over RGB) between
    the screenshots ``a`` and ``b``."""
    x0, y0, x1, y1 = box
    return int((np.abs(a[y0:y1, x0:x1] - b[y0:y1, x0:x1]).sum(axis=2) > level).sum())


def drawn_where_projected(page, handle, box, least=20, timeout=60.0):
    """Whether the scene node ``handle`` is drawn inside the screen rectangle ``box``: hiding it
    changes at least ``least`` pixels there, showing it again restores them (waited for, not
    slept on). The scene must hold still meanwhile (playback paused, camera unmoved)."""
    shown = pixels(page)
    handle.visible = False
    try:
        hidden = wait(lambda: (lambda now: now if changed(shown, now, box) >= least else None)(pixels(page)),
                      timeout, what=f"hiding {handle.name} to change the pixels where it projects")
    finally:
        handle.visible = True
    wait(lambda: changed(hidden, pixels(page), box) >= least, timeout,
         what=f"showing {handle.name} again to redraw it")
    return True


LONG = int(60_000 * PATIENCE)
"""Milliseconds a Playwright wait for an element may take at most (a bound, not a pause)."""


def wait_still(page, timeout=60.0, level=40.0):
    """Wait until the 3D view holds still: two screenshots in a row alike (every pixel left of the
    panel within ``level``); returns the last. For a scene that is paused and a camera that has
    been moved: the page has drawn what it was sent (instead of sleeping for a guessed time)."""
    box = (0, 0, VIEW_RIGHT, HEIGHT)
    last = [pixels(page)]

    def alike():
        now = pixels(page)
        same = changed(last[0], now, box, level) == 0
        last[0] = now
        return now if same else None

    return wait(alike, timeout, "the view to hold still", every=0.1)
