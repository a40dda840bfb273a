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
import math
import os
import sys
import time

from .cli_common import UsageError
from .cli_common import device_arg as _device
from .verbosity import choose_warp_verbosity, set_warp_verbosity

__all__ = ["COMMANDS", "UsageError", "main"]

COMMANDS = {
    "view": "warpsim.viewer.command",
    "render": "warpsim.render.command",
    "plot": "warpsim.render.plot",
    "sweep": "warpsim.sweeps.command",
    "query": "warpsim.sweeps.query_command",
    "pick": "warpsim.browse.pick",
    "export": "warpsim.render.export_command",
}
"""Sub-commands beyond list/run/info, by name -> module path. A command module (e.g.
``warpsim.viewer.command``) defines ``add_parser(sub)`` (adds its sub-parser to argparse's
sub-parsers; imports nothing heavy) and ``run(args, out, err) -> int`` (exit status; raise
:class:`UsageError` for a usage mistake, reported as one line with exit 2). Reuse this module's
``_parse_sets``, ``_timing`` and ``_device`` for scene names, ``--set`` and ``--device``."""


class _Parser(argparse.ArgumentParser):
    def error(self, message):
        raise UsageError(message)


def _wanted_commands(argv):
    """Command modules the parser must import for ``argv``: none for list/run/info (so ``warpsim
    info`` starts in a fraction of a second), the one named, or all (help, mistakes)."""
    first = next((a for a in (sys.argv[1:] if argv is None else argv) if not str(a).startswith("-")), None)
    if first in ("list", "run", "info"):
        return set()
    return {first} if first in COMMANDS else None


def _parser(argv=None):
    p = _Parser(prog="warpsim", description="Run warpsim scenes and stream them to USD caches.")
    p.add_argument("--verbose", action="store_true",
                   help="show Warp's start-up banner and kernel-module load lines (also accepted after the command)")
    names = ["list", "run", "info", *COMMANDS]
    sub = p.add_subparsers(dest="command", metavar="{" + ",".join(names) + "}", parser_class=_Parser)
    sub.required = True
    sub.add_parser("list", help="list the scenes and their parameters")
    r = sub.add_parser("run", help="simulate a scene and write a USD cache")
    r.add_argument("scene", help="scene name (see 'warpsim list')")
    r.add_argument("--frames", type=int, default=None,
                   help="frames to simulate after frame 0 (default 120; with --from-sweep: the sweep's)")
    r.add_argument("--fps", type=float, default=None, help="frames per second of the cache (default: the scene's)")
    r.add_argument("--substeps", type=substeps_arg, default=None,
                   help="simulation steps per frame at the scene's frame rate, or 'auto': at least the scene's own "
                        "count and as many as keep each step within half the stability limit (default: the "
                        "scene's). On a scene with a dt parameter N steps split the scene's frame (dt x its own "
                        "steps): the step becomes frame/N, a warning says it overrides dt and --strict refuses; "
                        "with --set dt the two must agree (give --fps too) or the run is refused")
    r.add_argument("--strict", action="store_true",
                   help="exit 2 before running when the time step is above the stability limit or --substeps "
                        "overrides the scene's dt (default: warn)")
    r.add_argument("--integrator", default=None, help="time integrator (scenes with an 'integrator' parameter)")
    r.add_argument("--device", default=None, help="Warp device, e.g. cpu or cuda:0 (default: CUDA when present)")
    r.add_argument("--out", default=None, help="cache to write (.usd/.usda/.usdc; default usd_out/SCENE.usda)")
    r.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE",
                   help="set a scene parameter (repeatable)")
    r.add_argument("--chunk", type=int, default=24, help="frames per chunk file (default 24)")
    r.add_argument("--flatten", action="store_true", help="at the end, replace the chunked cache by one self-contained .usdc "
                   "(--out NAME.usda becomes NAME.usdc; the .usda and its chunk files are removed)")
    r.add_argument("--checkpoint-every", type=int, default=0, metavar="N",
                   help="save the simulation state beside the cache every N frames")
    r.add_argument("--resume", action="store_true", help="continue from the last checkpoint, appending frames")
    r.add_argument("--no-progress", action="store_true", help="no progress bar")
    r.add_argument("--from-sweep", default=None, metavar="ROOT",
                   help="re-run one world of the sweep whose root is ROOT exactly (with --world N)")
    r.add_argument("--world", type=int, default=None, metavar="N", help="the world of --from-sweep to re-run")
    r.add_argument("--preview", default=None, metavar="FILE.gif",
                   help="also render the cache to a .gif/.mp4/.png beside it (at most 300 frames; see 'warpsim render')")
    i = sub.add_parser("info", help="summarise a USD cache")
    i.add_argument("cache", help="path of a .usd/.usda/.usdc file")
    i.add_argument("--verify", action="store_true",
                   help="compare every chunk file's CRC-32 (reads them all; done anyway below 256 MiB)")
    wanted = _wanted_commands(argv)
    for name, module in COMMANDS.items():
        if wanted is not None and name not in wanted:  # not asked for: a placeholder, its module unimported
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


