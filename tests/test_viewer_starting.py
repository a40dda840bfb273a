"""While a live scene is built, ``warpsim view`` already serves a page on the viewer's address that
says what the build is doing (what the scene says on standard error: building, the hair's sag-free
solve), in Chromium; the viewer then serves on the same port (an open tab reconnects to it)."""
from __future__ import annotations

import subprocess
import sys

import playwright.sync_api as playwright  # the test extra installs it; CI must run this test, never skip it
from browser_page import ARGS, CHROMIUM, HEIGHT, LONG, WIDTH, free_port

from warpsim.viewer.server import check_port
from warpsim.viewer.starting import StartingPage


def test_the_starting_page_says_what_the_build_does():
    port = free_port()
    page_server = StartingPage("127.0.0.1", port, "warpsim view hair: starting")
    try:
        with page_server.reporting():
            print("warpsim: hair: solving the sag-free rest state of 2,000 strands x 16 segments ...", file=sys.stderr)
        with playwright.sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
            page = browser.new_page(viewport={"width": WIDTH, "height": HEIGHT})
            page.goto(f"http://127.0.0.1:{port}")
            page.get_by_text("warpsim view hair: starting", exact=False).first.wait_for(timeout=LONG)
            page.get_by_text("hair: solving the sag-free rest state", exact=False).first.wait_for(timeout=LONG)
            with page_server.reporting():  # a later line shows in the open page
                print("warpsim: hair: sag-free done in 12.0 s", file=sys.stderr)
            page.get_by_text("sag-free done in 12.0 s", exact=False).first.wait_for(timeout=LONG)
            browser.close()
    finally:
        page_server.close()
    check_port("127.0.0.1", port)  # free again: the viewer serves there next


def test_warpsim_view_names_its_address_before_it_builds_and_serves_there():
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "warpsim", "view", "bounce", "--device", "cpu", "--port", str(port)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        first = proc.stdout.readline()
        assert f"http://127.0.0.1:{port}" in first and "the page says how the start goes" in first
        assert f"http://127.0.0.1:{port}" in proc.stdout.readline()  # the viewer, on the same port
        with playwright.sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
            page = browser.new_page(viewport={"width": WIDTH, "height": HEIGHT})
            page.goto(f"http://127.0.0.1:{port}")
            page.get_by_text("restitution (live)").wait_for(timeout=LONG)
            browser.close()
    finally:
        proc.terminate()
        proc.communicate(timeout=60)
