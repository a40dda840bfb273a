"""``warpsim sweep``: many worlds of one scene in one batched run.

    warpsim sweep SCENE --worlds N --vary KEY=LO:HI[:log] --vary KEY=A,B,C [--sample grid|random|lhs]
                  [--seed S] [--frames N] [--fps F] [--substeps S] [--device D] [--out PATH]
                  [--set KEY=VALUE ...] [--layout variants|grid] [--table CSV] [--track NAME=INDEX ...]
                  [--rank METRIC [--top K]] [--where METRIC<VALUE ...]

Writes ``PATH`` (default ``usd_out/SCENE_sweep.usda``): a root whose ``/World`` carries a variant
set ``world`` (or, with ``--layout grid``, every world side by side), the batch layer beside it
(``<stem>.batch_0000.usdc``) and the table ``<stem>.csv`` (one row per world: parameters and
metrics). ``--rank``/``--where`` print the picked worlds and write ``<stem>.picked.usda`` holding
only those. Exit status 2 for usage mistakes (one line), 1 when the run fails.
"""
from __future__ import annotations

import os
import sys

from . import preflight

LAYER_EXT = ".usdc"


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
    s.add_argument("--substeps", type=int, default=None, help="steps per frame (default: the scene's)")
    s.add_argument("--device", default=None, help="Warp device, e.g. cpu or cuda:0 (default: CUDA when present)")
    s.add_argument("--out", default=None, help="root USD to write (default usd_out/SCENE_sweep.usda)")
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
    s.add_argument("--fused", action="store_true",
                   help="step mass-spring scenes through the fused semi-implicit kernel (faster on GPUs; agrees "
                        "to float32 rounding)")
    s.add_argument("--no-progress", action="store_true", help="no progress bar")
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
            if cls.name != "teapot":
                raise ValueError(f"--track {item!r}: give a particle index (NAME=INDEX)") from None
            from ..scenes.teapot import ANCHORS, anchor_vertex

            if value not in ANCHORS:
                raise ValueError(f"--track {item!r}: not an index or one of {', '.join(ANCHORS)}") from None
            if scene is None:
                scene = cls(params, device=device)
            q0 = scene.model.particle_q.numpy()[: scene.body.surface_count]
            index = anchor_vertex(q0, value)
        name = (name or (value if not value.lstrip("-").isdigit() else f"p{index}")).strip()
        out[name] = index
    return out


def _format(value):
    if isinstance(value, float):
        return f"{value:.6g}"
    if isinstance(value, (tuple, list)):
        return ",".join(f"{v:g}" for v in value)
    return str(value)