def substeps_arg(text):
    """``--substeps`` value: an int, or "auto" (sub-step inside the stability limit)."""
    if str(text).strip().lower() == "auto":
        return "auto"
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number or 'auto'") from None


def timing_note(timing, strict, err) -> None:
    """The timing's note (``--substeps N`` overriding a scene's dt) as one ``warpsim: warning:``
    line on ``err``, or with ``strict`` a :class:`UsageError` (exit 2)."""
    if not timing.note:
        return
    if strict:
        raise UsageError(f"--strict: {timing.note}")
    print(f"warpsim: warning: {timing.note}", file=err)


def stability_check(scene, frame_dt, substeps, strict, err) -> None:
    """Before the first step: one ``warpsim: warning:`` line on ``err`` when the scene's step is
    above its stability limit (naming the limiter and the remedies), or with ``strict`` a
    :class:`UsageError` (exit 2)."""
    line = scene.stability_warning(frame_dt, substeps)
    if line is None:
        return
    if strict:
        raise UsageError(f"--strict: {line}")
    print(f"warpsim: warning: {line}", file=err)


def _one_line(exc):
    return " ".join(str(exc).split("\n")).strip() or type(exc).__name__


def _command_module(path):
    import importlib

    return importlib.import_module(path)


def _cmd_list(out):
    from .scenes import format_value, scenes

    registry = scenes()
    width = max((len(n) for n in registry), default=0)
    for name, cls in registry.items():
        print(f"{name:<{width}}  {cls.description}", file=out)
        for key, param in cls.params.items():
            choices = f" ({'|'.join(map(str, param.choices))})" if param.choices else ""
            print(f"    {key}={format_value(param.default)}  {param.help}{choices}", file=out)
    print("\nRun one with: warpsim run SCENE [--frames N] [--set KEY=VALUE ...]", file=out)
    return 0


