"""``warpsim sweep``: many worlds of one scene in one batched run.

    warpsim sweep SCENE --worlds N --vary KEY=LO:HI[:log] --vary KEY=A,B,C [--sample grid|random|lhs]
                  [--seed S] [--frames N] [--fps F] [--substeps S] [--device D] [--out PATH]
                  [--set KEY=VALUE ...] [--layout variants|grid] [--table CSV] [--track NAME=INDEX ...]
                  [--rank METRIC [--top K]] [--where METRIC<VALUE ...] [--rerun N]
                  [--inside BOX@T0:T1 ...] [--outside BOX@T0:T1 ...] [--occupancy-res R]

Writes ``PATH`` (default ``usd_out/SCENE_sweep.usda``): a root whose ``/World`` carries a variant
set ``world`` (or, with ``--layout grid``, every world side by side), the batch layer beside it
(``<stem>.batch_0000.usdc``) and the table ``<stem>.csv`` (one row per world: parameters and
metrics) and the occupancy record ``<stem>.occupancy.npz`` (:mod:`warpsim.browse.occupancy`;
``warpsim query`` asks it later). ``--rank``/``--where``/``--inside``/``--outside`` print the
picked worlds and write ``<stem>.picked.usda`` holding only those. Exit status 2 for usage
mistakes (one line), 1 when the run fails.
"""
from __future__ import annotations

import os
import sys

from ..cli_common import (
    UsageError, check_output_path, device_arg, hold_output, parse_sets, substeps_arg, warn_or_refuse,
)
from . import preflight

LAYER_EXT = ".usdc"
STORE_MODES = ("all", "preview", "none")
PREVIEW_EVERY = 4
"""``--store preview`` keeps every 4th frame and the last (the thumbnails' frame): a quarter of the
bytes; USD tools hold or interpolate between the kept samples, at the sweep's frame times."""
AUTO_STORE_BYTES = 2 << 30
"""Largest batch layer the default ``--store`` keeps every frame of (and preview frames of) [bytes]."""