def run(args, out, err):
    import warp as wp

    wp.config.quiet = True
    if hasattr(wp, "LOG_WARNING"):
        wp.config.log_level = wp.LOG_WARNING
    from .. import cli
    from ..core.errors import SimulationError
    from ..distributed.ray_sweep import RaySweepError, ray_usage_error
    from ..scenes import get_scene
    from .metrics import BUILTIN, parse_rank, parse_where, select
    from .sweep import run_batch, sample_worlds, write_table
    from .usd import LAYOUTS, write_sweep_root

    usage = cli.UsageError
    try:
        cls = get_scene(args.scene)
    except ValueError as exc:
        raise usage(str(exc)) from None
    if args.frames < 0:
        raise usage(f"--frames {args.frames}: it must be >= 0")
    if args.layout not in LAYOUTS:
        raise usage(f"--layout {args.layout!r}: use one of {', '.join(LAYOUTS)}")
    if ray_usage_error(args):
        raise usage(ray_usage_error(args))
    if args.top is not None and args.top < 1:
        raise usage(f"--top {args.top}: it must be >= 1")
    if args.top is not None and args.rank is None:
        raise usage("--top needs --rank METRIC (the order to take the top worlds from)")
    path = args.out or os.path.join("usd_out", f"{cls.name}_sweep.usda")
    stem, ext = os.path.splitext(path)
    if ext not in (".usd", ".usda", ".usdc"):
        raise usage(f"--out {path!r} must end in .usd, .usda or .usdc")
    table = args.table or stem + ".csv"
    try:  # seed, world count, --ray address: before anything is sampled
        preflight.check_seed(args.seed)
        if args.worlds is not None:
            preflight.check_worlds(args.worlds)
        preflight.check_ray_address(getattr(args, "ray", None))
    except ValueError as exc:
        raise usage(str(exc)) from None
    cli._check_out(path, "--out")
    if os.path.splitext(table)[1].lower() != ".csv":
        raise usage(f"--table {table!r} must end in .csv")
    cli._check_out(table, "--table")
    fixed = cli._parse_sets(cls, args.sets, None)
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
        fps, _, _ = _timing(cls, base, args.fps, args.substeps)
        track = resolve_track(cls, base, args.track, "cpu") if args.track else None
    except ValueError as exc:
        raise usage(str(exc)) from None
    names = [k for k in world_params[0]] + list(BUILTIN)
    for name in track or {}:
        names += [f"{name}_x", f"{name}_y", f"{name}_z", f"{name}_peak_y"]
    try:  # picking is checked before anything runs
        rank = parse_rank(args.rank, names) if args.rank else None
        where = [parse_where(w, names) for w in args.where]
        numeric = preflight.numeric_columns(world_params)
        for flag, metric in ([("--rank", rank[0])] if rank else []) + [("--where", w[0]) for w in where]:
            if metric in world_params[0] and metric not in numeric:
                value = world_params[0][metric]
                kind = "a vector" if isinstance(value, (tuple, list)) else f"a {type(value).__name__}"
                raise ValueError(f"{flag} {metric}: parameter {metric} is {kind} ({_format(value)}), not one number; "
                                 f"{flag} compares numbers: a metric ({', '.join(BUILTIN[:3])}, ...) or a numeric "
                                 f"parameter ({', '.join(sorted(numeric)) or 'none here'})")
    except ValueError as exc:
        raise usage(str(exc)) from None
    device = cli._device(args.device)
    if getattr(args, "ray", None) is None:
        try:
            _check_memory(cls, base, len(world_params), device)
        except ValueError as exc:
            raise usage(str(exc)) from None
    layer = f"{stem}.batch_0000{LAYER_EXT}"
    progress = None
    try:
        if getattr(args, "ray", None) is not None:
            from ..distributed.ray_sweep import DEFAULT_BATCH_SIZE, run_ray_sweep

            result = run_ray_sweep(cls.name, world_params, frames=args.frames, out_path=path, table_path=table,
                                   fps=args.fps, substeps=args.substeps, device=args.device,
                                   batch_size=args.batch_size or DEFAULT_BATCH_SIZE, address=args.ray,
                                   num_cpus=args.ray_cpus, resume=args.resume, layout=args.layout,
                                   batch_options={**({"track": track} if track else {}),
                                                  **({"fused": True} if args.fused else {})} or None, log=err)
            rows, root = result["rows"], result["root"]
            import glob

            layers = sorted(glob.glob(os.path.join(glob.escape(stem) + ".batches", "batch_*", "*" + LAYER_EXT)))
        else:
            if not args.no_progress:
                from tqdm import tqdm

                progress = tqdm(total=args.frames, unit="frame", desc=f"{cls.name} x{len(world_params)}", file=err,
                                dynamic_ncols=True)
            rows = run_batch(cls.name, world_params, frames=args.frames, fps=args.fps, substeps=args.substeps,
                             device=device, layer_path=layer, first_world=0, track=track,
                             progress=(lambda f: progress.update(1)) if progress else None, fused=args.fused)
            if progress:
                progress.close()
                progress = None
            write_table(table, rows)
            layers = [layer]
            root = write_sweep_root(path, layers, len(world_params), layout=args.layout)
    except (SimulationError, ValueError, RaySweepError) as exc:
        if progress:
            progress.close()
        if isinstance(exc, ValueError) and not isinstance(exc, SimulationError) and _is_usage(exc):
            raise usage(str(exc).splitlines()[0]) from None
        print(f"warpsim: sweep failed: {str(exc).splitlines()[0]}", file=err)
        return 1
    blown = sum(1 for r in rows if r.get("blown_up"))
    print(f"ran {len(rows)} worlds of scene {cls.name!r} x {args.frames} frames at {fps:g} fps on {device}"
          f"{f' ({blown} blew up and were frozen)' if blown else ''}", file=out)
    print(f"open: {os.path.relpath(root)}   table: {os.path.relpath(table)}", file=out)
    if args.rank or args.where:
        picked = select(rows, rank=rank, top=args.top, where=where)
        shown = [k for k in world_params[0]] + [m for m in ([rank[0]] if rank else []) + [w[0] for w in where]
                                                 if m not in world_params[0]]
        shown = list(dict.fromkeys(shown))
        print(f"picked {len(picked)} of {len(rows)} worlds:", file=out)
        print("  " + "  ".join(["world", *shown]), file=out)
        for r in picked:
            print("  " + "  ".join([str(r["world"]), *(_format(r.get(k, "")) for k in shown)]), file=out)
        if picked:
            pick_path = write_sweep_root(stem + ".picked" + ext, layers, len(rows), layout=args.layout,
                                         worlds=[r["world"] for r in picked])
            print(f"picked worlds: {os.path.relpath(pick_path)}", file=out)
    return 0


def _check_memory(cls, base, worlds, device):
    """Refuse a sweep whose memory estimate (from world 0 built on the CPU) does not fit."""
    scene = cls(base, device="cpu")
    model = getattr(getattr(scene, "sim", None), "model", None)
    if model is None:
        return
    preflight.check_sweep_memory(cls.name, int(model.particle_count), int(model.spring_count), worlds, device)


def _timing(cls, params, fps, substeps):
    from .. import cli
    from .sweep import frame_timing

    try:
        return frame_timing(cls, params, fps, substeps)
    except ValueError as exc:
        raise cli.UsageError(f"--fps/--substeps: {exc}") from None


def _is_usage(exc):
    """Whether a ValueError from the run is about the request (parameters, a spec) rather than a
    failure of the simulation: the batch checks everything before the first step."""
    return not isinstance(exc, OSError) and "frame" not in str(exc).split(":")[0]


if __name__ == "__main__":  # pragma: no cover
    from ..cli import main

    sys.exit(main(["sweep", *sys.argv[1:]]))
