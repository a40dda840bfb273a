"""What every ``warpsim`` command module shares, one floor below the dispatcher ``warpsim.cli``
(so a command module imports this, never the command line that loads it): the usage-mistake
exception, option parsing (``--set``, ``--substeps``, ``--device``, the frame timing from
``--fps`` / ``--substeps``), output checks (an ``--out`` that can be written, held by this command
alone) and the timing and stability warnings. The examples and benchmarks also run their ``main``
through :func:`run_script` (a mistake is one line and exit 2, as in the command line) with
:class:`DefaultsHelpFormatter` (``--help`` shows every default)."""

from __future__ import annotations

import argparse
import os
import sys

__all__ = ["DefaultsHelpFormatter", "UsageError", "check_output_path", "device_arg", "hold_output", "one_line",
           "parse_sets", "run_script", "stability_check", "substeps_arg", "timing_from_flags", "timing_note",
           "warn_or_refuse"]


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


def parse_sets(cls, sets, integrator):
    """{key: typed value} from --set KEY=VALUE items (and --integrator)."""
    from .core.names import close_matches
    from .scenes import parse_value

    given = {}
    for item in sets:
        if "=" not in item:
            raise UsageError(f"--set {item!r} is malformed; write --set KEY=VALUE (e.g. --set dt=0.01)")
        key, text = item.split("=", 1)
        key = key.strip()
        if key not in cls.params:
            raise UsageError(f"scene {cls.name!r} has no parameter {key!r}.{close_matches(key, cls.params)} "
                             f"Its parameters: {', '.join(cls.params) or 'none'}.")
        try:
            given[key] = parse_value(cls.params[key], key, text)
        except ValueError as exc:
            raise UsageError(str(exc)) from None
    if integrator is not None:
        if "integrator" not in cls.params:
            raise UsageError(f"scene {cls.name!r} has no integrator choice")
        if "integrator" in given and given["integrator"] != integrator:
            raise UsageError("--integrator and --set integrator=... disagree; give one")
        try:
            given["integrator"] = parse_value(cls.params["integrator"], "integrator", integrator)
        except ValueError as exc:
            raise UsageError(f"--integrator: {exc}") from None
    return given


def substeps_arg(text):
    """``--substeps`` value: an int, or "auto" (sub-step inside the stability limit)."""
    if str(text).strip().lower() == "auto":
        return "auto"
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number or 'auto'") from None


def timing_from_flags(cls, params, given, fps, substeps):
    """(timing, params) from the flags and the scene's defaults: the run's
    :class:`~warpsim.scenes.timing.FrameTiming` (see there for the rules) and ``params`` with a
    ``dt`` parameter set to the step taken; :class:`UsageError` (exit 2) for a bad value or flags
    that disagree."""
    from .scenes.timing import resolve_timing

    try:
        timing = resolve_timing(cls, params, fps=fps, substeps=substeps, given=given)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    return timing, timing.scene_params(params)


def warn_or_refuse(line, strict, err) -> None:
    """``line`` as one ``warpsim: warning:`` line on ``err``, or with ``strict`` (``--strict``) a
    :class:`UsageError` ``--strict: line`` (exit 2)."""
    if strict:
        raise UsageError(f"--strict: {line}")
    print(f"warpsim: warning: {line}", file=err)


def timing_note(timing, strict, err) -> None:
    """The timing's note (``--substeps N`` overriding a scene's dt) as one ``warpsim: warning:``
    line on ``err``, or with ``strict`` a :class:`UsageError` (exit 2)."""
    if timing.note:
        warn_or_refuse(timing.note, strict, err)


def stability_check(scene, frame_dt, substeps, strict, err) -> None:
    """Before the first step: one ``warpsim: warning:`` line on ``err`` when the scene's step is
    above its stability limit (naming the limiter and the remedies), or with ``strict`` a
    :class:`UsageError` (exit 2)."""
    line = scene.stability_warning(frame_dt, substeps)
    if line is not None:
        warn_or_refuse(line, strict, err)


def check_output_path(path, flag="--out"):
    """Create the folder of ``--out`` (or another output option ``flag``) and make sure a file
    can be written there, so an unusable path is one line and exit 2 before the scene is built."""
    import tempfile

    if os.path.isdir(path):
        raise UsageError(f"{flag} {path!r} is a folder; name a file in it, e.g. "
                         f"{os.path.join(path, 'scene' + (os.path.splitext(path)[1] or '.usda'))!r}")
    from .core.safe_files import check_replaceable

    try:
        check_replaceable(path, flag)  # a FIFO or a device there: refused, never written into
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    folder = os.path.dirname(os.path.abspath(path))
    probe = folder
    while not os.path.lexists(probe):
        probe = os.path.dirname(probe)
    if not os.path.isdir(probe):
        raise UsageError(f"{flag} {path!r}: {probe!r} is a file, not a folder; choose another {flag}")
    try:
        os.makedirs(folder, exist_ok=True)
        tempfile.TemporaryFile(dir=folder).close()
    except OSError as exc:
        raise UsageError(f"{flag} {path!r}: cannot write in folder {folder!r} ({exc.strerror or exc}); choose a "
                         "writable folder") from None
    if os.path.lexists(path) and not os.access(path, os.W_OK):
        raise UsageError(f"{flag} {path!r} exists and is not writable; choose another {flag} or change its "
                         "permissions")


def hold_output(path, flag="--out", inputs=(), own=None):
    """Refuse an output that is one of ``inputs`` or a file of a cache or sweep other than its
    own (``own``: the root this command writes), then take its lock for the rest of the command
    (``warpsim.usd.lock``; another process writing it: one line, exit 2)."""
    from .usd.family import check_output
    from .usd.lock import hold

    try:
        check_output(path, inputs, flag, own=own)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    hold(path, flag)


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
