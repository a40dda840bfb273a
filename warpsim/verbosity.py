"""How much Warp itself prints: its start-up banner and one "Module ... load on device ... took
... ms" line per kernel module. The ``warpsim`` command line and the examples keep those out of
their tables and progress bars unless ``--verbose`` asks for them; warnings and errors always show.

    from warpsim.verbosity import set_warp_verbosity
    set_warp_verbosity(args.verbose)
"""

from __future__ import annotations

import os
from typing import Optional

__all__ = ["ENV", "choose_warp_verbosity", "set_warp_verbosity", "warp_verbose"]

ENV = "WARPSIM_VERBOSE"
"""Environment variable: ``1`` shows Warp's messages in every warpsim command and example."""

_verbose: Optional[bool] = None


def warp_verbose() -> bool:
    """The process-wide choice: the last ``set_warp_verbosity(True/False)``, else ``$WARPSIM_VERBOSE``."""
    if _verbose is not None:
        return _verbose
    return os.environ.get(ENV, "").strip().lower() in ("1", "true", "yes", "on")


def choose_warp_verbosity(verbose: Optional[bool]) -> None:
    """Record the process-wide choice without importing Warp (``None``: back to ``$WARPSIM_VERBOSE``);
    :func:`set_warp_verbosity` applies it once Warp is needed."""
    global _verbose
    _verbose = None if verbose is None else bool(verbose)


def set_warp_verbosity(verbose: Optional[bool] = None) -> None:
    """Show Warp's banner and module-load lines (``verbose=True``) or only its warnings and errors
    (``False``); ``None`` applies the process-wide choice (:func:`warp_verbose`). Imports Warp."""
    if verbose is not None:
        choose_warp_verbosity(verbose)
    import warp as wp

    quiet = not warp_verbose()
    setattr(wp.config, "quiet", quiet)  # Warp < 1.19 (gone in 1.19, where log_level below applies)
    if hasattr(wp, "LOG_WARNING"):  # Warp >= 1.19 filters its messages by level
        wp.config.log_level = wp.LOG_WARNING if quiet else wp.LOG_INFO