def add_parser(sub):

    s = sub.add_parser("sweep", help="many worlds of a scene in one batched run: USD variants, a table, picking")
    s.add_argument("scene", help="scene name (see 'warpsim list')")
    s.add_argument("--worlds", type=int, default=None, help="number of worlds (grid: default the listed values)")
    s.add_argument("--vary", action="append", default=[], metavar="KEY=LO:HI[:log]|KEY=A,B,C",
                   help="a parameter that differs between worlds (repeatable)")
    s.add_argument("--sample", default="grid", help="grid (default), random or lhs")
    s.add_argument("--seed", type=int, default=0, help="seed of random / lhs sampling (default 0)")
    s.add_argument("--frames", type=int, default=120, help="frames after frame 0 (default 120)")
    s.add_argument("--fps", type=float, default=None, help="frames per second (default: the scene's)")
    s.add_argument("--substeps", type=substeps_arg, default=None,
                   help="steps per frame at the scene's frame rate (as 'warpsim run --help' says), or 'auto': the "
                        "most any world needs, so every world steps within half its own stability limit (default: "
                        "the scene's)")
    s.add_argument("--strict", action="store_true",
                   help="exit 2 before running when a world's step is above its stability limit or --substeps "
                        "overrides the scene's dt (default: warn)")
    s.add_argument("--device", default=None, help="Warp device, e.g. cpu or cuda:0 (default: CUDA when present)")
    s.add_argument("--devices", default=None, metavar="D0,D1,...|all",
                   help="split the worlds over several devices of this machine in one process, a contiguous block "
                        "and a thread each (e.g. cuda:0,cuda:1, all: every GPU, cpu,cpu); the same table and samples "
                        "as on one device")
    s.add_argument("--out", default=None, help="root USD to write; a relative path is taken from the current "
                   "folder (default usd_out/SCENE_sweep.usda; the table, record and picked worlds go beside it)")
    s.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE",
                   help="a parameter shared by every world (repeatable)")
    s.add_argument("--layout", default="variants", help="variants (a 'world' variant set, default) or grid")
    s.add_argument("--table", default=None, help="CSV table (default: beside --out, <stem>.csv)")
    s.add_argument("--track", action="append", default=[], metavar="NAME=INDEX",
                   help="report final and peak positions of a particle (index within a world; teapot: spout, "
                        "handle, knob, bottom)")
    s.add_argument("--rank", default=None, metavar="METRIC",
                   help="order worlds by a metric, smallest first (METRIC:desc or --rank=-METRIC: largest first)")
    s.add_argument("--top", type=int, default=None, metavar="K", help="keep the first K worlds of --rank")
    s.add_argument("--where", action="append", default=[], metavar="METRIC<VALUE",
                   help="keep worlds whose metric passes (< <= > >= == !=; repeatable)")
    s.add_argument("--inside", action="append", default=[], metavar="X0,Y0,Z0,X1,Y1,Z1@T0:T1",
                   help="keep worlds with a (tracked) particle inside the box [m] at some frame of the window [s] "
                        "(repeatable; adds insideK_time, insideK_entry, insideK_share to rank by)")
    s.add_argument("--outside", action="append", default=[], metavar="X0,Y0,Z0,X1,Y1,Z1@T0:T1",
                   help="keep worlds with no (tracked) particle inside the box during the window (repeatable)")
    s.add_argument("--occupancy-res", type=int, default=None, metavar="R",
                   help="cells along the longest side of the occupancy record's grid (default 16)")
    s.add_argument("--occupancy-bounds", default=None, metavar="X0,Y0,Z0,X1,Y1,Z1",
                   help="box [m] the occupancy grid covers (default: frame 0's extent, padded)")
    s.add_argument("--thumbnails", action="store_true",
                   help="draw every world's picture for the gallery after the sweep also past 10,000 worlds (there "
                        "they are off by default: about 10 ms each on a CPU)")
    s.add_argument("--no-thumbnails", action="store_true",
                   help="draw no picture of each world for the gallery after the sweep (it then draws them on "
                        "first show)")
    from ..browse.query import accept_negative_boxes

    accept_negative_boxes(s)
    s.add_argument("--fused", action="store_true",
                   help="step mass-spring scenes through the fused semi-implicit kernel (faster on GPUs; agrees "
                        "to float32 rounding)")
    s.add_argument("--chunk", type=int, default=None, metavar="K",
                   help="frames per chunk file of the batch layer (default: 24, fewer where a chunk would hold over "
                        "128 MiB, so worker processes write many worlds' chunks side by side; completed chunks "
                        "survive a kill)")
    s.add_argument("--no-progress", action="store_true", help="no progress bar")
    s.add_argument("--store", default=None, choices=STORE_MODES,
                   help="what the batch layer keeps: all (every frame), preview (every "
                        f"{PREVIEW_EVERY}th frame and the last: the gallery and a DCC glance) or none (the table, "
                        "occupancy record, manifest and thumbnails only); every world re-runs bit-exactly, so "
                        "'warpsim pick' and --rerun make any world's full cache later (default: all when every "
                        f"frame fits in {AUTO_STORE_BYTES >> 30} GiB and half the free disk, else preview, else none; "
                        "the sweep says which and why)")
    s.add_argument("--rerun", type=int, default=None, metavar="N",
                   help="run only world N of this sweep, alone, exactly as in the whole sweep (writes "
                        "<stem>.world_NNNNNN.usda)")
    try:
        from ..distributed.ray_sweep import add_ray_arguments
    except ImportError:  # pragma: no cover - the distributed package is optional
        pass
    else:
        add_ray_arguments(s)
    return s


def resolve_track(cls, params, items, device):
    """{name: particle index within a world} from ``--track NAME=INDEX`` / ``INDEX`` / an anchor name."""
    out = {}
    scene = None
    for item in items:
        name, _, value = item.partition("=") if "=" in item else (None, "", item)
        value = value.strip()
        try:
            index = int(value)
        except ValueError:
            anchors = cls.track_anchors  # the scene's named particles (Scene.anchor_particle)
            if not anchors:
                raise ValueError(f"--track {item!r}: give a particle index (NAME=INDEX)") from None
            if value not in anchors:
                raise ValueError(f"--track {item!r}: not an index or one of {', '.join(anchors)}") from None
            if scene is None:
                scene = cls(params, device=device)
            index = scene.anchor_particle(value)
        name = (name or (value if not value.lstrip("-").isdigit() else f"p{index}")).strip()
        out[name] = index
    return out


