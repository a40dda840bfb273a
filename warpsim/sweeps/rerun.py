"""Re-running one world of a sweep exactly: ``warpsim run SCENE --from-sweep ROOT --world N``,
``warpsim sweep ... --rerun N`` and :func:`rerun_world`.

A sweep writes a manifest beside its root (``<stem>.sweep.json``): the warpsim version, the
scene and its defaults (parameter defaults, fps, substeps), frames, the ``--fps`` / ``--substeps``
given, the device, ``fused``, and every world's parameters as the batch received them. A re-run
builds a batch of world N alone whose tiling base and plan come from the whole sweep
(``WorldBatch(reference_params=...)``), so world N gets the same arrays as in the sweep; springs
and cloth sum per particle in a fixed order and every other stage acts per particle or per world,
so its steps give the same bits, and its cache (a plain ``warpsim run`` cache) holds the same
samples as ``/Worlds/world_N`` of the sweep, bit for bit, on the same device. Another device,
``--fps`` or ``--substeps`` runs but warns that the result will differ.

Bad input raises ValueError with one line (the command line exits 2): a root without a
manifest, a manifest of another warpsim version or of changed scene defaults, a world out of
range.
"""
from __future__ import annotations

import json
import math
import os

from ..cli_common import UsageError, device_arg, one_line
from ..core.safe_files import open_temporary

__all__ = ["manifest_path", "pick_or_rerun", "read_manifest", "rerun_world", "run_world", "write_manifest"]

FORMAT = "warpsim-sweep"
MANIFEST_VERSION = 1


def manifest_path(root) -> str:
    """The manifest kept beside a sweep root: ``<stem>.sweep.json``."""
    return os.path.splitext(os.path.abspath(os.fspath(root)))[0] + ".sweep.json"


def world_cache_path(root, world: int) -> str:
    """Default cache of a re-run world, beside the root: ``<stem>.world_NNNNNN.usda``."""
    return os.path.splitext(os.fspath(root))[0] + f".world_{int(world):06d}.usda"


def _json_value(value):
    if isinstance(value, (tuple, list)):
        return [_json_value(v) for v in value]
    if hasattr(value, "item"):  # NumPy scalars
        return value.item()
    return value


def scene_defaults(cls) -> dict:
    """What a scene gives a run when nothing is set: parameter defaults, fps and substeps."""
    return {"fps": float(cls.fps), "substeps": int(cls.substeps),
            "params": {k: _json_value(p.default) for k, p in cls.params.items()}}


def _typed(cls, params: dict) -> dict:
    """JSON lists back to tuples where the scene's default is a tuple or list."""
    out = {}
    for k, v in params.items():
        default = cls.params[k].default if k in cls.params else None
        out[k] = tuple(v) if isinstance(v, list) and isinstance(default, (tuple, list)) else v
    return out


def write_manifest(root, scene_name, world_params, *, frames, fps=None, substeps=None, device=None,
                   fused=False, frame_steps=None) -> str:
    """Write the manifest of the sweep whose root is ``root``; ``world_params`` as given to
    :func:`warpsim.sweeps.sweep.run_batch`, ``fps`` / ``substeps`` as given (None: the scene's),
    ``frame_steps`` the steps each frame took (``run_batch``'s ``timing``; auto sub-steps are
    resolved over all worlds, so a world alone must be told). Returns its path."""
    from .._version import __version__
    from ..scenes import get_scene

    from .sweep import sweep_timing

    cls = get_scene(scene_name)
    timing = sweep_timing(cls, _typed(cls, world_params[0]), fps, substeps)
    run_fps, run_substeps = timing.fps, timing.steps
    data = {"format": FORMAT, "version": MANIFEST_VERSION, "warpsim": __version__, "scene": cls.name,
            "defaults": scene_defaults(cls), "frames": int(frames),
            "fps": None if fps is None else float(fps),
            "substeps": None if substeps is None else ("auto" if substeps == "auto" else int(substeps)),
            "run_fps": run_fps, "run_substeps": run_substeps,
            "device": None if device is None else str(device), "fused": bool(fused),
            "frame_steps": None if frame_steps is None else int(frame_steps),
            "worlds": [{k: _json_value(v) for k, v in p.items()} for p in world_params]}
    path = manifest_path(root)
    tmp = path + ".tmp"
    with open_temporary(tmp) as f:
        json.dump(data, f, indent=1)
    os.replace(tmp, path)
    return path


