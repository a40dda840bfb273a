"""Live viewer loop overhead against the same scene stepping headless (same process).

Headless: ``scene.advance(frame_dt, substeps)`` per frame, as ``warpsim run`` steps it (no
output). Viewer: the viewer's frame, i.e. ``Session.advance`` (advance + ``frame_data`` + the
viewer sink's validation, copies and subsampling) plus ``Drawer.draw`` pushing the frame into a
running viser server (``--browser``: with a headless Chromium tab connected and rendering it,
otherwise no client). Prints frames per second of both, the displayed frames per second and
the overhead %. Goals (issue 15): teapot on the CPU >= 30 displayed fps with <= 20 % overhead;
a 1,000,000-particle liquid on a GPU displayed at >= 10 fps (subsampled to --max-points)::

    python benchmarks/bench_viewer.py --device cpu
    python benchmarks/bench_viewer.py --device cuda:0 --scene dam_break \\
        --set spacing=0.00493 --set surface=false --max-points 200000
"""
from __future__ import annotations

import argparse
import os
import socket
import sys
import time

from warpsim.cli_common import DefaultsHelpFormatter, parse_sets, run_script
from warpsim.verbosity import set_warp_verbosity

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

ARGS = ["--no-sandbox", "--headless=new", "--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
        "--disable-background-networking", "--disable-component-update", "--disable-sync", "--no-first-run"]


def _free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=DefaultsHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--scene", default="teapot")
    ap.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--seconds", type=float, default=2.0, help="wall seconds per timed loop")
    ap.add_argument("--rounds", type=int, default=5, help="paired rounds (headless, viewer); the median is shown")
    ap.add_argument("--max-points", type=int, default=200_000)
    ap.add_argument("--draw-fps", type=float, default=45.0, help="the viewer's display rate cap (default 45, as the viewer)")
    ap.add_argument("--browser", action="store_true", help="connect headless Chromium to the server while timing")
    a = ap.parse_args(argv)

    import warp as wp

    set_warp_verbosity()  # quiet unless $WARPSIM_VERBOSE=1 (Warp 1.19 ignores config.quiet)
    from warpsim.scenes import get_scene
    from warpsim.viewer.server import Viewer

    cls = get_scene(a.scene)
    given = parse_sets(cls, a.sets, None)
    params = cls.resolve_params(given)

    from warpsim.viewer.session import frame_timing

    frame_dt, substeps, _ = frame_timing(cls, params)
    scene = cls(dict(params), device=a.device)  # the headless reference
    data = scene.frame_data()  # particles per points prim, as the scene hands them to every sink
    count = sum(len(d["points"]) for name, d in data.items() if "points" in d and name not in ("springs", "drag"))

    # the viewer's loop, as fast as it can, drawing every frame
    v = Viewer(cls, params, a.device, port=_free_port(), max_points=a.max_points, paused=True,
               draw_fps=a.draw_fps)
    v.start()
    pw = browser = None
    if a.browser:
        from playwright.sync_api import sync_playwright

        pw = sync_playwright().start()
        browser = pw.chromium.launch(executable_path="/usr/bin/chromium", args=ARGS)
        page = browser.new_page(viewport={"width": 1000, "height": 640})
        page.goto(v.url)
        page.wait_for_selector("canvas", timeout=60_000)
        time.sleep(3.0)
    s = v.session

    def headless_run(seconds):
        """Frames per second stepping headless for ``seconds``."""
        frames, t0 = 0, time.perf_counter()
        while time.perf_counter() - t0 < seconds:
            scene.advance(frame_dt, substeps)
            frames += 1
        wp.synchronize_device(a.device)
        return frames / (time.perf_counter() - t0)

    def viewer_run(seconds):
        """(simulated frames/s, displayed frames/s) of the viewer's own loop, as fast as it goes."""
        f0, d0 = s.frame, v.draw_count
        t0 = time.perf_counter()
        s.set_playing(True)
        time.sleep(seconds)
        s.set_playing(False)
        with s.lock:  # the loop finishes its frame
            wp.synchronize_device(a.device)
            dt = time.perf_counter() - t0
        return (s.frame - f0) / dt, (v.draw_count - d0) / dt

    s.speed = float("inf")
    headless_run(0.5)  # warm-up: kernel loads, graph capture
    viewer_run(1.0)
    # paired rounds (headless, then viewer): the ratio within a pair cancels slow changes in the
    # machine's other load; the median pair is reported
    results = [(headless_run(a.seconds), viewer_run(a.seconds)) for _ in range(a.rounds)]
    results.sort(key=lambda r: r[0] / r[1][0])
    headless_fps, (viewer_fps, shown_fps) = results[len(results) // 2]
    spread = [100 * (r[0] / r[1][0] - 1) for r in results]
    error = s.error
    if browser is not None:
        browser.close()
        pw.stop()
    v.stop()
    if error:
        print(f"viewer loop failed: {error}")
        return 1
    shown = {k: len(it.points) for k, it in s.items.items()}
    print(f"scene {a.scene} on {a.device}: {count} points, drawn {shown}, frame_dt {frame_dt:.4g} s, "
          f"{substeps} substeps{', browser connected' if a.browser else ''}; median of {a.rounds} paired rounds "
          f"of {a.seconds:g} s")
    print(f"headless:  {headless_fps:.1f} frames/s ({1e3 / headless_fps:.2f} ms/frame)")
    print(f"viewer:    {viewer_fps:.1f} simulated frames/s, {shown_fps:.1f} displayed frames/s "
          f"(display capped at {a.draw_fps:g}/s)")
    print(f"overhead:  {100 * (headless_fps / viewer_fps - 1):.1f} % of the headless frame time (rounds: "
          f"{', '.join(f'{x:.0f}' for x in spread)} %); real time needs {1 / frame_dt:.1f} frames/s")
    return 0


if __name__ == "__main__":
    sys.exit(run_script(main))