def run(args, out, err):
    from ..verbosity import set_warp_verbosity

    set_warp_verbosity()  # Warp's module-load lines only with --verbose
    from ..core.errors import SimulationError
    from ..distributed.devices import DeviceSweepError
    from ..distributed.ray_sweep import RaySweepError
    from ..scenes import get_scene

    try:
        cls = get_scene(args.scene)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    devices = _checked_flags(args)
    path, table = _checked_outputs(args, cls)
    world_params, base, timing, track = _sampled_worlds(args, cls)
    regions, occupancy, rank, where = _picking(args, world_params, timing.fps, track)
    device = device_arg(args.device) if devices is None else ",".join(devices)
    if args.rerun is not None:
        from .rerun import rerun_in_sweep

        return rerun_in_sweep(args, cls, world_params, path, device, out, err)
    import warnings

    from ..core.stability import StabilityWarning

    warnings.simplefilter("ignore", StabilityWarning)  # run_batch's warn() says it once, per world
    if timing.note:  # --substeps N overriding the scene's dt (--strict: refused)
        warn_or_refuse(timing.note, args.strict, err)
    _check_resources(args, cls, base, len(world_params), path, device, devices, timing.fps, err)
    args.thumbnail_pool = None  # (the thumbnails' workers: started once the frames are stepped, _run_here)
    try:
        rows, root, layers = _execute(args, cls, world_params, (path, table), (device, devices), track, occupancy,
                                      err)
    except (SimulationError, ValueError, RaySweepError, DeviceSweepError) as exc:
        _close_thumbnail_pool(args)
        if isinstance(exc, ValueError) and not isinstance(exc, SimulationError) and _is_usage(exc):
            raise UsageError(str(exc).splitlines()[0]) from None
        print(f"warpsim: sweep failed: {str(exc).splitlines()[0]}", file=err)
        return 1
    except BaseException:
        _close_thumbnail_pool(args)
        raise
    unstable = sum(1 for r in rows if r.get("unstable"))
    blown = sum(1 for r in rows if r.get("blown_up") and not r.get("unstable"))  # the unstable ones are said below
    note = f"{blown} blew up and were frozen" if blown else ""
    if unstable:
        note += f"{', ' if note else ''}{unstable} went unstable (column unstable)"
    print(f"ran {len(rows)} worlds of scene {cls.name!r} x {args.frames} frames at {timing.fps:g} fps on {device}"
          f"{f' ({note})' if note else ''}", file=out)
    print(f"open: {os.path.relpath(root)}   table: {os.path.relpath(table)}", file=out)
    print(args.store_note, file=out)
    thumbs_device = device if getattr(args, "ray", None) is None and devices is None else \
        devices[0] if devices is not None else "cpu"
    try:
        return _answer(args, rows, (root, layers, path), list(world_params[0]), (regions, rank, where),
                       thumbs_device, out, err)
    finally:
        _close_thumbnail_pool(args)


def _thumbnails_wanted(args, worlds):
    """True (drawn), False (``--no-thumbnails``) or "many" (past ``OPT_IN_WORLDS`` without ``--thumbnails``)."""
    from ..browse.panel import OPT_IN_WORLDS

    return not args.no_thumbnails and ("many" if worlds > OPT_IN_WORLDS and not args.thumbnails else True)


def _is_cuda(device) -> bool:
    """Whether ``device`` (a Warp device or its name) is a CUDA device."""
    return str(getattr(device, "alias", device)).startswith("cuda")


def _start_thumbnail_pool(args, worlds, device):
    """Start the workers that will draw the thumbnails (:func:`warpsim.browse.thumbs.start_workers`)
    while the sweep completes its layer, record, table and root; none when this process draws them."""
    if _thumbnails_wanted(args, worlds) is not True or getattr(args, "thumbnail_pool", None) is not None:
        return
    from ..browse.panel import THUMB_SIZE
    from ..browse.thumbs import start_workers

    try:
        args.thumbnail_pool = start_workers(worlds, THUMB_SIZE, device)
    except OSError:  # (then they start when drawn, as without this head start)
        args.thumbnail_pool = None


def _close_thumbnail_pool(args):
    pool, args.thumbnail_pool = getattr(args, "thumbnail_pool", None), None
    if pool is not None:
        pool.close(wait=False)