def read_manifest(root, scene=None) -> dict:
    """The manifest of the sweep at ``root``, checked against this warpsim and the scene's current
    defaults (and against ``scene``, a scene name, when given). ValueError (one line) otherwise."""
    from .._version import __version__
    from ..scenes import get_scene

    root = os.fspath(root)
    path = manifest_path(root)
    if not os.path.exists(path):
        what = "does not exist" if not os.path.exists(root) else "is not a warpsim sweep root"
        raise ValueError(f"{root} {what} (no manifest {os.path.basename(path)} beside it); give the root a "
                         "'warpsim sweep' wrote (sweeps made before re-runs existed must be run again)")
    from ..usd.pxr_errors import DamagedFileError

    if not os.path.isfile(path):  # a FIFO or a folder would block or fail obscurely
        raise ValueError(f"{path} is not a regular file; give the root a 'warpsim sweep' wrote")
    try:
        with open(path, encoding="utf-8") as f:
            data = json.load(f)
    except (OSError, ValueError) as exc:  # UnicodeDecodeError is a ValueError
        raise DamagedFileError(f"sweep manifest {path} is damaged or not a manifest ({type(exc).__name__}: "
                               f"{str(exc)[:80]}); run the sweep again") from None
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise DamagedFileError(f"sweep manifest {path} is not a warpsim sweep manifest (field 'format' is "
                               f"{data.get('format') if isinstance(data, dict) else None!r}); run the sweep again")
    check_manifest_fields(data, path)
    if data.get("warpsim") != __version__:
        raise ValueError(f"the sweep {root} was made by warpsim {data.get('warpsim')}, this is {__version__}: "
                         "its worlds would not re-run exactly; run the sweep again with this version")
    try:  # before any advice to run it: a manifest naming no known scene is damaged (or from another install)
        cls = get_scene(data["scene"])
    except ValueError:
        raise DamagedFileError(f"sweep manifest {path}: field 'scene' is {data.get('scene')!r}, a scene this warpsim "
                               "does not have ('warpsim list' shows them); the manifest is damaged or from another "
                               "installation: run the sweep again") from None
    if scene is not None and scene != data.get("scene"):
        raise ValueError(f"the sweep {root} is of scene {data.get('scene')!r}, not {scene!r}; give "
                         f"'warpsim run {data.get('scene')} --from-sweep ...'")
    now, then = scene_defaults(cls), data.get("defaults", {})
    if now != then:
        keys = [k for k in sorted(set(now["params"]) | set(then.get("params", {})))
                if now["params"].get(k) != then.get("params", {}).get(k)]
        keys += [k for k in ("fps", "substeps") if now[k] != then.get(k)]
        first = keys[0] if keys else "?"
        old = then.get(first, then.get("params", {}).get(first))
        new = now.get(first, now["params"].get(first))
        raise ValueError(f"scene {cls.name!r} changed since the sweep {root} was made (default {first}: {old!r} then, "
                         f"{new!r} now); its worlds would not re-run exactly: run the sweep again")
    from ..usd.pxr_errors import DamagedFileError

    for i, p in enumerate(data["worlds"]):
        unknown = [k for k in p if k not in cls.params]
        if unknown:
            raise DamagedFileError(f"sweep manifest {path}: field 'worlds'[{i}] names {unknown[0]!r}, not a parameter "
                                   f"of scene {cls.name!r}; the manifest is damaged: run the sweep again")
        try:
            cls.resolve_params(_typed(cls, p))
        except (ValueError, TypeError) as exc:
            raise DamagedFileError(f"sweep manifest {path}: field 'worlds'[{i}]: {' '.join(str(exc).split())}; the "
                                   "manifest is damaged: run the sweep again") from None
    data["cls"] = cls
    data["worlds"] = [_typed(cls, p) for p in data["worlds"]]
    return data


def _whole(value, low) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= low


