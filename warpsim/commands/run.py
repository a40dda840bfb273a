"""``warpsim run SCENE``: simulate a scene and stream it to a USD cache (chunk files, optional
checkpoints beside it, ``--resume`` from the last one, ``--preview`` rendered at the end);
``--from-sweep ROOT --world N`` re-runs one world of a sweep alone
(:func:`warpsim.sweeps.rerun.run_command`). Exit status: 2 for a usage mistake (one line, before
any simulation), 1 when the simulation fails (the frames written so far stay readable)."""
from __future__ import annotations

import math
import os
import time

from ..cli_common import (
    UsageError,
    check_output_path,
    device_arg,
    hold_output,
    one_line,
    parse_sets,
    stability_check,
    substeps_arg,
    timing_from_flags,
    timing_note,
)
from ..verbosity import set_warp_verbosity

__all__ = ["add_parser", "checkpoint_path", "run"]


def add_parser(sub):
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
    r.add_argument("--out", default=None, help="cache to write (.usd/.usda/.usdc); a relative path is taken from "
                   "the current folder (default usd_out/SCENE.usda)")
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
    r.add_argument("--preview", nargs="?", const="", default=None, metavar="FILE.gif",
                   help="also render the cache to a .gif/.mp4/.png (at most 300 frames; see 'warpsim render'); a "
                        "relative path is taken from the current folder (--preview alone: beside the cache, its name "
                        "with .gif)")


def checkpoint_path(cache_path):
    """The checkpoint file kept beside a cache: ``<stem>.checkpoint.npz``."""
    return os.path.splitext(os.path.abspath(cache_path))[0] + ".checkpoint.npz"


def run(args, out, err):
    set_warp_verbosity()  # no kernel-cache chatter between the progress bar and the result (unless --verbose)
    from ..scenes import get_scene

    try:
        cls = get_scene(args.scene)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    if args.from_sweep is not None or args.world is not None:  # one world of a sweep, exactly
        from ..sweeps.rerun import run_command

        return run_command(args, out, err)
    path = _checked_output(args, cls)
    given = parse_sets(cls, args.sets, args.integrator)
    ckpt_file = checkpoint_path(path)
    if args.resume:
        ckpt, start, params, timing = _resumed(args, cls, given, ckpt_file)
    else:
        ckpt, start = None, 0
        params = cls.resolve_params(given)
        timing, params = timing_from_flags(cls, params, given, args.fps, args.substeps)
        timing_note(timing, args.strict, err)
    device = device_arg(args.device)
    scene = _built_scene(cls, params, device, ckpt, ckpt_file)
    if start > args.frames + 1:
        raise UsageError(f"--resume: the checkpoint is at frame {start - 1}, beyond --frames {args.frames}")
    # the one timing (warpsim.scenes.timing): frames frame_dt apart, `substeps` steps each (automatic
    # timing: at least that many, within half the stability limit)
    scene.use_timing(timing)
    stability_check(scene, timing.frame_dt, timing.steps, args.strict, err)
    from ..sweeps.preflight import steps_note

    note = steps_note(scene, timing.frame_dt, timing.steps, args.frames + 1 - max(start, 1))  # said now, with the figure
    if note:
        print(f"warpsim: note: {note}", file=err)
    writer = _open_writer(args, cls, scene, path, params, timing, device, start)
    if not args.resume and os.path.exists(ckpt_file):
        os.remove(ckpt_file)  # it described the cache this run replaces
    t0 = time.perf_counter()
    if _simulate(args, cls, scene, writer, timing, start, (ckpt_file, params), device, err):
        return 1
    seconds = time.perf_counter() - t0
    _report(args, cls, writer, start, seconds, device, out, err)
    return 0


def _checked_output(args, cls):
    """The cache path of ``--out`` (default ``usd_out/SCENE.usda``) once the frame, chunk and
    checkpoint counts are valid, its folder writable, it is held by this command and a
    ``--preview`` can be written; UsageError otherwise."""
    from ..usd.writer import ROOT_EXTENSIONS

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
    check_output_path(path)
    hold_output(path)
    if args.preview is not None:
        from ..extras import render_modules, require_extra
        from ..render.command import preview_target
        from ..render.output import check_out

        preview = preview_target(args.preview, path)
        require_extra("render", f"--preview {preview}", render_modules(preview))  # before simulating
        try:
            check_out(preview, "--preview")
        except (ValueError, OSError) as exc:
            raise UsageError(str(exc)) from None
    return path


