"""What every viewer front end shares: serving in the foreground until Ctrl-C or ``stop``."""

from __future__ import annotations

import time


class Serving:
    """Mix-in for a viewer with ``server`` (None until ``start``), ``_stop`` (a threading.Event),
    ``start()`` and ``stop()``."""

    def request_stop(self):
        """Ask :meth:`run` to stop at its next check (safe from a signal handler: it sets an event)."""
        self._stop.set()

    def run(self):
        """Serve until Ctrl-C (or :meth:`stop` / :meth:`request_stop` from another thread)."""
        if self.server is None:
            self.start()
        try:
            while not self._stop.is_set():
                time.sleep(0.2)
        except KeyboardInterrupt:
            pass
        finally:
            self.stop()