def _cmd_info(path, out, err=None, verify=False):
    from .usd.validate import cache_info

    if os.path.isdir(path):
        raise UsageError(f"{path!r} is a folder; give the cache file in it (.usd, .usda or .usdc)")
    if os.path.exists(path) and not os.path.isfile(path):  # reading a FIFO would wait for a writer for ever
        raise UsageError(f"{path!r} is not a regular file (a pipe, socket or device); give the cache file itself")
    staged = _staged_sweep_note(path)
    if staged is not None and not os.path.exists(path):  # a first sweep killed before it published anything
        print(staged, file=out)
        print(f"warpsim: error: {path} is not written yet: {staged.split(': ', 1)[1]}", file=err or sys.stderr)
        return 1
    try:
        info = cache_info(path, verify=True if verify else None)
    except FileNotFoundError as exc:  # checks.MissingFileError (not imported here: it would load Warp)
        raise UsageError(str(exc)) from None
    except ValueError as exc:  # the root layer itself is damaged
        print(f"warpsim: error: {_one_line(exc)}", file=err or sys.stderr)
        return 1
    if info["frames"]:
        span = f"frames {info['start']}..{info['end']} ({info['frames']} frames at {info['fps']:g} fps, " \
               f"{(info['frames'] - 1) / info['fps']:.3g} s)"
    else:
        span = "no frames"
    print(f"{info['path']}: {span}", file=out)
    if staged is not None:  # a later sweep into this root was interrupted: the result above is the older one
        print(staged.replace("a sweep ", "a newer sweep ", 1), file=out)
    writing = _writer_note(path)
    if writing:
        print(writing, file=out)
    for prim in info["prims"]:
        count = prim.get("count")
        count = "" if count is None else (f"  count {count[0]}" if count[0] == count[1] else
                                          f"  count {count[0]}..{count[1]}")
        bounds = prim.get("bounds")
        bounds = "" if bounds is None else "  bounds [" + ", ".join(f"{v:.4g}" for v in bounds[0]) + "] .. [" + \
            ", ".join(f"{v:.4g}" for v in bounds[1]) + "]"
        kind = "animated" if prim["animated"] else "static"
        print(f"  {prim['path']:<28} {prim['type']:<15} {kind:<8}{count}{bounds}", file=out)
    damaged = info.get("damaged")
    if not damaged:
        return 0
    readable = ", ".join(f"{a}..{b}" for a, b in info["readable"]) or "none"
    print(f"DAMAGED: {len(damaged)} chunk file(s) (checked: {info['checked']}); counts and bounds above cover the "
          "readable frames only", file=out)
    for fname, start, end, why in damaged:
        print(f"  {fname}  frames {start}..{end}: {why}", file=out)
    print(f"readable frames: {readable}", file=out)
    print(f"warpsim: error: {path}: {len(damaged)} damaged chunk file(s) (first: {damaged[0][0]}, frames "
          f"{damaged[0][1]}..{damaged[0][2]}, {damaged[0][3]}); readable frames {readable}", file=err or sys.stderr)
    return 1


def _writer_note(path):
    """A line when a live process on this host holds the lock of ``path`` (the cache is still being
    written: the frames above are the ones completed so far), else None."""
    import socket

    from .usd.lock import lock_info, lock_path, pid_alive

    holder = lock_info(lock_path(path)) or {}
    if holder.get("host") != socket.gethostname() or not pid_alive(holder.get("pid")) or \
            holder.get("pid") == os.getpid():
        return None
    return f"being written by pid {holder['pid']} ('{str(holder.get('command') or '')[:120]}'): the frames above are " \
        "the ones completed so far"


def _staged_sweep_note(path):
    """One line on the interrupted sweep staged for root ``path`` (its staged layer, completed
    frames, how to continue), or None when none is staged."""
    from .sweeps.staging import staged_sweep

    staged = staged_sweep(path)
    if staged is None:
        return None
    rel = os.path.relpath
    settings = staged["settings"]
    what = f"of scene {settings['scene']!r} " if settings.get("scene") else ""
    if staged["why"]:
        return f"{rel(path)}: a sweep {what}into it was interrupted, but {staged['why']}; run the sweep again"
    frames = ", ".join(f"{a}..{b}" for a, b in staged["frames"]) or "none"
    total = settings.get("frames")
    of = f" of 0..{total}" if isinstance(total, int) else ""
    damaged = f" ({len(staged['damaged'])} damaged chunk file(s))" if staged["damaged"] else ""
    import socket

    from .usd.lock import lock_info, lock_path, pid_alive

    holder = lock_info(lock_path(path)) or {}  # the sweep's lock file names its command (stale once killed)
    if holder.get("host") == socket.gethostname() and pid_alive(holder.get("pid")) and holder.get("pid") != os.getpid():
        return (f"{rel(path)}: a sweep {what}into it is running (pid {holder['pid']}): its staged layer "
                f"{rel(staged['layer'])} holds completed frames {frames}{of} so far")
    cmd = str(holder.get("command") or "")
    again = "the same 'warpsim sweep ...' options and --resume"
    if cmd.startswith("warpsim sweep"):
        again = f"'{cmd}{'' if ' --resume' in cmd else ' --resume'}'"
    return (f"{rel(path)}: a sweep {what}into it was interrupted: its staged layer {rel(staged['layer'])} holds "
            f"completed frames {frames}{of}{damaged}; continue it with {again}, or run it again without --resume")