def _resumed(args, cls, given, ckpt_file):
    """(checkpoint (arrays, meta), first frame, params, timing) of ``--resume``: the parameters and
    timing the run started with; UsageError when the flags or ``--set`` values differ from them."""
    from ..scenes.timing import FrameTiming
    from ..usd.checkpoint import META_KEYS, load_checkpoint

    if not os.path.exists(ckpt_file):
        raise UsageError(f"--resume: no checkpoint {ckpt_file}; run with --checkpoint-every N first")
    try:
        arrays, meta = load_checkpoint(ckpt_file, required=META_KEYS)
    except ValueError as exc:
        raise UsageError(f"--resume: {one_line(exc)}") from None
    if meta["scene"] != cls.name:
        raise UsageError(f"--resume: the checkpoint is of scene {meta['scene']!r}, not {cls.name!r}")
    for key, value in given.items():
        saved = meta["params"].get(key)
        if (list(value) if isinstance(value, tuple) else value) != saved:
            raise UsageError(f"--resume: {key}={value} differs from the checkpoint's {key}={saved}; "
                             "a resumed run keeps the parameters it started with")
    given = {k: tuple(v) if isinstance(v, list) else v for k, v in meta["params"].items()}
    start = int(meta["frame"]) + 1
    fps, substeps = float(meta["fps"]), int(meta["substeps"])
    auto = bool(meta.get("auto_substeps", False))
    if args.fps is not None and not math.isclose(args.fps, fps) or args.substeps not in (
            None, substeps, "auto" if auto else None):
        raise UsageError(f"--resume: the checkpoint was made at {fps:g} fps with {substeps} substeps")
    params = cls.resolve_params(given)
    frame_dt = float(meta["frame_dt"]) if "frame_dt" in meta else \
        params["dt"] * substeps if "dt" in params else 1.0 / fps  # checkpoints made before frame_dt was kept
    timing = FrameTiming(fps=fps, frame_dt=frame_dt, steps=substeps, step_dt=frame_dt / substeps,
                         chosen="auto" if auto else "by hand", fixed=not auto)
    return (arrays, meta), start, params, timing


def _built_scene(cls, params, device, ckpt, ckpt_file):
    """The scene on ``device``, restored from the checkpoint ``ckpt`` when resuming; UsageError
    naming the scene or the checkpoint when they do not fit."""
    try:
        scene = cls(params, device=device)
    except ValueError as exc:
        raise UsageError(f"scene {cls.name!r}: {exc}") from None
    except (MemoryError, RuntimeError) as exc:  # a size no check of the scene's caught: one line, not a traceback
        text = one_line(exc)
        if not isinstance(exc, MemoryError) and "allocate" not in text:
            raise
        sizes = ", ".join(f"{k}={v}" for k, v in params.items() if isinstance(v, int) and not isinstance(v, bool))
        raise UsageError(f"scene {cls.name!r}: out of memory while building ({text}); lower its sizes"
                         f"{f' ({sizes})' if sizes else ''}, or free memory") from None
    if ckpt is not None:
        try:
            scene.restore(ckpt[0])
        except (ValueError, KeyError, TypeError, IndexError) as exc:
            raise UsageError(f"--resume: checkpoint {ckpt_file} does not fit scene {cls.name!r} ({type(exc).__name__}: "
                             f"{one_line(exc)}); run again without --resume") from None
    return scene


WORKER_RUN_BYTES = 1 << 30
"""A run on a GPU writing at least this many bytes [bytes] has a worker process author its chunks."""


def _write_workers(device, scene, frames) -> int:
    """Worker processes authoring a run's chunk files: one on a GPU when the run writes at least
    :data:`WORKER_RUN_BYTES` (its first frame's arrays times its frames), where writing would hold
    up the stepping (measured on an H200: ``dam_break`` and ``smoke``, 63 and 32 MB over 120 frames,
    ran 1.4x slower with a worker: it starts, and shares the host); none on the CPU, whose cores
    step. The frames are the same bytes either way; ``WARPSIM_WRITE_WORKERS=N`` sets the count."""
    import warp as wp

    from ..process_pool import default_workers, forced_workers

    forced = forced_workers()
    if forced is not None:
        return forced
    if not wp.get_device(device).is_cuda:
        return 0
    frame = sum(int(getattr(v, "nbytes", 0) or getattr(v, "capacity", 0) or 0)
                for values in scene.frame_data().values() for v in (values or {}).values())
    return min(1, default_workers()) if frame * (int(frames) + 1) >= WORKER_RUN_BYTES else 0


def _open_writer(args, cls, scene, path, params, timing, device, start):
    """The cache writer of ``path`` with the scene's prims declared and begun (``--resume``: from
    frame ``start``); UsageError when the cache cannot be written or resumed."""
    from ..usd.writer import UsdCacheWriter, settings_run_id

    try:
        run_id = settings_run_id({"scene": cls.name, "params": params, "fps": timing.fps,
                                  "frame_dt": timing.frame_dt, "steps": timing.steps, "auto": timing.auto,
                                  "frames": args.frames, "chunk": args.chunk,
                                  "device": str(device)})  # runs that differ tell their chunks apart in 'info'
        writer = UsdCacheWriter(path, fps=timing.fps, chunk_size=args.chunk, flatten=args.flatten,
                                resume_frame=start if args.resume else None, run_id=run_id,
                                workers=_write_workers(device, scene, args.frames))
        scene.declare(writer)
        writer.begin()
    except ValueError as exc:
        raise UsageError(f"--resume: {exc}" if args.resume else str(exc)) from None
    return writer


