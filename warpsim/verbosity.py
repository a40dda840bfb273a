"""How much Warp itself prints: its start-up banner, the native "Warp CUDA warning: Could not find
or load the NVIDIA CUDA driver" on a machine without a GPU, and one "Module ... load on device ...
took ... ms" line per kernel module. warpsim is quiet by default (the ``warpsim`` command line, the
examples and the Python API: the first ``ws.<name>`` applies it) and verbose on request:
``--verbose``, ``$WARPSIM_VERBOSE=1`` or ``set_warp_verbosity(True)``. Warnings and errors always
show. A first (cold) run says once, on stderr, that kernels are being compiled and cached.

    from warpsim.verbosity import set_warp_verbosity
    set_warp_verbosity(args.verbose)
"""

from __future__ import annotations

import os
import sys
import tempfile
import threading
from typing import Optional

__all__ = ["COMPILE_NOTICE", "ENV", "choose_warp_verbosity", "set_warp_verbosity", "warp_verbose"]

ENV = "WARPSIM_VERBOSE"
"""Environment variable: ``1`` shows Warp's messages in every warpsim command and example."""

COMPILE_NOTICE = "warpsim: compiling Warp kernels on first use (once: they are cached in {dir} for later runs)"
"""Said once per process, on stderr, before the first kernel module is compiled (a cold cache)."""

CUDA_DRIVER_WARNING = "Could not find or load the NVIDIA CUDA driver"
"""Part of the line Warp's native library prints when a machine has no CUDA driver."""

_verbose: Optional[bool] = None
_lock = threading.Lock()
_notice_said = False
_hooked = False
_started = False


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
    """Show Warp's banner, CUDA-driver warning and module-load lines (``verbose=True``) or only its
    warnings and errors (``False``); ``None`` applies the process-wide choice (:func:`warp_verbose`).
    Imports Warp; quiet, it starts Warp's runtime with the native no-driver line filtered out."""
    if verbose is not None:
        choose_warp_verbosity(verbose)
    import warp as wp

    quiet = not warp_verbose()
    setattr(wp.config, "quiet", quiet)  # Warp < 1.19 (gone in 1.19, where log_level below applies)
    if hasattr(wp, "LOG_WARNING"):  # Warp >= 1.19 filters its messages by level
        wp.config.log_level = wp.LOG_WARNING if quiet else wp.LOG_INFO
    _hook_compile_notice()
    if quiet:
        _init_without_driver_warning(wp)


def _init_without_driver_warning(wp) -> None:
    """``wp.init()`` with file descriptor 2 captured, then everything it printed re-emitted except
    the native "no CUDA driver" line (printed by C code: Python's sys.stderr cannot catch it). Once
    per process (``wp.init()`` on a started runtime prints nothing)."""
    global _started
    with _lock:
        if _started:
            return
        _started = True
        try:
            fd = sys.stderr.fileno()
        except (AttributeError, OSError, ValueError):  # a replaced stderr (notebooks): nothing to filter
            wp.init()
            return
        sys.stderr.flush()
        saved = os.dup(fd)
        with tempfile.TemporaryFile() as tmp:
            try:
                os.dup2(tmp.fileno(), fd)
                wp.init()
            finally:
                sys.stderr.flush()
                os.dup2(saved, fd)
                os.close(saved)
                tmp.seek(0)
                text = tmp.read().decode("utf-8", "replace")
                kept = [line for line in text.splitlines(keepends=True) if CUDA_DRIVER_WARNING not in line]
                if kept:
                    sys.stderr.write("".join(kept))
                    sys.stderr.flush()


def _say_compiling(wp) -> None:
    global _notice_said
    with _lock:
        if _notice_said:
            return
        _notice_said = True
    print(COMPILE_NOTICE.format(dir=wp.config.kernel_cache_dir), file=sys.stderr, flush=True)


def _hook_compile_notice() -> None:
    """Say :data:`COMPILE_NOTICE` once, just before Warp compiles a module whose binary is not in
    the kernel cache (Warp itself says it only after, and only when verbose). Left out, silently,
    on a Warp whose ``Module._compile(device, output_dir, output_name, ...)`` differs."""
    global _hooked
    with _lock:
        if _hooked:
            return
        _hooked = True
    import warp as wp

    from .kernels import reduce  # any kernel: its module's class is Warp's (no public name for it)

    module_cls = type(reduce.reduce_rows.module)
    original = getattr(module_cls, "_compile", None)
    if original is None:
        return

    def _compile(self, device=None, output_dir=None, output_name=None, *args, **kwargs):
        if not _notice_said and output_dir is not None and output_name is not None and \
                not os.path.exists(os.path.join(output_dir, output_name)):
            _say_compiling(wp)
        return original(self, device, output_dir, output_name, *args, **kwargs)

    _compile.__doc__ = original.__doc__
    setattr(module_cls, "_compile", _compile)  # noqa: B010  (module_cls is found at run time)