def _parse_sets(cls, sets, integrator):
    """{key: typed value} from --set KEY=VALUE items (and --integrator)."""
    from .scenes import close_matches, parse_value

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


def _timing(cls, params, given, fps, substeps):
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


def checkpoint_path(cache_path):
    """The checkpoint file kept beside a cache: ``<stem>.checkpoint.npz``."""
    return os.path.splitext(os.path.abspath(cache_path))[0] + ".checkpoint.npz"


def _cmd_run(args, out, err):
    set_warp_verbosity()  # no kernel-cache chatter between the progress bar and the result (unless --verbose)
    from .usd.checkpoint import META_KEYS, load_checkpoint, save_checkpoint
    from .core.errors import SimulationError
    from .scenes import get_scene
    from .usd.writer import ROOT_EXTENSIONS, UsdCacheWriter

    try:
        cls = get_scene(args.scene)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    if args.from_sweep is not None or args.world is not None:  # one world of a sweep, exactly
        from .sweeps.rerun import run_command

        return run_command(args, out, err)
    if args.frames is None:
        args.frames = 120
    if args.frames < 0:
        raise UsageError(f"--frames {args.frames}: it must be >= 0")
    if args.chunk < 1:
        raise UsageError(f"--chunk {args.chunk}: it must be >= 1")
    if args.checkpoint_every < 0:
        raise UsageError(f"--checkpoint-every {args.checkpoint_every}: it must be >= 0")
    path = args.out or os.path.join("usd_out", f"{cls.name}.usda")
    if os.path.splitext(path)[1] not in ROOT_EXTENSIONS:
        raise UsageError(f"--out {path!r} must end in .usd, .usda or .usdc")
    _check_out(path)
    _hold_output(path)
    if args.preview is not None:
        from .extras import render_modules, require_extra
        from .render.output import check_out

        require_extra("render", f"--preview {args.preview}", render_modules(args.preview))  # before simulating
        try:
            check_out(os.path.join(os.path.dirname(path), args.preview))
        except (ValueError, OSError) as exc:
            raise UsageError(f"--preview: {exc}") from None
    given = _parse_sets(cls, args.sets, args.integrator)
    ckpt_file = checkpoint_path(path)
    start = 0
    ckpt = None
    if args.resume:
        if not os.path.exists(ckpt_file):
            raise UsageError(f"--resume: no checkpoint {ckpt_file}; run with --checkpoint-every N first")
        try:
            arrays, meta = load_checkpoint(ckpt_file, required=META_KEYS)
        except ValueError as exc:
            raise UsageError(f"--resume: {_one_line(exc)}") from None
        if meta["scene"] != cls.name:
            raise UsageError(f"--resume: the checkpoint is of scene {meta['scene']!r}, not {cls.name!r}")
        for key, value in given.items():
            saved = meta["params"].get(key)
            if (list(value) if isinstance(value, tuple) else value) != saved:
                raise UsageError(f"--resume: {key}={value} differs from the checkpoint's {key}={saved}; "
                                 "a resumed run keeps the parameters it started with")
        given = {k: tuple(v) if isinstance(v, list) else v for k, v in meta["params"].items()}
        ckpt = (arrays, meta)
        start = int(meta["frame"]) + 1
        fps, substeps = float(meta["fps"]), int(meta["substeps"])
        auto = bool(meta.get("auto_substeps", False))
        if args.fps is not None and not math.isclose(args.fps, fps) or args.substeps not in (
                None, substeps, "auto" if auto else None):
            raise UsageError(f"--resume: the checkpoint was made at {fps:g} fps with {substeps} substeps")
        params = cls.resolve_params(given)
        from .scenes.timing import FrameTiming

        frame_dt = float(meta["frame_dt"]) if "frame_dt" in meta else \
            params["dt"] * substeps if "dt" in params else 1.0 / fps  # checkpoints made before frame_dt was kept
        timing = FrameTiming(fps=fps, frame_dt=frame_dt, steps=substeps, step_dt=frame_dt / substeps,
                             chosen="auto" if auto else "by hand", fixed=not auto)
    else:
        params = cls.resolve_params(given)
        timing, params = _timing(cls, params, given, args.fps, args.substeps)
        timing_note(timing, args.strict, err)
        fps, substeps, auto = timing.fps, timing.steps, timing.auto
    device = _device(args.device)
    try:
        scene = cls(params, device=device)
    except ValueError as exc:
        raise UsageError(f"scene {cls.name!r}: {exc}") from None
    if ckpt is not None:
        try:
            scene.restore(ckpt[0])
        except (ValueError, KeyError, TypeError, IndexError) as exc:
            raise UsageError(f"--resume: checkpoint {ckpt_file} does not fit scene {cls.name!r} ({type(exc).__name__}: "
                             f"{_one_line(exc)}); run again without --resume") from None
    if start > args.frames + 1:
        raise UsageError(f"--resume: the checkpoint is at frame {start - 1}, beyond --frames {args.frames}")
    # the one timing (warpsim.scenes.timing): frames frame_dt apart, `substeps` steps each (automatic
    # timing: at least that many, within half the stability limit)
    frame_dt = timing.frame_dt
    scene.use_timing(timing)
    stability_check(scene, frame_dt, substeps, args.strict, err)
    from .sweeps.preflight import frame_time_note, steps_note

    note = steps_note(scene, frame_dt, substeps, args.frames + 1 - max(start, 1))  # many steps: said now, with the figure
    if note:
        print(f"warpsim: note: {note}", file=err)
    try:
        from .usd.writer import settings_run_id

        run_id = settings_run_id({"scene": cls.name, "params": params, "fps": fps, "frame_dt": frame_dt,
                                  "steps": substeps, "auto": auto, "frames": args.frames, "chunk": args.chunk,
                                  "device": str(device)})  # runs that differ tell their chunks apart in 'info'
        writer = UsdCacheWriter(path, fps=fps, chunk_size=args.chunk, flatten=args.flatten,
                                resume_frame=start if args.resume else None, run_id=run_id)
        scene.declare(writer)
        writer.begin()
    except ValueError as exc:
        raise UsageError(f"--resume: {exc}" if args.resume else str(exc)) from None
    if not args.resume and os.path.exists(ckpt_file):
        os.remove(ckpt_file)  # it described the cache this run replaces

    def save(frame):
        writer.flush()  # the cache holds every frame up to the checkpoint before it exists
        save_checkpoint(ckpt_file, scene.checkpoint(), {
            "scene": cls.name, "frame": frame, "fps": fps, "substeps": substeps, "auto_substeps": auto,
            "frame_dt": frame_dt,
            "params": {k: list(v) if isinstance(v, tuple) else v for k, v in params.items()}})

    progress = None
    if not args.no_progress:
        from tqdm import tqdm

        progress = tqdm(total=args.frames + 1, initial=start, unit="frame", desc=cls.name, file=err,
                        dynamic_ncols=True)
    frame = start
    t0 = time.perf_counter()
    import warnings

    from .core.stability import StabilityWarning

    warnings.simplefilter("ignore", StabilityWarning)  # said once above, as one line
    try:
        with writer:
            try:
                if start == 0:
                    writer.write_frame(0, scene.frame_data())
                    if progress:
                        progress.update(1)
                for frame in range(max(start, 1), args.frames + 1):
                    t_frame = time.perf_counter()
                    scene.advance(frame_dt, substeps)
                    if frame == max(start, 1):  # a slow first frame: the whole run's time, with the figure
                        note = frame_time_note(time.perf_counter() - t_frame, args.frames - frame, device)
                        if note:
                            (progress.write if progress else lambda s: print(s, file=err))(f"warpsim: note: {note}")
                    writer.write_frame(frame, scene.frame_data())
                    if progress:
                        progress.update(1)
                    if args.checkpoint_every and (frame % args.checkpoint_every == 0 or frame == args.frames):
                        save(frame)
            except (SimulationError, ValueError, OSError) as exc:  # the frame could not be written (disk full)
                if progress:
                    progress.close()
                    progress = None
                writer.close()
                kept = f"frames {writer.chunks[0][0]}..{writer.chunks[-1][1]}" if writer.chunks else "no frames"
                from .usd.pxr_errors import error_line

                msg = error_line(exc) if isinstance(exc, OSError) else str(exc)  # no bare "[Errno 28]"
                if not msg.startswith("frame"):
                    msg = f"frame {frame}: {msg}"
                print(f"warpsim: simulation failed at {msg}\nwarpsim: kept {kept} in {writer.output_path}", file=err)
                return 1
    finally:
        if progress:
            progress.close()
    seconds = time.perf_counter() - t0
    written = args.frames + 1 - start
    print(f"wrote {written} frames ({start}..{args.frames}, {written / max(seconds, 1e-9):.1f} frames/s) "
          f"of scene {cls.name!r} on {device}", file=out)
    print(f"open: {os.path.relpath(writer.output_path)}   (e.g. usdview {os.path.relpath(writer.output_path)})",
          file=out)
    if args.preview is not None:  # rendered from the cache just written; a relative name lands beside it
        from .render.command import render_to

        preview = os.path.join(os.path.dirname(writer.output_path), args.preview)
        result = render_to(writer.output_path, preview, err, device=device, progress=not args.no_progress,
                           max_frames=300)  # long runs: every k-th frame, played in real time
        print(f"preview: {os.path.relpath(result['path'])} ({result['frames']} frames, {result['seconds']:.2f} s)",
              file=out)
    return 0


