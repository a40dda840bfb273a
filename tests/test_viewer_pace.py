"""Drawing less when the page cannot keep up (warpsim.viewer.pace): thinning keeps whole strands,
one in k, and the round-trip probe halves the strands drawn while the slowest page lags and draws
them all again once it keeps up (a stand-in viser server whose page answers late, then at once)."""
from __future__ import annotations

import threading
import time

import numpy as np

from browser_page import wait
from warpsim.viewer.geometry import curve_segments
from warpsim.viewer.pace import BEHIND, ClientPace, thin_strands


def test_thinning_keeps_whole_strands_one_in_k():
    rng = np.random.default_rng(3)
    counts = [5] * 12
    points = rng.normal(size=(sum(counts), 3)).astype(np.float32)
    segments = curve_segments(points, counts)  # 12 strands of 4 segments
    assert np.array_equal(thin_strands(segments, 1), segments)
    kept = thin_strands(segments, 4)
    assert len(kept) == 3 * 4  # strands 0, 4 and 8, whole
    assert np.array_equal(kept, np.concatenate([segments[4 * s:4 * s + 4] for s in (0, 4, 8)]))


class _Page:
    def __init__(self):
        self.delay = 2 * BEHIND

    def get_render(self, height, width, transport_format="png", timeout=None):
        time.sleep(self.delay)
        return np.zeros((height, width, 4), np.uint8)


class _Server:
    def __init__(self, page):
        self.page = page

    def get_clients(self):
        return {7: self.page}


def feed(pace, every, stop):
    """Tell ``pace`` a frame was sent every ``every`` s until ``stop`` is set (a thread)."""
    def run():
        while not stop.wait(every):
            pace.sent()

    threading.Thread(target=run, daemon=True).start()


def test_the_probe_thins_while_the_page_lags_and_draws_all_once_it_keeps_up():
    page = _Page()
    pace = ClientPace(_Server(page), every=0.01)
    try:
        wait(lambda: pace.rounds >= 3 and pace.slowest() >= BEHIND, 30, "slow round trips measured")
        assert pace.step == 1  # no frame sent (paused): nothing to fall behind, nothing thinned
        stop = threading.Event()
        feed(pace, 0.01, stop)  # frames sent every 10 ms while the page answers in a second
        wait(lambda: pace.step >= 4, 30, "the strands thinned while the page lags")
        assert "drawing 1 strand in" in pace.note() and pace.slowest() >= BEHIND
        page.delay = 0.0
        wait(lambda: pace.step == 1, 30, "every strand drawn again")
        assert pace.note() is None
        stop.set()
    finally:
        pace.stop()
    # frames 0.5 s apart (a slow simulation): a page 0.6 s behind keeps up with them, nothing thinned
    page.delay = 1.2 * BEHIND
    pace = ClientPace(_Server(page), every=0.01)
    try:
        stop = threading.Event()
        feed(pace, 0.5, stop)
        wait(lambda: pace.slowest() >= 1.2 * BEHIND and pace.period > 0.4, 30, "slow frames and round trips")
        rounds = pace.rounds
        wait(lambda: pace.rounds >= rounds + 3, 30, "three more rounds of probes")
        stop.set()
        assert pace.step == 1
    finally:
        pace.stop()
