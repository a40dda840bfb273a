"""Whether the browser keeps up, and drawing less when it does not (viser front end).

:class:`ClientPace` measures each open tab's round trip in a background thread: a tiny picture
asked of the page (``client.get_render`` at 8 x 8 pixels) comes back only once the page has taken
every message sent before it and drawn a frame, so its delay is how far the page is behind.
:func:`thin_strands` keeps every k-th curve of a segments item (whole strands, not dashes): the
viewer draws long curve sets (hair) thinned while the slowest page lags, and says so in its panel.
"""
from __future__ import annotations

import threading
import time

import numpy as np

__all__ = ["ClientPace", "THIN_SEGMENTS", "thin_strands"]

PROBE_PERIOD = 2.0
"""Seconds between two round trips asked of one page."""
BEHIND = 0.5
"""A round trip longer than this [s] and than two frames sent (a page that falls behind the frames
it is sent): draw half as many strands."""
CAUGHT_UP = 0.15
"""A round trip shorter than this [s] or than half a frame sent: draw twice as many again (up to
all)."""
THIN_SEGMENTS = 16_384
"""Curve sets of more segments than this may be thinned (hair at its default: 32,000; not a
teapot's 5,238 springs)."""
MOST_THINNING = 16


class ClientPace:
    """Round trips of the pages of a viser ``server`` (see the module docstring); ``step`` is the
    thinning to draw with now (1: every strand, k: one strand in k)."""

    def __init__(self, server, every=PROBE_PERIOD):
        self.server = server
        self.every = float(every)
        self.seconds = {}
        """Client id -> its last round trip [s]."""
        self.step = 1
        self.period = 0.0
        """Seconds between two frames sent to the pages, smoothed (:meth:`sent`)."""
        self._last_sent = None
        self.sent_count = 0
        """Frames sent to the pages (:meth:`sent`)."""
        self.rounds = 0
        """Probe rounds made (every open page asked once a round)."""
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="warpsim-pace", daemon=True)
        self._thread.start()

    def slowest(self):
        """The longest last round trip of an open page [s] (0 with none measured)."""
        clients = self.server.get_clients() if self.server is not None else {}
        return max([s for cid, s in self.seconds.items() if cid in clients] or [0.0])

    def note(self):
        """A line for the panel while strands are thinned (None otherwise)."""
        if self.step == 1:
            return None
        return (f"drawing 1 strand in {self.step}: the page is {self.slowest():.1f} s behind "
                f"(all are drawn again once it keeps up)")

    def _run(self):
        counted = 0
        while not self._stop.wait(self.every):
            server = self.server
            if server is None:
                return
            for cid, client in list(server.get_clients().items()):
                t0 = time.perf_counter()
                try:
                    client.get_render(8, 8, transport_format="png", timeout=10.0 * BEHIND + self.every)
                except Exception:  # noqa: BLE001  (a page that closed or never answered: the slowest)
                    if cid not in server.get_clients():
                        self.seconds.pop(cid, None)
                        continue
                self.seconds[cid] = time.perf_counter() - t0
            if self._stop.is_set():
                return
            self.rounds += 1
            slowest = self.slowest()
            # frames flowing (paused: nothing to fall behind), two or more, so their period is known
            flowing, counted = self.sent_count != counted and self.period > 0.0, self.sent_count
            if flowing and slowest > max(BEHIND, 2.0 * self.period):
                self.step = min(2 * self.step, MOST_THINNING)
            elif slowest < max(CAUGHT_UP, 0.5 * self.period):
                self.step = max(self.step // 2, 1)

    def sent(self, now=None):
        """A frame was sent to the pages (at ``now`` [s], ``time.perf_counter()``)."""
        now = time.perf_counter() if now is None else now
        if self._last_sent is not None:
            gap = now - self._last_sent
            self.period = gap if self.period == 0.0 else 0.8 * self.period + 0.2 * gap
        self._last_sent = now
        self.sent_count += 1

    def stop(self):
        """Stop probing; every strand is drawn from the next frame on."""
        self._stop.set()
        self.step = 1


def thin_strands(points, step):
    """Every ``step``-th curve of segments ``points`` (s, 2, 3) [m]: a curve is a run of segments
    each starting where the last ended; returns the kept segments (all for ``step`` <= 1)."""
    points = np.asarray(points)
    if step <= 1 or len(points) < 2:
        return points
    starts = np.ones(len(points), bool)
    starts[1:] = np.any(points[1:, 0] != points[:-1, 1], axis=1)
    curve = np.cumsum(starts) - 1
    return points[curve % int(step) == 0]