def _hold_output(path, flag="--out", inputs=(), own=None):
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


def _check_out(path, flag="--out"):
    """Create the folder of ``--out`` (or another output option ``flag``) and make sure a file
    can be written there, so an unusable path is one line and exit 2 before the scene is built."""
    import tempfile

    if os.path.isdir(path):
        raise UsageError(f"{flag} {path!r} is a folder; name a file in it, e.g. "
                         f"{os.path.join(path, 'scene' + (os.path.splitext(path)[1] or '.usda'))!r}")
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
            print(f"warpsim: error: the '{args.command}' command failed to load ({_one_line(_BROKEN[args.command])})",
                  file=err)
            return 1
        if args.command == "list":
            status = _cmd_list(out)
        elif args.command == "info":
            status = _cmd_info(args.cache, out, err, args.verify)
        else:
            from .usd.lock import command_scope

            with command_scope():  # the outputs' locks (warpsim.usd.lock) end with the command
                if args.command in COMMANDS:
                    status = _command_module(COMMANDS[args.command]).run(args, out, err)
                else:
                    status = _cmd_run(args, out, err)
        out.flush()  # a closed pipe shows up here, not in the interpreter's exit
        return status
    except UsageError as exc:
        print(f"warpsim: error: {_one_line(exc)}", file=err)
        return 2
    except BrokenPipeError:
        _silence_stdout(out)
        return 0
    except (ValueError, OSError) as exc:  # bad values and files found before the simulation starts
        from .usd.pxr_errors import error_line

        print(f"warpsim: error: {error_line(exc)}", file=err)
        return int(getattr(exc, "exit_status", 2))  # a damaged record or manifest: 1
    except SystemExit as exc:  # --help
        return exc.code if isinstance(exc.code, int) else 0
    except KeyboardInterrupt:  # 130 = 128 + SIGINT, as shells report it (Ctrl-C while serving: view exits 0)
        kept = "" if argv and argv[0] in ("view", "list", "info") else "; the frames written so far are kept"
        print(f"warpsim: interrupted{kept}", file=err)  # the viewer writes only recordings, completed on stop
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
