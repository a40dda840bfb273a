"""``warpsim pick``: one world of a sweep as a file any USD tool opens (Blender, usdview).

    warpsim pick ROOT --world N --out FILE [--flatten]

Writes ``FILE`` (.usd, .usda or .usdc) whose default prim ``/World`` is world N alone (a
reference to its prim in the sweep's batch layer, or with ``--flatten`` a self-contained copy of
its samples), with the stage settings importers read: ``metersPerUnit``, ``upAxis``,
``startTimeCode`` / ``endTimeCode`` and ``timeCodesPerSecond`` / ``framesPerSecond`` of the
sweep. The world's parameters come along in ``/World``'s ``customData["warpsim"]`` (authored
on every world's prim by the sweep). A selector layer without these settings imports at the
wrong scale with an empty frame range; Blender's importer cannot choose a variant of the root.
Exit status 2 (one line) for a root that is not a sweep's, a world out of range, a bad ``--out``.
"""
from __future__ import annotations

import os

__all__ = ["add_parser", "pick_world", "run"]


def add_parser(sub):
    s = sub.add_parser("pick", help="write one world of a sweep as a USD file any tool opens (stage settings kept)")
    s.add_argument("root", help="root USD written by 'warpsim sweep'")
    s.add_argument("--world", type=int, required=True, metavar="N", help="the world's index (the table's 'world')")
    s.add_argument("--out", required=True, help="file to write (.usd, .usda or .usdc)")
    s.add_argument("--flatten", action="store_true",
                   help="copy the world's samples into the file (self-contained) instead of referencing the batch")
    return s


def pick_world(root, world, out_path, flatten=False) -> str:
    """Write world ``world`` of the sweep root ``root`` to ``out_path`` (see the module
    docstring) and return its absolute path. ValueError / FileNotFoundError (one line) for a
    root that is not a sweep's, a world it does not hold, an ``out_path`` that is not USD."""
    from pxr import Sdf, Usd

    from .roots import sweep_root_files
    from .usd import world_prim_name

    files = sweep_root_files(root)
    owner = dict(files["worlds"])
    world = int(world)
    if world not in owner:
        known = sorted(owner)
        raise ValueError(f"--world {world} is out of range: {root} holds worlds {known[0]}..{known[-1]} "
                         f"({len(known)} worlds)" if known == list(range(known[0], known[-1] + 1)) else
                         f"--world {world} is not in {root}; its worlds: {', '.join(map(str, known[:20]))}")
    out_path = os.path.abspath(os.fspath(out_path))
    if os.path.splitext(out_path)[1] not in (".usd", ".usda", ".usdc"):
        raise ValueError(f"--out {out_path!r} must end in .usd, .usda or .usdc")
    if os.path.isdir(out_path):
        raise ValueError(f"--out {out_path!r} is a folder; name a file in it")
    batch = Sdf.Layer.FindOrOpen(owner[world])
    if batch is None:
        raise FileNotFoundError(f"batch layer {owner[world]} of world {world} is missing; run the sweep again")
    folder = os.path.dirname(out_path)
    os.makedirs(folder, exist_ok=True)
    layer = Sdf.Layer.CreateAnonymous(".usda")
    layer.defaultPrim = "World"
    fps = batch.timeCodesPerSecond
    layer.timeCodesPerSecond = fps
    layer.framesPerSecond = batch.framesPerSecond if batch.HasFramesPerSecond() else fps
    layer.pseudoRoot.SetInfo("upAxis", batch.pseudoRoot.GetInfo("upAxis") if batch.pseudoRoot.HasInfo("upAxis")
                             else "Y")
    layer.pseudoRoot.SetInfo("metersPerUnit", batch.pseudoRoot.GetInfo("metersPerUnit")
                             if batch.pseudoRoot.HasInfo("metersPerUnit") else 1.0)
    if batch.HasStartTimeCode():
        layer.startTimeCode, layer.endTimeCode = batch.startTimeCode, batch.endTimeCode
    spec = Sdf.CreatePrimInLayer(layer, "/World")
    spec.specifier = Sdf.SpecifierDef
    spec.typeName = "Xform"
    source = os.path.abspath(owner[world])
    asset = source if flatten else os.path.relpath(source, folder).replace(os.sep, "/")
    if not flatten and not asset.startswith("."):
        asset = "./" + asset
    spec.referenceList.Prepend(Sdf.Reference(asset, f"/Worlds/{world_prim_name(world)}"))
    layer.customLayerData = {"warpsim": {"pickedWorld": world, "sweepRoot": os.path.abspath(os.fspath(root))}}
    if flatten:
        result = Usd.Stage.Open(layer).Flatten()
        result.defaultPrim = "World"
        result.customLayerData = dict(layer.customLayerData)
    else:
        result = layer
    tmp = out_path + ".tmp" + os.path.splitext(out_path)[1]
    if not result.Export(tmp):
        raise PermissionError(f"could not write {out_path}; check the folder is writable")
    os.replace(tmp, out_path)
    return out_path


def run(args, out, err):
    from .. import cli

    try:
        path = pick_world(args.root, args.world, args.out, flatten=args.flatten)
    except (FileNotFoundError, ValueError) as exc:
        raise cli.UsageError(str(exc)) from None
    print(f"world {args.world} of {os.path.relpath(os.path.abspath(args.root))}: {os.path.relpath(path)}"
          f"{' (flattened)' if args.flatten else ''}", file=out)
    return 0