def _simulate(args, cls, scene, writer, timing, start, checkpoint, device, err):
    """Advance and write frames ``start..args.frames`` (a checkpoint every ``--checkpoint-every``
    frames: ``checkpoint`` = (its path, the run's params)); 0, or 1 after one line on ``err`` when a
    frame fails (the frames written so far are kept and named)."""
    import warnings

    from ..core.errors import SimulationError
    from ..core.stability import StabilityWarning
    from ..sweeps.preflight import frame_time_note
    from ..usd.checkpoint import save_checkpoint

    ckpt_file, params = checkpoint

    def save(frame):
        writer.flush()  # the cache holds every frame up to the checkpoint before it exists
        save_checkpoint(ckpt_file, scene.checkpoint(), {
            "scene": cls.name, "frame": frame, "fps": timing.fps, "substeps": timing.steps,
            "auto_substeps": timing.auto, "frame_dt": timing.frame_dt,
            "params": {k: list(v) if isinstance(v, tuple) else v for k, v in params.items()}})

    progress = None
    if not args.no_progress:
        from tqdm import tqdm

        progress = tqdm(total=args.frames + 1, initial=start, unit="frame", desc=cls.name, file=err,
                        dynamic_ncols=True)
    frame = start
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
                    scene.advance(timing.frame_dt, timing.steps)
                    writer.write_frame(frame, scene.frame_data())
                    if frame == max(start, 1) + 1:  # the whole run's time, estimated from this frame, measured
                        # (stepping and writing): the first frame, which compiles and loads the kernels, is left
                        # out (it may take minutes where the rest run at several frames a second)
                        note = frame_time_note(time.perf_counter() - t_frame, args.frames - frame, device, frame)
                        if note:
                            (progress.write if progress else lambda s: print(s, file=err))(f"warpsim: note: {note}")
                    if progress:
                        progress.update(1)
                    if args.checkpoint_every and (frame % args.checkpoint_every == 0 or frame == args.frames):
                        save(frame)
            except (SimulationError, ValueError, OSError) as exc:  # the frame could not be written (disk full)
                if progress:
                    progress.close()
                    progress = None
                from ..core.safe_files import disk_full

                if disk_full(exc) is None:
                    writer.close()
                else:  # the disk takes no more: closing writes nothing new, and may fail the same way
                    try:
                        writer.close()
                    except OSError:
                        pass
                _failed(writer, frame, exc, err)
                return 1
    finally:
        if progress:
            progress.close()
    return 0


def _failed(writer, frame, exc, err):
    """The two lines of a run that failed at ``frame``: why, and the frames kept in the cache."""
    from ..core.safe_files import disk_full
    from ..usd.pxr_errors import error_line
    from ..usd.writer import CacheWriteError

    if isinstance(exc, CacheWriteError):  # one line: the file, why, the frames kept
        print(f"warpsim: error: frame {frame} could not be written: {exc}", file=err)
        return
    kept = f"frames {writer.chunks[0][0]}..{writer.chunks[-1][1]}" if writer.chunks else "no frames"
    msg = error_line(exc) if isinstance(exc, OSError) else str(exc)  # no bare "[Errno 28]"
    if not msg.startswith("frame"):
        msg = f"frame {frame}: {msg}"
    if disk_full(exc) is not None:  # e.g. the checkpoint beside the cache: one line
        print(f"warpsim: error: {msg}; kept {kept} in {os.path.relpath(writer.output_path)} (readable)", file=err)
        return
    print(f"warpsim: simulation failed at {msg}\nwarpsim: kept {kept} in {writer.output_path}", file=err)


def open_hint(path) -> str:
    """How to look at the cache ``path``: ``warpsim view`` (works wherever warpsim does), Blender's
    importer, and where ``usdview`` comes from (pip's usd-core has no usdview)."""
    return (f"e.g. warpsim view {os.path.relpath(path)}, or Blender: File > Import > Universal Scene Description; "
            "usdview comes with NVIDIA's prebuilt USD or a USD build, not with pip's usd-core")


def _report(args, cls, writer, start, seconds, device, out, err):
    """The result lines on ``out`` (frames written, speed, the file to open) and the ``--preview``
    rendered from the cache just written (``render.command.preview_target``)."""
    written = args.frames + 1 - start
    print(f"wrote {written} frames ({start}..{args.frames}, {written / max(seconds, 1e-9):.1f} frames/s) "
          f"of scene {cls.name!r} on {device}", file=out)
    print(f"open: {os.path.relpath(writer.output_path)}   ({open_hint(writer.output_path)})", file=out)
    if args.preview is not None:
        from ..render.command import preview_target, render_to

        preview = preview_target(args.preview, writer.output_path)
        result = render_to(writer.output_path, preview, err, device=device, progress=not args.no_progress,
                           max_frames=300, flag="--preview")  # long runs: every k-th frame, played in real time
        print(f"preview: {os.path.relpath(result['path'])} ({result['frames']} frames, {result['seconds']:.2f} s)",
              file=out)