def _rate(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and value > 0


_MANIFEST_FIELDS = {  # field -> (check, what it must be)
    "scene": (lambda v: isinstance(v, str) and bool(v), "a scene name"),
    "frames": (lambda v: _whole(v, 0), "a whole number >= 0"),
    "fps": (lambda v: v is None or _rate(v), "null or a rate > 0 [frames/s]"),
    "substeps": (lambda v: v is None or v == "auto" or _whole(v, 1), "null, 'auto' or a whole number >= 1"),
    "run_fps": (_rate, "a rate > 0 [frames/s]"),
    "run_substeps": (lambda v: _whole(v, 1), "a whole number >= 1"),
    "device": (lambda v: v is None or isinstance(v, str) and bool(v.strip()), "null or a device name"),
    "fused": (lambda v: isinstance(v, bool), "true or false"),
    "frame_steps": (lambda v: v is None or _whole(v, 1), "null or a whole number of steps >= 1"),
    "worlds": (lambda v: isinstance(v, list) and bool(v) and all(isinstance(w, dict) for w in v),
               "a non-empty list of parameter objects"),
    "defaults": (lambda v: isinstance(v, dict), "an object"),
}


def check_manifest_fields(data, path) -> None:
    """DamagedFileError (exit 1) naming the file and the field when a manifest field is missing
    or malformed (a tampered or damaged manifest, never the user's options)."""
    from ..usd.pxr_errors import DamagedFileError

    for key, (ok, what) in _MANIFEST_FIELDS.items():
        if key not in data:
            raise DamagedFileError(f"sweep manifest {path}: field {key!r} is missing; the manifest is damaged: run "
                                   "the sweep again")
        if not ok(data[key]):
            raise DamagedFileError(f"sweep manifest {path}: field {key!r} is {data[key]!r}, not {what}; the manifest "
                                   "is damaged: run the sweep again")


def _check_world(world, count, root) -> int:
    if isinstance(world, bool) or not isinstance(world, int) and not (hasattr(world, "__index__")):
        raise TypeError(f"world {world!r} is not an integer index; give 0 .. {count - 1}")
    world = int(world)
    if not 0 <= world < count:
        raise ValueError(f"world {world} is out of range: the sweep {root} has worlds 0 .. {count - 1}")
    return world


def _differences(manifest, fps, substeps, device) -> list:
    """Why a re-run at these settings will not equal the sweep's samples (empty: it will)."""
    out = []
    if fps is not None and not math.isclose(float(fps), manifest["run_fps"], rel_tol=1e-12):
        out.append(f"--fps {fps:g} (the sweep: {manifest['run_fps']:g})")
    if not _same_substeps(manifest, substeps):
        out.append(f"--substeps {substeps} (the sweep: {manifest['run_substeps']})")
    if device is not None and manifest["device"] is not None and str(device) != manifest["device"]:
        out.append(f"device {device} (the sweep ran on {manifest['device']})")
    return out


def _same_substeps(manifest, substeps) -> bool:
    """Whether ``--substeps`` (None, an int or "auto") asks for what the sweep was run with."""
    given = manifest["substeps"]
    if substeps is None or str(substeps) == str(given):
        return True
    if "auto" in (str(substeps), str(given)):
        return False
    return int(substeps) == manifest["run_substeps"]


def _settings(manifest, fps, substeps) -> tuple:
    """(fps, substeps) to run with: the sweep's own (as it was given them: None = the scene's)
    unless another value is asked for."""
    same_fps = fps is None or math.isclose(float(fps), manifest["run_fps"], rel_tol=1e-12)
    same_substeps = _same_substeps(manifest, substeps)
    return (manifest["fps"] if same_fps else fps), (manifest["substeps"] if same_substeps else substeps)


def _frame_steps(manifest, fps, substeps):
    """The steps per frame the sweep's batch took (auto sub-steps resolve over all its worlds, so
    a world alone is told the count), or None when other settings were asked for."""
    same = (fps is None or math.isclose(float(fps), manifest["run_fps"], rel_tol=1e-12)) and _same_substeps(manifest,
                                                                                                       substeps)
    return manifest.get("frame_steps") if same else None


def sweep_frame_steps(scene_name, world_params, *, fps=None, substeps=None, device=None, fused=False):
    """The steps per frame every world of a sweep takes with automatic timing, from all its
    worlds' parameters (as given to :func:`warpsim.sweeps.sweep.run_batch`): the max over the
    worlds of each world's own count (``WorldBatch.auto_steps``: every world's step <= 0.5 x its
    own limit), so a sweep split into batches or devices afterwards steps every block alike (give
    each ``run_batch(frame_steps=...)``). The sweep's batch is built, not run. None when the
    count is fixed (the settings give it) or the scene has no step limit (flocks)."""
    from ..scenes import get_scene
    from .sweep import make_batch, sweep_timing, timed_params

    cls = get_scene(scene_name)
    world_params = [_typed(cls, p) for p in world_params]
    timing = sweep_timing(cls, world_params, fps, substeps)
    if not timing.auto:
        return None
    batch = make_batch(cls, timed_params(cls, world_params, timing), device=device, fused=fused)
    if getattr(batch, "batch_scene", None) is None:  # flocks: no sub-step limit
        return None
    return int(batch.use_timing(timing).steps)


def run_world(scene_name, world_params, world, *, out, frames, fps=None, substeps=None, device=None, fused=False,
              progress=None, frame_steps=None, flatten=False) -> str:
    """Run world ``world`` of the sweep whose worlds are ``world_params`` (as given to
    :func:`warpsim.sweeps.sweep.run_batch`, with the same ``fps``/``substeps``/``fused``) alone
    and write its frames 0 .. ``frames`` to the cache ``out`` (a ``warpsim run`` cache). Returns
    the cache path. ``progress(frame)`` is called after each frame; ``frame_steps``: the steps per
    frame the whole batch took (its manifest's ``frame_steps``), None to let the world decide."""
    from ..scenes import get_scene
    from ..usd.writer import UsdCacheWriter
    from ..worlds.batch import is_agent_scene
    from ..worlds.batch import WorldBatch
    from .sweep import sweep_timing, timed_params

    cls = get_scene(scene_name)
    world_params = [_typed(cls, p) for p in world_params]
    world = _check_world(world, len(world_params), "given")
    if is_agent_scene(cls):
        raise ValueError(f"scene {cls.name!r} is a flock: re-running one of its worlds alone is not supported")
    timing = sweep_timing(cls, world_params, fps, substeps)  # the sweep's one FrameTiming, as run_batch
    fps, substeps, frame_dt = timing.fps, timing.steps, timing.frame_dt
    world_params = timed_params(cls, world_params, timing)
    batch = WorldBatch(cls, [world_params[world]], device=device, fused=fused, reference_params=world_params)
    batch.use_timing(timing if frame_steps is None else timing.with_steps(int(frame_steps)))
    writer = UsdCacheWriter(out, fps=fps, flatten=flatten)
    batch.scene.declare(writer)
    writer.begin()

    def write(frame):
        x, v = batch.world_slices()
        writer.write_frame(frame, batch.world_frame_data(x[0], v[0], 0))

    with writer:
        write(0)
        for frame in range(1, int(frames) + 1):
            batch.advance(frame_dt, substeps)
            write(frame)
            if progress is not None:
                progress(frame)
    return writer.output_path


def rerun_world(root, world, *, out=None, frames=None, fps=None, substeps=None, device=None, warn=None,
                progress=None, flatten=False) -> str:
    """Re-run world ``world`` of the sweep at ``root`` alone, with its parameters, on the sweep's
    device (``device``: another one), and write it to the cache ``out`` (default beside the root,
    ``<stem>.world_NNNNNN.usda``); ``frames`` defaults to the sweep's. On the same device, fps
    and substeps its samples equal the sweep's ``/Worlds/world_NNNNNN`` bit for bit; other
    settings call ``warn(message)`` (default: a Python warning) first. Returns the cache path.
    ValueError (one line) for a root that is not a sweep, another warpsim version or changed
    scene defaults, a world out of range."""
    _check_api_args(root, frames, fps, substeps, out)
    manifest = read_manifest(root)
    world = _check_world(world, len(manifest["worlds"]), root)
    if frames is None:
        frames = manifest["frames"]
    if int(frames) < 0:
        raise ValueError(f"frames {frames}: it must be >= 0")
    out = out or world_cache_path(root, world)
    _check_rerun_out(out, root)
    diffs = _differences(manifest, fps, substeps, device)
    if diffs:
        message = (f"world {world} re-runs with {', '.join(diffs)}: the result will differ from its samples in the "
                   "sweep")
        if warn is None:
            import warnings

            warnings.warn(message, stacklevel=2)
        else:
            warn(message)
    run_fps, run_substeps = _settings(manifest, fps, substeps)
    run_device = device if device is not None else manifest["device"]
    return run_world(manifest["scene"], manifest["worlds"], world, out=out,
                     frames=frames, fps=run_fps, substeps=run_substeps, device=run_device,
                     fused=manifest["fused"], progress=progress, frame_steps=_frame_steps(manifest, fps, substeps),
                     flatten=flatten)


def _check_api_args(root, frames, fps, substeps, out) -> None:
    """TypeError / ValueError naming the argument for values of the wrong kind (before any work)."""
    if not isinstance(root, (str, os.PathLike)):
        raise TypeError(f"root {root!r} is not a path; give the sweep's root file (.usda)")
    if frames is not None and not _whole(frames, -(1 << 62)):
        raise TypeError(f"frames {frames!r} is not a whole number; give e.g. frames=120 (or None: the sweep's)")
    if fps is not None and not (isinstance(fps, (int, float)) and not isinstance(fps, bool)):
        raise TypeError(f"fps {fps!r} is not a number; give e.g. fps=60 (or None: the sweep's)")
    if fps is not None and not _rate(fps):
        raise ValueError(f"fps {fps!r}: it must be > 0 [frames/s]")
    if substeps is not None and substeps != "auto" and not _whole(substeps, -(1 << 62)):
        raise TypeError(f"substeps {substeps!r} is not a whole number or 'auto'")
    if substeps is not None and substeps != "auto" and substeps < 1:
        raise ValueError(f"substeps {substeps}: it must be >= 1")
    if out is not None and not isinstance(out, (str, os.PathLike)):
        raise TypeError(f"out {out!r} is not a path; give a .usda/.usdc file name")
    if out is not None and os.path.splitext(os.fspath(out))[1] not in (".usd", ".usda", ".usdc"):
        raise ValueError(f"out {os.fspath(out)!r} must end in .usd, .usda or .usdc")


def _check_rerun_out(out, root, flag="out") -> None:
    """ValueError when the re-run's cache would overwrite the sweep root or one of its files."""
    from ..usd.family import check_output
    from ..browse.roots import root_worlds

    try:
        layers = sorted({p for _, p in (root_worlds(root) or (None, []))[1]})
    except Exception:  # noqa: BLE001  (a damaged root: its own name still counts)
        layers = []
    check_output(out, [root, *layers], flag)


# ----------------------------------------------------------------------------------------------
# Command line: warpsim run SCENE --from-sweep ROOT --world N
# ----------------------------------------------------------------------------------------------
def run_command(args, out, err) -> int:
    """``warpsim run SCENE --from-sweep ROOT --world N [--frames F] [--fps F] [--substeps S]
    [--device D] [--out PATH]``; UsageError (exit 2) for bad input found before the run."""
    from ..core.errors import SimulationError

    usage = UsageError
    if args.world is None or args.from_sweep is None:
        raise usage("--from-sweep ROOT and --world N go together (re-run world N of the sweep at ROOT)")
    for flag, given in (("--set", args.sets), ("--integrator", args.integrator), ("--resume", args.resume),
                        ("--checkpoint-every", args.checkpoint_every), ("--preview", args.preview)):
        if given:
            raise usage(f"{flag} cannot be used with --from-sweep: world {args.world} re-runs with the sweep's "
                        "parameters")
    try:
        manifest = read_manifest(args.from_sweep, scene=args.scene)
        world = _check_world(args.world, len(manifest["worlds"]), args.from_sweep)
    except ValueError as exc:
        if getattr(exc, "exit_status", 2) != 2:
            raise  # a damaged manifest: exit 1, naming the file and the field
        raise usage(one_line(exc)) from None
    frames = manifest["frames"] if args.frames is None else args.frames
    if frames < 0:
        raise usage(f"--frames {frames}: it must be >= 0")
    path = args.out or world_cache_path(args.from_sweep, world)
    if os.path.splitext(path)[1] not in (".usd", ".usda", ".usdc"):
        raise usage(f"--out {path!r} must end in .usd, .usda or .usdc")
    try:
        _check_rerun_out(path, args.from_sweep, "--out")
    except ValueError as exc:
        raise usage(one_line(exc)) from None
    from ..usd.lock import hold

    hold(path, "--out")  # released when the command ends
    device = device_arg(args.device) if args.device is not None else None
    if device is None and manifest["device"] is not None:
        try:  # the sweep's device must be here
            device = device_arg(manifest["device"])
        except usage:
            raise usage(f"the sweep {args.from_sweep} ran on {manifest['device']!r} (its manifest), which this machine "
                        "does not have; give --device (e.g. --device cpu; world "
                        f"{world} then differs from its samples in the sweep)") from None
    return _run_and_report(manifest, world, path, frames, args.fps, args.substeps, device,
                           not args.no_progress, out, err, SimulationError)


def _run_and_report(manifest, world, path, frames, fps, substeps, device, show_progress, out, err,
                    SimulationError) -> int:

    for line in _differences(manifest, fps, substeps, device):
        print(f"warpsim: warning: {line}: world {world} will differ from its samples in the sweep", file=err)
    run_fps, run_substeps = _settings(manifest, fps, substeps)
    progress = None
    if show_progress:
        from tqdm import tqdm

        progress = tqdm(total=frames, unit="frame", desc=f"{manifest['scene']} world {world}", file=err,
                        dynamic_ncols=True)
    try:
        result = run_world(manifest["scene"], manifest["worlds"], world, out=path, frames=frames, fps=run_fps,
                           substeps=run_substeps, device=device, fused=manifest["fused"],
                           progress=(lambda f: progress.update(1)) if progress else None,
                           frame_steps=_frame_steps(manifest, fps, substeps))
    except SimulationError as exc:
        print(f"warpsim: simulation failed: {one_line(exc)}", file=err)
        return 1
    except ValueError as exc:
        raise UsageError(one_line(exc)) from None
    finally:
        if progress:
            progress.close()
    print(f"re-ran world {world} of scene {manifest['scene']!r} ({frames} frames) on "
          f"{device or manifest['device'] or 'the default device'}", file=out)
    print(f"open: {os.path.relpath(result)}", file=out)
    return 0


def rerun_in_sweep(args, cls, world_params, path, device, out, err) -> int:
    """``warpsim sweep ... --rerun N``: world N of the sweep these arguments describe, alone, into
    ``<stem>.world_NNNNNN.usda`` beside ``path`` (the sweep's root)."""
    from ..core.errors import SimulationError

    try:
        world = _check_world(args.rerun, len(world_params), f"described ({len(world_params)} worlds)")
    except ValueError as exc:
        raise UsageError(f"--rerun: {one_line(exc)}") from None
    manifest = {"scene": cls.name, "worlds": world_params, "fps": args.fps, "substeps": args.substeps,
                "fused": bool(args.fused), "device": None, "run_fps": None, "run_substeps": None}
    from .sweep import sweep_timing

    try:
        timing = sweep_timing(cls, world_params, args.fps, args.substeps)
        manifest["run_fps"], manifest["run_substeps"] = timing.fps, timing.steps
        # automatic sub-steps follow the sweep's stiffest world: found as the sweep finds them
        manifest["frame_steps"] = sweep_frame_steps(cls.name, world_params, fps=args.fps, substeps=args.substeps,
                                                    device=device, fused=bool(args.fused))
    except ValueError as exc:
        raise UsageError(one_line(exc)) from None
    return _run_and_report(manifest, world, world_cache_path(path, world), args.frames, None, None, device,
                           not args.no_progress, out, err, SimulationError)


# ----------------------------------------------------------------------------------------------
# Checking a re-run against the sweep
# ----------------------------------------------------------------------------------------------
def _samples(stage, root_path) -> dict:
    """{(prim path relative to root_path, attribute): [(time, numpy array), ...]} of every
    time-sampled attribute below ``root_path``; a sweep's curves stored as their particles'
    points (``warpsim:segments``) in the form a full cache writes them (segment ends, extent)."""
    import numpy as np
    from pxr import Usd

    from ..usd.prims import curve_samples, segment_pairs

    out = {}
    root = stage.GetPrimAtPath(root_path)
    for prim in Usd.PrimRange(root):
        rel = str(prim.GetPath())[len(root_path):]
        for attr in prim.GetAttributes():
            times = attr.GetTimeSamples()
            if times:
                out[(rel, attr.GetName())] = [(t, np.asarray(attr.Get(t))) for t in times]
        pairs = segment_pairs(prim)
        if pairs is not None and (rel, "points") in out:
            width = float(np.asarray(prim.GetAttribute("widths").Get(), np.float64)[0])
            curves = [(t, curve_samples(x, pairs, width)) for t, x in out[(rel, "points")]]
            out[(rel, "points")] = [(t, c["points"]) for t, c in curves]
            out[(rel, "extent")] = [(t, c["extent"]) for t, c in curves]
            if (rel, "velocities") in out:
                out[(rel, "velocities")] = [(t, v[pairs.reshape(-1)]) for t, v in out[(rel, "velocities")]]
    return out


def first_difference(root, world, cache):
    """None when the cache ``cache`` holds exactly (bit for bit, same attributes and time samples)
    the samples of world ``world`` in the sweep at ``root``; otherwise a line naming the first
    difference."""
    from pxr import Usd

    sweep = Usd.Stage.Open(os.fspath(root))
    prim = sweep.GetPrimAtPath("/World")
    variants = prim.GetVariantSets().GetVariantSet("world")
    name = f"world_{int(world):06d}"
    if not variants or name not in variants.GetVariantNames():
        return f"{root} has no variant {name} (a sweep root with --layout variants is needed)"
    variants.SetVariantSelection(name)
    expected = _samples(sweep, "/World")
    run = Usd.Stage.Open(os.fspath(cache))
    got = _samples(run, str(run.GetDefaultPrim().GetPath()))
    for key in sorted(set(expected) | set(got)):
        if key not in got or key not in expected:
            return f"{key[0]}.{key[1]} is only in the {'sweep' if key in expected else 're-run'}"
        a, b = expected[key], got[key]
        if [t for t, _ in a] != [t for t, _ in b]:
            return f"{key[0]}.{key[1]}: time samples {len(a)} in the sweep, {len(b)} in the re-run"
        for (t, x), (_, y) in zip(a, b):
            if x.dtype != y.dtype or x.shape != y.shape or x.tobytes() != y.tobytes():
                return f"{key[0]}.{key[1]} differs at time {t:g}"
    return None


def pick_or_rerun(root, world, out_path, flatten=False, allow_damaged=False) -> str:
    """``warpsim pick``: world ``world`` of the sweep ``root`` into ``out_path``: its stored frames
    (:func:`warpsim.browse.pick.pick_world`), or for a sweep run with ``--store none`` the world
    re-run alone from the sweep's manifest, bit for bit as in the sweep (:func:`rerun_world`), into
    the full cache ``out_path`` (chunks beside it; ``flatten``: one self-contained ``.usdc``)."""
    from ..browse.pick import UnstoredWorldError, pick_world

    try:
        return pick_world(root, world, out_path, flatten=flatten, allow_damaged=allow_damaged)
    except UnstoredWorldError:
        pass
    world = int(world)
    count = len(read_manifest(root)["worlds"])
    if not 0 <= world < count:
        raise ValueError(f"--world {world} is out of range: {root} holds worlds 0..{count - 1} ({count} worlds)")
    out_path = os.path.abspath(os.fspath(out_path))
    if os.path.splitext(out_path)[1] not in (".usd", ".usda", ".usdc"):
        raise ValueError(f"--out {out_path!r} must end in .usd, .usda or .usdc")
    if os.path.isdir(out_path):
        raise ValueError(f"--out {out_path!r} is a folder; name a file in it")
    return rerun_world(root, world, out=out_path, flatten=flatten)
