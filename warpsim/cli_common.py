"""What every ``warpsim`` command module shares with ``warpsim.cli``, one floor below both (so a
command module imports this, not the command line that loads it): the usage-mistake exception and
the ``--device`` check; the examples and benchmarks also run their ``main`` through
:func:`run_script` (a mistake is one line and exit 2, as in the command line) with
:class:`DefaultsHelpFormatter` (``--help`` shows every default)."""

from __future__ import annotations

import argparse
import os
import sys

__all__ = ["DefaultsHelpFormatter", "UsageError", "device_arg", "one_line", "run_script"]


class UsageError(Exception):
    """A mistake in the command line: reported with exit status 2."""


def device_arg(name) -> str:
    """The Warp device named by ``--device`` (``None``: ``cuda:0`` when CUDA is available, else
    ``cpu``) as a string; UsageError listing the available devices when it does not exist."""
    import warp as wp

    if name is None:
        return "cuda:0" if wp.is_cuda_available() else "cpu"
    try:
        return str(wp.get_device(name))
    except Exception as exc:  # noqa: BLE001  (Warp raises plain Exception/RuntimeError/ValueError)
        choices = [str(d) for d in wp.get_devices()]
        raise UsageError(f"--device {name!r} is not available ({exc}); available: {', '.join(choices)}") from None


def one_line(exc) -> str:
    """An exception's text on one line (its type name when it has none)."""
    return " ".join(str(exc).split("\n")).strip() or type(exc).__name__


class DefaultsHelpFormatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """``--help`` with each option's default, also for options without help text (argparse's own
    formatter skips those; on/off flags show none), and the description as written."""

    def add_argument(self, action):
        if action.help is None and self._shows_default(action):
            action.help = "(default: %(default)s)"  # argparse formats no help text for help=None
        super().add_argument(action)

    @staticmethod
    def _shows_default(action):
        return action.default not in (None, argparse.SUPPRESS) and not isinstance(action.default, bool) and \
            (bool(action.option_strings) or action.nargs in (argparse.OPTIONAL, argparse.ZERO_OR_MORE))

    def _get_help_string(self, action):
        text = action.help or ""
        if "%(default)" not in text and self._shows_default(action):
            text += " (default: %(default)s)"
        return text


def run_script(main, argv=None, prog=None) -> int:
    """Run an example's or benchmark's ``main(argv)`` as ``warpsim`` runs a command: a usage mistake
    or bad value (UsageError, ValueError, a missing or unwritable file) is one line on stderr and
    exit status 2, a failed simulation (SimulationError) one line and 1, Ctrl-C one line and 130;
    otherwise ``main``'s return value (None: 0). Use as ``sys.exit(run_script(main))``."""
    from .core.errors import SimulationError

    prog = prog or os.path.basename(sys.argv[0] or "script")
    try:
        status = main(argv) if argv is not None else main()
    except SimulationError as exc:
        print(f"{prog}: error: {one_line(exc)}", file=sys.stderr)
        return 1
    except (UsageError, ValueError, OSError) as exc:
        print(f"{prog}: error: {one_line(exc)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130
    return int(status or 0)
