"""The ``warpsim`` command line (also ``python -m warpsim``).

    warpsim list                                   scenes, descriptions, settable parameters
    warpsim run SCENE [--frames N] [--fps F] [--substeps S] [--integrator NAME] [--device D]
                      [--out PATH] [--set KEY=VALUE ...] [--chunk K] [--flatten]
                      [--checkpoint-every N] [--resume]
    warpsim run SCENE --from-sweep ROOT --world N   world N of a sweep, alone, bit for bit
    warpsim info CACHE                             prims, frame range, counts, bounds

Exit status: 0 on success, 2 for usage mistakes (unknown scene or parameter, malformed value,
an unusable --out, a damaged checkpoint: any bad value or file found before the simulation
starts, reported as one line), 1 when the simulation fails (the frames written so far stay
readable) or ``info`` finds damaged chunk files (it lists them and the frames still readable).
"""
from __future__ import annotations

import argparse
import os
import sys

from .cli_common import UsageError, one_line
from .verbosity import choose_warp_verbosity

__all__ = ["COMMANDS", "UsageError", "main"]

COMMANDS = {
    "list": "warpsim.commands.listing",
    "run": "warpsim.commands.run",
    "info": "warpsim.commands.info",
    "view": "warpsim.viewer.command",
    "render": "warpsim.render.command",
    "plot": "warpsim.render.plot",
    "sweep": "warpsim.sweeps.command",
    "query": "warpsim.sweeps.query_command",
    "pick": "warpsim.sweeps.pick_command",
    "export": "warpsim.render.export_command",
}
"""Every sub-command, by name -> module path (in the order ``--help`` lists them). A command
module defines ``add_parser(sub)`` (adds its sub-parser to argparse's sub-parsers; imports
nothing heavy) and ``run(args, out, err) -> int`` (exit status; raise
:class:`~warpsim.cli_common.UsageError` for a usage mistake, reported as one line with exit 2);
``READ_ONLY = True`` when it writes nothing (it then runs outside the outputs' lock scope). The
options every command shares (``--set``, ``--substeps``, ``--device``, ``--out`` checks, the
timing) are public names of :mod:`warpsim.cli_common`."""

CORE = ("list", "run", "info")
"""Commands whose parsers are always built (their modules import nothing heavy)."""


class _Parser(argparse.ArgumentParser):
    def error(self, message):
        raise UsageError(message)


def _wanted_commands(argv):
    """Command modules the parser must import for ``argv`` besides :data:`CORE`: none for
    list/run/info (so ``warpsim info`` starts in a fraction of a second), the one named, or all
    (help, mistakes)."""
    first = next((a for a in (sys.argv[1:] if argv is None else argv) if not str(a).startswith("-")), None)
    if first in CORE:
        return set()
    return {first} if first in COMMANDS else None


def _parser(argv=None):
    p = _Parser(prog="warpsim", description="Run warpsim scenes and stream them to USD caches.")
    p.add_argument("--verbose", action="store_true",
                   help="show Warp's start-up banner and kernel-module load lines (also accepted after the command)")
    names = list(COMMANDS)
    sub = p.add_subparsers(dest="command", metavar="{" + ",".join(names) + "}", parser_class=_Parser)
    sub.required = True
    wanted = _wanted_commands(argv)
    for name, module in COMMANDS.items():
        if wanted is not None and name not in wanted and name not in CORE:  # a placeholder, its module unimported
            sub.add_parser(name, help=f"(see 'warpsim {name} --help')", add_help=False).add_argument(
                "rest", nargs=argparse.REMAINDER)
            continue
        try:
            _command_module(module).add_parser(sub)
        except Exception as exc:  # noqa: BLE001  (a broken command module must not take list/run/info down)
            _BROKEN[name] = f"{type(exc).__name__}: {exc}"
            sub.add_parser(name, help=f"(unavailable: {exc})", add_help=False).add_argument(
                "rest", nargs=argparse.REMAINDER)
    return p


_BROKEN = {}  # command name -> why its module failed to load


def _command_module(path):
    import importlib

    return importlib.import_module(path)


def _silence_stdout(out):
    """After a closed pipe (``warpsim list | head -1``): send further output, including the
    interpreter's final flush, to /dev/null instead of a BrokenPipeError traceback."""
    if out is sys.stdout:
        try:
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
        except (OSError, ValueError):  # pragma: no cover - stdout without a file descriptor
            pass


def main(argv=None, out=None, err=None):
    """Entry point; returns the exit status (0 ok, 1 simulation failed or damaged cache, 2 usage
    mistake: also any ValueError/FileNotFoundError/PermissionError before the simulation starts)."""
    out = out or sys.stdout
    err = err or sys.stderr
    argv = list(sys.argv[1:] if argv is None else argv)
    verbose = "--verbose" in argv
    argv = [a for a in argv if a != "--verbose"]  # a global flag, wherever it stands
    try:
        choose_warp_verbosity(True if verbose else None)  # applied where a command imports Warp
        args = _parser(argv).parse_args(argv)
        if args.command in _BROKEN:
            print(f"warpsim: error: the '{args.command}' command failed to load ({one_line(_BROKEN[args.command])})",
                  file=err)
            return 1
        command = _command_module(COMMANDS[args.command])
        if getattr(command, "READ_ONLY", False):
            status = command.run(args, out, err)
        else:
            from .usd.lock import command_scope

            with command_scope():  # the outputs' locks (warpsim.usd.lock) end with the command
                status = command.run(args, out, err)
        out.flush()  # a closed pipe shows up here, not in the interpreter's exit
        return status
    except UsageError as exc:
        print(f"warpsim: error: {one_line(exc)}", file=err)
        return 2
    except BrokenPipeError:
        _silence_stdout(out)
        return 0
    except (ValueError, OSError) as exc:  # bad values and files found before the simulation starts
        from .usd.pxr_errors import error_line

        print(f"warpsim: error: {error_line(exc)}", file=err)
        return int(getattr(exc, "exit_status", 2))  # a damaged record or manifest: 1
    except Exception as exc:  # noqa: BLE001  (a USD library error that escaped: one line, never a bare type name)
        if not (type(exc).__module__.startswith("pxr") or "pxrInternal" in str(exc)):
            raise
        from .usd.pxr_errors import error_line

        print(f"warpsim: error: {error_line(exc)}", file=err)
        return 1
    except SystemExit as exc:  # --help
        return exc.code if isinstance(exc.code, int) else 0
    except KeyboardInterrupt:  # 130 = 128 + SIGINT, as shells report it (Ctrl-C while serving: view exits 0)
        kept = "" if argv and argv[0] in ("view", "list", "info") else "; the frames written so far are kept"
        print(f"warpsim: interrupted{kept}", file=err)  # the viewer writes only recordings, completed on stop
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
