"""The page a tab sees while a live scene is built (``warpsim view SCENE``): served on the viewer's
own address at once, it says what the build is doing (building the scene, the hair's strands and
its sag-free solve, as the scene reports them on standard error), then makes way for the viewer
on the same port; an open tab reconnects to it by itself, and its first frame says it compiles
Warp's kernels (:meth:`warpsim.viewer.controls.Controls.starting`).
"""
from __future__ import annotations

import io
import sys
import time

__all__ = ["StartingPage"]


class StartingPage:
    """A viser server on ``host``:``port`` showing ``title`` and the lines :meth:`say` is given
    (and, inside ``with page.reporting():``, every line written to standard error)."""

    def __init__(self, host, port, title):
        import viser

        from .server import quiet_stdout

        with quiet_stdout():
            self.server = viser.ViserServer(host=host, port=port, label="warpsim (starting)", verbose=False)
        self.title = title
        self.t0 = time.perf_counter()
        self.lines = []
        self.text = self.server.gui.add_markdown(self._content())

    def _content(self):
        shown = "  \n".join(self.lines[-6:]) if self.lines else "..."
        return f"**{self.title}** ({time.perf_counter() - self.t0:.0f} s)  \n{shown}"

    def say(self, line):
        """Add ``line`` to the page (the newest six are shown)."""
        line = line.strip().removeprefix("warpsim: ")
        if line:
            self.lines.append(line)
            if self.server is not None:
                self.text.content = self._content()

    def reporting(self):
        """Context: standard error also goes to the page, line by line."""
        import contextlib

        page = self

        class Tee(io.TextIOBase):
            def __init__(self, out):
                self.out, self.part = out, ""

            def write(self, s):
                self.out.write(s)
                self.part += s
                *done, self.part = self.part.split("\n")
                for line in done:
                    page.say(line)
                return len(s)

            def flush(self):
                self.out.flush()

        return contextlib.redirect_stderr(Tee(sys.stderr))

    def close(self):
        """Stop serving (the port is free again for the viewer)."""
        from .server import quiet_stdout

        if self.server is not None:
            with quiet_stdout():
                self.server.stop()
            self.server = None
