"""Host memory the system can still give, for the checks that refuse a run before it allocates
(``warpsim.sweeps.preflight``, the donuts scene)."""

from __future__ import annotations

import os

UNKNOWN = 1 << 62
"""What ``available_host_bytes`` returns by default where the figure cannot be read."""


def available_host_bytes(unknown: int = UNKNOWN) -> int:
    """Memory the system can still give [bytes]: ``MemAvailable`` from /proc/meminfo, else the
    available pages (``os.sysconf``), else ``unknown``."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):  # pragma: no cover - no sysconf
        return int(unknown)