def _checked_flags(args):
    """The devices of ``--devices`` (None: one device) once the flags that need no scene agree;
    UsageError (exit 2) otherwise."""
    from ..browse.roots import LAYOUTS
    from ..distributed.ray_sweep import ray_usage_error

    if args.frames < 0:
        raise UsageError(f"--frames {args.frames}: it must be >= 0")
    if args.layout not in LAYOUTS:
        raise UsageError(f"--layout {args.layout!r}: use one of {', '.join(LAYOUTS)}")
    if ray_usage_error(args):
        raise UsageError(ray_usage_error(args))
    devices = None
    if getattr(args, "devices", None) is not None:
        from ..distributed.devices import parse_devices

        if args.device is not None:
            raise UsageError(f"--devices {args.devices} and --device {args.device}: give one of them")
        if getattr(args, "ray", None) is not None:
            raise UsageError("--devices splits a sweep over this machine's devices in one process; with --ray each "
                             "batch is a Ray task with one GPU (--device cuda): drop one of them")
        if args.rerun is not None:
            raise UsageError("--rerun runs one world on one device: give --device instead of --devices")
        try:
            devices = parse_devices(args.devices)
        except ValueError as exc:
            raise UsageError(str(exc)) from None
    if args.chunk is not None and args.chunk < 1:
        raise UsageError(f"--chunk {args.chunk}: it must be >= 1 (frames per chunk file)")
    if getattr(args, "ray", None) is not None:
        from ..extras import require_extra

        require_extra("ray", "warpsim sweep --ray")
    if getattr(args, "thumbnails", False) and args.no_thumbnails:
        raise UsageError("--thumbnails and --no-thumbnails: give one of them")
    if args.top is not None and args.top < 1:
        raise UsageError(f"--top {args.top}: it must be >= 1")
    if args.top is not None and args.rank is None:
        raise UsageError("--top needs --rank METRIC (the order to take the top worlds from)")
    return devices


def _checked_outputs(args, cls):
    """(root path, table path) once the seed, world count and ``--ray`` address pass and both
    outputs can be written and are held by this command; UsageError otherwise."""
    path = args.out or os.path.join("usd_out", f"{cls.name}_sweep.usda")
    stem, ext = os.path.splitext(path)
    if ext not in (".usd", ".usda", ".usdc"):
        raise UsageError(f"--out {path!r} must end in .usd, .usda or .usdc")
    table = args.table or stem + ".csv"
    try:  # seed, world count, --ray address: before anything is sampled
        preflight.check_seed(args.seed)
        if args.worlds is not None:
            preflight.check_worlds(args.worlds)
        preflight.check_ray_address(getattr(args, "ray", None))
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    check_output_path(path, "--out")
    if os.path.splitext(table)[1].lower() != ".csv":
        raise UsageError(f"--table {table!r} must end in .csv")
    check_output_path(table, "--table")
    hold_output(path, "--out")  # one writer per sweep root, table and record; never another's files
    hold_output(table, "--table", own=path)
    return path, table


def _sampled_worlds(args, cls):
    """(world parameters, world 0's resolved parameters, the one FrameTiming of every world,
    tracked particles or None) from ``--set``, ``--vary``, ``--worlds``, ``--sample`` and
    ``--track``; UsageError for a bad value."""
    from .sweep import sample_worlds

    fixed = parse_sets(cls, args.sets, None)
    worlds = args.worlds
    try:
        if worlds is None:
            if args.sample != "grid" or any(":" in v.split("=", 1)[-1] for v in args.vary):
                raise ValueError("--worlds N is needed for ranges and for random / lhs sampling")
            from .sampling import parse_vary

            worlds = 1
            for v in args.vary:
                worlds *= len(parse_vary(v, cls.params).values)
        world_params = sample_worlds(cls.name, fixed, args.vary, worlds, args.sample, args.seed)
        base = cls.resolve_params(world_params[0])
        timing = _timing(cls, world_params, args.fps, args.substeps)  # the one FrameTiming of every world
        track = resolve_track(cls, base, args.track, "cpu") if args.track else None
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    return world_params, base, timing, track


def _picking(args, world_params, fps, track):
    """(regions, occupancy options, rank, where) of ``--inside`` / ``--outside`` / ``--rank`` /
    ``--where``, checked against the table's columns before anything runs; UsageError otherwise."""
    from ..browse.query import region_columns
    from .metrics import BUILTIN, format_cell, parse_rank, parse_where

    names = [k for k in world_params[0]] + list(BUILTIN)
    for name in track or {}:
        names += [f"{name}_x", f"{name}_y", f"{name}_z", f"{name}_peak_y"]
    try:  # picking is checked before anything runs
        regions, occupancy = _regions(args, fps)
        names += region_columns(regions)
        rank = parse_rank(args.rank, names) if args.rank else None
        where = [parse_where(w, names) for w in args.where]
        numeric = preflight.numeric_columns(world_params)
        for flag, metric in ([("--rank", rank[0])] if rank else []) + [("--where", w[0]) for w in where]:
            if metric in world_params[0] and metric not in numeric:
                value = world_params[0][metric]
                kind = "a vector" if isinstance(value, (tuple, list)) else f"a {type(value).__name__}"
                raise ValueError(f"{flag} {metric}: parameter {metric} is {kind} ({format_cell(value)}), not one "
                                 f"number; {flag} compares numbers: a metric ({', '.join(BUILTIN[:3])}, ...) or a "
                                 f"numeric parameter ({', '.join(sorted(numeric)) or 'none here'})")
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    return regions, occupancy, rank, where


def _check_resources(args, cls, base, worlds, path, device, devices, fps, err):
    """Refuse a sweep whose memory (one device) or output (the disk of ``path``) does not fit,
    from world 0 built on the CPU; choose ``--store`` when not given (:func:`_choose_store`:
    ``args.store``, ``args.store_every`` and ``args.store_note``, the line said with the result);
    a large sweep's size is said on ``err`` before it starts."""
    try:
        scene = cls(base, device="cpu")  # world 0: the memory and output estimates
        if getattr(args, "ray", None) is None and devices is None:  # several devices: checked per block
            _check_memory(cls, scene, worlds, device)
        resume = bool(getattr(args, "resume", False))
        args.store_note = _choose_store(args, scene, path, worlds, args.frames + 1, fps, devices, resume)
        size_note = _check_disk(scene, path, worlds, args.frames + 1, fps, resume=resume,
                                store_every=args.store_every)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    if size_note:
        print(size_note, file=err)


def store_every(mode) -> int:
    """``run_batch``'s ``store_every`` of a ``--store`` mode: all 1, preview PREVIEW_EVERY, none 0."""
    return {"all": 1, "preview": PREVIEW_EVERY, "none": 0}[mode]


def _choose_store(args, scene, path, worlds, frames, fps, devices, resume) -> str:
    """Set ``args.store`` (given, or by size: all when every frame fits in ``AUTO_STORE_BYTES`` and
    half the free disk, else preview when that fits, else none) and ``args.store_every``; returns
    the line saying which and why. ValueError for preview / none with ``--ray``."""
    from .usd import estimate_sweep_bytes

    several = getattr(args, "ray", None) is not None or devices is not None
    layer = f"{os.path.splitext(path)[0]}.batch_0000{LAYER_EXT}"
    size = {m: estimate_sweep_bytes(scene, layer, worlds, frames, fps, store_every(m))["bytes"]
            for m in ("all", "preview")}
    fmt = preflight.format_bytes
    if args.store is not None:
        if args.store != "all" and getattr(args, "ray", None) is not None:
            raise ValueError(f"--store {args.store} runs in one process for now (on one device or over --devices); "
                             "drop --ray or use --store all")
        why = "as given"
    elif several or resume:
        args.store, why = "all", "the default with --ray / --devices / --resume"
    else:
        free = preflight.free_disk_bytes(path)
        room = min(AUTO_STORE_BYTES, free // 2)
        if size["all"] <= room:
            args.store, why = "all", f"the default: every frame is {fmt(size['all'])}"
        elif size["preview"] <= room:
            args.store, why = "preview", (f"every frame would be {fmt(size['all'])}, over {fmt(room)} (the most a "
                                          "default sweep writes: 2 GiB or half the free disk)")
        else:
            args.store, why = "none", (f"even every {PREVIEW_EVERY}th frame would be {fmt(size['preview'])}, over "
                                       f"{fmt(room)} (2 GiB or half the free disk)")
    args.store_every = store_every(args.store)
    what = {"all": "every frame", "preview": f"every {PREVIEW_EVERY}th frame and the last "
                                             f"({fmt(size['preview'])})",
            "none": "no frames: table, occupancy record and thumbnails"}[args.store]
    return (f"store: {args.store}, {what} ({why}); every world re-runs exactly: warpsim pick ROOT --world N "
            "makes its full cache")


def _execute(args, cls, world_params, outputs, devices, track, occupancy, err):
    """Run the sweep (on Ray, over ``--devices`` or here) and write its manifest: (rows, root,
    batch layers). ``outputs``: (root path, table path); ``devices``: (device, ``--devices`` list
    or None)."""
    from .rerun import write_manifest  # what re-running one world exactly needs

    device, several = devices
    run_timing = {}  # steps per frame the single-process batch took (a Ray sweep: the driver's count)
    if getattr(args, "ray", None) is not None:
        rows, root, layers = _run_on_ray(args, cls, world_params, outputs, device, track, occupancy, run_timing, err)
    elif several is not None:
        rows, root, layers = _run_on_devices(args, cls, world_params, outputs, several, track, occupancy,
                                             run_timing, err)
    else:
        rows, root, layers = _run_here(args, cls, world_params, outputs, device, track, occupancy, run_timing, err)
    write_manifest(root, cls.name, world_params, frames=args.frames, fps=args.fps, substeps=args.substeps,
                   device=args.device if getattr(args, "ray", None) is not None else
                   device if several is None else several[0], fused=args.fused,
                   frame_steps=run_timing.get("frame_steps"))
    return rows, root, layers


def _run_on_ray(args, cls, world_params, outputs, device, track, occupancy, run_timing, err):
    """``--ray``: batches as Ray tasks (:func:`warpsim.distributed.ray_sweep.run_ray_sweep`)."""
    from ..distributed.ray_sweep import default_batch_size, run_ray_sweep
    from .rerun import sweep_frame_steps

    path, table = outputs
    # automatic sub-steps resolve over the whole sweep, not per batch (its stiffest world)
    steps = sweep_frame_steps(cls.name, world_params, fps=args.fps, substeps=args.substeps, device=device,
                              fused=bool(args.fused))
    if steps is not None:
        run_timing["frame_steps"] = steps
    result = run_ray_sweep(cls.name, world_params, frames=args.frames, out_path=path, table_path=table,
                           fps=args.fps, substeps=args.substeps, device=args.device,
                           batch_size=args.batch_size or default_batch_size(len(world_params), args.device,
                                                                             args.ray), address=args.ray,
                           num_cpus=args.ray_cpus, resume=args.resume, layout=args.layout,
                           batch_options={**({"track": track} if track else {}),
                                          **({"fused": True} if args.fused else {}),
                                          **({"frame_steps": steps} if steps is not None else {})} or None,
                           log=err, occupancy=occupancy)
    return result["rows"], result["root"], result["layers"]


def _run_on_devices(args, cls, world_params, outputs, devices, track, occupancy, run_timing, err):
    """``--devices``: one block of worlds per device (:func:`warpsim.distributed.devices.run_device_sweep`)."""
    from ..distributed.devices import run_device_sweep
    from .staging import settings_digest

    path, table = outputs
    every = getattr(args, "store_every", 1)
    progress = None
    if not args.no_progress:
        from tqdm import tqdm

        progress = tqdm(total=args.frames, unit="frame", dynamic_ncols=True, file=err,
                        desc=f"{cls.name} x{len(world_params)} on {len(devices)} devices")
    done = [0]

    def advanced(frames_done):
        progress.update(frames_done - done[0])
        done[0] = frames_done

    try:
        result = run_device_sweep(
            cls.name, world_params, devices=devices, frames=args.frames, out_path=path, table_path=table,
            settings={"scene": cls.name, "frames": args.frames, "fps": args.fps, "substeps": args.substeps,
                      "chunk": args.chunk, "fused": bool(args.fused), "track": track or {},
                      "worlds": settings_digest(world_params), **({"store": args.store} if every != 1 else {})},
            store_every=every,
            fps=args.fps, substeps=args.substeps, layout=args.layout, track=track, fused=bool(args.fused),
            occupancy=occupancy, chunk_size=args.chunk, resume=bool(getattr(args, "resume", False)),
            warn=lambda line: warn_or_refuse(line, args.strict, err), progress=advanced if progress else None,
            log=err)
    finally:
        if progress:
            progress.close()
    if result["frame_steps"] is not None:
        run_timing["frame_steps"] = result["frame_steps"]
    return result["rows"], result["root"], result["layers"]


def _run_here(args, cls, world_params, outputs, device, track, occupancy, run_timing, err):
    """One batch in this process, staged (:class:`warpsim.sweeps.staging.SweepStaging`: written
    under a temporary name, ``--resume`` goes on) and published whole with its table and root."""
    from ..browse.roots import write_sweep_root
    from .staging import SweepStaging, settings_digest
    from .sweep import run_batch, write_table

    path, table = outputs
    every = getattr(args, "store_every", 1)
    settings = {"scene": cls.name, "frames": args.frames, "fps": args.fps, "substeps": args.substeps,
                "chunk": args.chunk, "fused": bool(args.fused), "track": track or {},
                "worlds": settings_digest(world_params)}
    if every != 1:  # (an all sweep's settings, and so its run id, stay as before --store)
        settings["store"] = args.store
    staging = SweepStaging(path, settings, resume=bool(getattr(args, "resume", False)), stored=every != 0)
    layer_path = staging.layer
    if every == 0:  # --store none: the last frame goes to a scratch layer the thumbnails are drawn from
        import tempfile

        layer_path = os.path.join(tempfile.mkdtemp(prefix="warpsim_sweep_last_"), "last.usdc")
    first = staging.resume_frame()
    if first:
        print(f"resuming: frames 0..{first - 1} are in {os.path.relpath(staging.layer)}; re-simulating them "
              "without writing, then writing on", file=err)
    progress = None
    if not args.no_progress:
        from tqdm import tqdm

        progress = tqdm(total=args.frames, unit="frame", desc=f"{cls.name} x{len(world_params)}", file=err,
                        dynamic_ncols=True)
    record = _record_path(path)
    clock = []

    def staged(name):
        """A stage after the frames: the thumbnails' workers start with the first (they warm up while
        the layer, record, table and root are completed; on a GPU they started after the first frame);
        the progress bar's label."""
        _start_thumbnail_pool(args, len(world_params), device)
        if progress:
            progress.set_description_str(f"{cls.name} x{len(world_params)}: {name}")

    def advanced(frame):
        """Progress, and the sweep's time estimated from its second frame, measured (the time between
        the first two frames' reports: stepping every world and writing them; the first frame, which
        compiles Warp's kernels, left out)."""
        import time

        clock.append(time.perf_counter())
        if len(clock) == 1 and _is_cuda(device):  # (a GPU's frames leave the host's cores to spare: the
            _start_thumbnail_pool(args, len(world_params), device)  # workers warm up beside the frame loop)
        if len(clock) == 2 and not first:
            note = preflight.frame_time_note(clock[1] - clock[0], args.frames - frame, device, frame,
                                             measured=f"stepping its {len(world_params):,} worlds and writing them",
                                             fix="fewer worlds or frames")
            if note:
                (progress.write if progress else lambda line: print(line, file=err))(f"warpsim: note: {note}")
        if progress:
            progress.update(1)

    try:
        rows = run_batch(cls.name, world_params, frames=args.frames, fps=args.fps, substeps=args.substeps,
                         device=device, layer_path=layer_path, first_world=0, track=track, store_every=every,
                         progress=advanced, fused=args.fused,
                         occupancy={**occupancy, "path": staging.partial(record)},
                         warn=lambda line: warn_or_refuse(line, args.strict, err), chunk_size=args.chunk,
                         resume_frame=first, timing=run_timing, on_stage=staged)
    except BaseException:
        staging.abandon()  # refused before any frame (e.g. a batch that cannot be built): no progress file
        if every == 0:
            import shutil

            shutil.rmtree(os.path.dirname(layer_path), ignore_errors=True)
        raise
    finally:
        if progress:
            progress.close()
    layer = staging.publish([(staging.partial(record), record)])  # the old sweep stays whole until here
    if len(rows) > 10_000 and not args.no_progress:
        print(f"writing the table and the root of {len(rows):,} worlds", file=err)
    write_table(table, rows)
    if every == 0:
        from ..browse.roots import write_unstored_root
        from .sweep import sweep_timing

        root = write_unstored_root(path, len(world_params), scene=cls.name, frames=args.frames,
                                   fps=sweep_timing(cls, world_params, args.fps, args.substeps).fps)
        staging.finish()
        return rows, root, [layer_path]  # (the scratch layer: thumbnails, then removed)
    root = write_sweep_root(path, [layer], len(world_params), layout=args.layout)
    staging.finish()
    return rows, root, [layer]


def _answer(args, rows, written, params, picking, device, out, err):
    """After the run: the occupancy record's summary, the gallery's thumbnails, the answers to
    ``--inside`` / ``--outside`` and the picked worlds (listed, and written as
    ``<stem>.picked<ext>``). ``written``: (root, batch layers, ``--out``); ``picking``: (regions,
    rank, where). The exit status."""
    from ..browse.query import apply_regions, region_columns
    from ..browse.roots import write_sweep_root
    from .metrics import print_picked, select

    root, layers, path = written
    regions, rank, where = picking
    candidates = rows
    if regions and not os.path.exists(_record_path(path)):  # a Ray sweep whose batch failed keeps none
        print("warpsim: sweep failed: no occupancy record to answer --inside/--outside (a batch failed); run the "
              "sweep again with --resume", file=err)
        return 1
    if getattr(args, "ray", None) is None or os.path.exists(_record_path(path)):
        from ..browse.occupancy import OccupancyRecord
        from ..browse.panel import thumbnails_after_sweep
        from ..browse.query import answer_region, answers_note, cached_positions

        record = OccupancyRecord.load(_record_path(path))
        print(record.describe(), file=out)
        enabled = _thumbnails_wanted(args, len(rows))
        bar = None
        if enabled is True and not args.no_progress:
            from tqdm import tqdm

            bar = tqdm(total=len(rows), unit="world", desc="thumbnails", file=err, dynamic_ncols=True)
        try:
            print(thumbnails_after_sweep(root, layers, record, enabled=enabled, device=device,
                                         progress=bar.update if bar else None,
                                         pool=getattr(args, "thumbnail_pool", None)), file=out)
        finally:
            if bar:
                bar.close()
        store = getattr(args, "store", None) or "all"
        if store == "none":  # the scratch layer of the last frame has served the thumbnails
            import shutil

            for layer in layers:  # (one a block with --devices)
                shutil.rmtree(os.path.dirname(layer), ignore_errors=True)
        # a preview's cache lacks most frames: its answers come from the record alone
        positions = cached_positions(root, record) if regions and store == "all" else None
        answers = [answer_region(record, r, positions) for r in regions]
        candidates = apply_regions(rows, record, regions, answers=answers)
        if regions:
            print(answers_note(record, regions, answers), file=out)
    if args.rank or args.where or regions:
        picked = select(candidates, rank=rank, top=args.top, where=where)
        print_picked(picked, len(rows), params, rank=rank, where=where, extra=region_columns(regions), out=out)
        if picked and (getattr(args, "store", None) or "all") == "none":
            print(f"picked worlds: none written (--store none keeps no frames); warpsim pick {os.path.relpath(root)} "
                  "--world N --out FILE re-runs one", file=out)
        elif picked:
            stem, ext = os.path.splitext(path)
            pick_path = write_sweep_root(stem + ".picked" + ext, layers, len(rows), layout=args.layout,
                                         worlds=[r["world"] for r in picked])
            print(f"picked worlds: {os.path.relpath(pick_path)}", file=out)
    return 0


def _check_memory(cls, scene, worlds, device):
    """Refuse a sweep whose memory estimate (from world 0 built on the CPU) does not fit."""
    model = getattr(getattr(scene, "sim", None), "model", None)
    if model is None:
        return
    preflight.check_sweep_memory(cls.name, int(model.particle_count), int(model.spring_count), worlds, device)


def _check_disk(scene, path, worlds, frames, fps, resume=False, store_every=1):
    """The line saying how much a large sweep writes (None: a small one), from world 0's
    ``scene`` and the prims its batch layers write (``store_every``: of ``--store``); ValueError
    when the disk holding ``path`` has less free (not when resuming: the chunks written so far are
    kept)."""
    from .usd import estimate_sweep_bytes

    stem = os.path.splitext(path)[0]
    need = estimate_sweep_bytes(scene, f"{stem}.batch_0000{LAYER_EXT}", worlds, frames, fps, store_every)
    frames = need["frames"]
    detail = f" ({worlds} worlds x {frames} frames of {preflight.format_bytes(need['frame_bytes'])})"
    return preflight.check_disk(path, need["bytes"], detail, free=None if not resume else 1 << 62)


def _record_path(root):
    from ..browse.occupancy import occupancy_path

    return occupancy_path(root)


def _regions(args, fps):
    """(regions, occupancy options) from --inside/--outside/--occupancy-*; windows checked
    against the run's frames. ValueError (one line) for a bad box, window or resolution."""
    from ..browse.occupancy import DEFAULT_RESOLUTION, parse_bounds
    from ..browse.query import check_window, parse_region

    regions = [parse_region(t, True) for t in args.inside] + [parse_region(t, False) for t in args.outside]
    for r in regions:
        check_window(r, fps, args.frames + 1)
    res = DEFAULT_RESOLUTION if args.occupancy_res is None else args.occupancy_res
    if not 1 <= res <= 256:
        raise ValueError(f"--occupancy-res {res}: give 1..256 cells along the grid's longest side")
    bounds = parse_bounds(args.occupancy_bounds) if args.occupancy_bounds else None
    return regions, {"resolution": res, "bounds": bounds}


def _timing(cls, world_params, fps, substeps):
    """The sweep's :class:`~warpsim.scenes.timing.FrameTiming` (``warpsim.sweeps.sweep.sweep_timing``);
    flags that disagree: a usage error (exit 2)."""
    from .sweep import sweep_timing

    try:
        return sweep_timing(cls, world_params, fps, substeps)
    except ValueError as exc:
        raise UsageError(str(exc)) from None


def _is_usage(exc):
    """Whether a ValueError from the run is about the request (parameters, a spec) rather than a
    failure of the simulation: the batch checks everything before the first step."""
    return not isinstance(exc, OSError) and "frame" not in str(exc).split(":")[0]


if __name__ == "__main__":  # pragma: no cover
    from ..cli import main

    sys.exit(main(["sweep", *sys.argv[1:]]))
