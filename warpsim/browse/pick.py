"""``warpsim pick``: one world of a sweep as a file any USD tool opens (Blender, usdview).

    warpsim pick ROOT --world N --out FILE [--flatten]

Writes ``FILE`` (.usd, .usda or .usdc) whose default prim ``/World`` is world N alone (a
reference to its prim in the sweep's batch layer, or with ``--flatten`` a self-contained copy of
its samples), with the stage settings importers read: ``metersPerUnit``, ``upAxis``,
``startTimeCode`` / ``endTimeCode`` and ``timeCodesPerSecond`` / ``framesPerSecond`` of the
sweep. The world's parameters come along in ``/World``'s ``customData["warpsim"]`` (authored
on every world's prim by the sweep). A picked world is one world, so the file holds it in the
form a lone run writes: curves the sweep stores compactly as its particles' points and
``warpsim:segments`` (springs), which Blender, usdview and Houdini do not read, are written into
the file as the lone run's ``BasisCurves`` (:func:`full_form`; a teapot world: 5,238 curves).
``warpsim pick`` then lists what the file holds (:func:`describe`). A selector layer without these settings imports at the
wrong scale with an empty frame range; Blender's importer cannot choose a variant of the root.
Exit status 2 (one line) for a root that is not a sweep's, a world out of range, a bad ``--out``.
"""
from __future__ import annotations

import os

from ..cli_common import UsageError
from ..core.safe_files import clear_temporary

__all__ = ["UnstoredWorldError", "add_parser", "describe", "full_form", "pick_world", "run"]


class UnstoredWorldError(ValueError):
    """The sweep was run with ``--store none``: the world has no stored frames to pick; re-run it
    (:func:`warpsim.sweeps.rerun.pick_or_rerun`, which ``warpsim pick`` uses)."""


def add_parser(sub):
    s = sub.add_parser("pick", help="write one world of a sweep as a USD file any tool opens (stage settings kept)")
    s.add_argument("root", help="root USD written by 'warpsim sweep'")
    s.add_argument("--world", type=int, required=True, metavar="N", help="the world's index (the table's 'world')")
    s.add_argument("--out", required=True, help="file to write (.usd, .usda or .usdc); a relative path is taken "
                   "from the current folder")
    s.add_argument("--flatten", action="store_true",
                   help="copy the world's samples into the file (self-contained) instead of referencing the batch")
    s.add_argument("--allow-damaged", action="store_true",
                   help="pick from a sweep whose batch layer has damaged chunk files anyway (their frames are missing)")
    return s


def pick_world(root, world, out_path, flatten=False, allow_damaged=False) -> str:
    """Write world ``world`` of the sweep root ``root`` to ``out_path`` (see the module
    docstring) and return its absolute path. ValueError / FileNotFoundError (one line) for a
    root that is not a sweep's, a world it does not hold, an ``out_path`` that is not USD or one
    of the sweep's own files; :class:`warpsim.usd.validate.DamagedCacheError` (exit 1) when the
    world's batch layer has damaged or missing chunk files (checked like ``warpsim info``)."""
    from .roots import sweep_root_files

    if isinstance(world, bool) or not hasattr(world, "__index__"):
        raise TypeError(f"world {world!r} is not an integer index; give the table's 'world' (e.g. 0)")
    for name, value in (("root", root), ("out_path", out_path)):
        if not isinstance(value, (str, os.PathLike)):
            raise TypeError(f"{name} {value!r} is not a path; give a .usda/.usdc file name")
    from .roots import unstored_sweep

    if os.path.isfile(os.fspath(root)) and unstored_sweep(root) is not None:
        raise UnstoredWorldError(f"{root} was swept with --store none: world {int(world)} has no stored frames; "
                                 "warpsim pick re-runs it (warpsim.sweeps.rerun.pick_or_rerun in Python)")
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
    from ..usd.family import check_output
    from ..usd.lock import OutputLock

    from ..usd.validate import check_damage

    check_output(out_path, [root, *sorted(set(owner.values()))], "--out")
    if os.path.isfile(owner[world]):  # (a missing layer is said below)
        from ..usd.pxr_errors import DamagedFileError
        from ..usd.validate import DamagedCacheError

        try:
            check_damage(owner[world], allow_damaged, what="pick", verify=False)  # sizes: cheap per thumbnail
        except DamagedCacheError:
            raise
        except ValueError as exc:  # the batch layer itself does not open: the sweep is damaged (exit 1)
            why = str(exc).rsplit("(USD says: ", 1)[-1].rstrip(")") if "USD says" in str(exc) else str(exc)
            raise DamagedFileError(f"batch layer {os.path.relpath(owner[world])} of world {world} is damaged (does not "
                                   f"open in USD: {why}); run the sweep again") from None
    with OutputLock(out_path, "--out"):
        return _write_pick(root, world, owner, out_path, flatten)


def _write_pick(root, world, owner, out_path, flatten) -> str:
    from pxr import Sdf, Usd

    from .roots import world_prim_name

    from ..usd.pxr_errors import pxr_reason

    try:
        batch = Sdf.Layer.FindOrOpen(owner[world])
    except Exception as exc:  # noqa: BLE001  (Tf.ErrorException: a truncated or damaged batch layer)
        raise ValueError(f"batch layer {owner[world]} of world {world} does not open ({pxr_reason(exc, 120)}); "
                         "run the sweep again") from None
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
    full = full_form(layer, "/World", source, f"/Worlds/{world_prim_name(world)}")
    tmp = out_path + ".tmp" + os.path.splitext(out_path)[1]
    try:
        if flatten:
            result = Usd.Stage.Open(layer).Flatten()
            result.defaultPrim = "World"
            result.customLayerData = dict(layer.customLayerData)
            from ..usd.prims import SEGMENTS_ATTR

            for path in full:  # a self-contained file keeps no trace of the sweep's compact form
                spec = result.GetPrimAtPath(path)
                spec.RemoveProperty(spec.properties[SEGMENTS_ATTR])
        else:
            result = layer
        clear_temporary(tmp)  # never through a link planted at the temporary name
        written = result.Export(tmp)
    except Exception as exc:  # noqa: BLE001  (Tf.ErrorException, often with an empty message)
        why = pxr_reason(exc, 120) if str(exc).strip() else "USD gave no reason"
        raise PermissionError(f"could not write {out_path} ({why}); check the folder is writable and the sweep's "
                              "files are intact") from None
    if not written:
        raise PermissionError(f"could not write {out_path}; check the folder is writable")
    os.replace(tmp, out_path)
    return out_path


def full_form(layer, world_path, batch, batch_world) -> list:
    """Write the curves a sweep stores as its particles' points
    (:class:`warpsim.usd.prims.JoinedPointsDecl`, e.g. springs) of the world prim ``batch_world`` of
    the batch layer file ``batch`` into ``layer`` over its prim ``world_path`` (which references
    that world), in the form a lone run writes them: a ``BasisCurves`` prim declared by the lone
    run's own declaration (:func:`warpsim.usd.prims.curves_decl`) with its samples at every stored
    frame (segment ends, extent, velocities), bit for bit, and the sweep's ``warpsim:segments``
    blocked. Blender,
    usdview and Houdini draw curves; they do not read ``warpsim:segments``. Returns the prim paths
    written (none for a world without such prims)."""
    import numpy as np
    from pxr import Sdf, Usd

    from ..usd.prims import SEGMENTS_ATTR, curves_decl
    from ..usd.writer import declare_prim, to_vt

    stage = Usd.Stage.OpenMasked(os.fspath(batch), Usd.StagePopulationMask([batch_world]))  # this world only
    found = []
    for prim in stage.GetPrimAtPath(batch_world).GetChildren():
        decl = curves_decl(prim)
        if decl is None:
            continue
        keys = ["points"] + (["velocities"] if decl.has_velocities else [])
        attrs = {key: prim.GetAttribute(key) for key in keys}
        times = _stored_times(prim, batch)
        values = [(t, {key: _sample(attrs[key], t) for key in keys}) for t in times]
        frames = [(t, {key: np.asarray(v) for key, v in data.items()}) for t, data in values
                  if all(v is not None for v in data.values())]  # (--allow-damaged: a lost chunk's frames stay out)
        found.append((f"{world_path}/{prim.GetName()}", decl, frames))
    del stage
    with Sdf.ChangeBlock():
        for path, decl, frames in found:
            declare_prim(layer, Sdf.Path(path), decl)
            spec = layer.GetPrimAtPath(path)
            Sdf.AttributeSpec(spec, SEGMENTS_ATTR, Sdf.ValueTypeNames.IntArray, Sdf.VariabilityUniform,
                              True).default = Sdf.ValueBlock()
            for t, data in frames:
                for name, value in decl.frame_samples(data, t).items():
                    layer.SetTimeSample(f"{path}.{name}", t, to_vt(decl.attrs[name].type_name, value))
    return [path for path, _, _ in found]


def _stored_times(prim, batch) -> list:
    """The frames of ``prim``'s ``points`` in the batch layer file ``batch``; where a chunk file is
    damaged (a pick with ``--allow-damaged``; USD then cannot list them at once), the frames of
    the chunk files that open (warpsim's clips map times one to one)."""
    from pxr import Sdf, Tf, Usd

    try:
        return list(prim.GetAttribute("points").GetTimeSamples())
    except Tf.ErrorException:
        pass
    clips = Usd.ClipsAPI(prim.GetParent())
    source = clips.GetClipPrimPath() or str(prim.GetParent().GetPath())
    times = set()
    for asset in clips.GetClipAssetPaths():
        try:
            layer = Sdf.Layer.FindOrOpen(os.path.join(os.path.dirname(os.fspath(batch)), asset.path))
        except Tf.ErrorException:
            continue  # the damaged chunk: its frames are missing
        if layer is not None:
            times.update(layer.ListTimeSamplesForPath(f"{source}/{prim.GetName()}.points"))
    return sorted(times)


def _sample(attr, t):
    """``attr``'s value at time ``t``, or None where its chunk file is lost or damaged (a pick with
    ``--allow-damaged``: those frames are missing from the file, as from the sweep)."""
    from pxr import Tf

    try:
        return attr.Get(t)
    except Tf.ErrorException:
        return None


def describe(path) -> list:
    """Lines saying what the USD file ``path`` holds under its default prim: its frames, and per
    prim its type and counts (points, faces, curves) at the last frame, and an opacity below 1."""
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(os.fspath(path))
    t = Usd.TimeCode(stage.GetEndTimeCode()) if stage.HasAuthoredTimeCodeRange() else Usd.TimeCode.Default()
    lines = []
    if stage.HasAuthoredTimeCodeRange():
        lines.append(f"frames {stage.GetStartTimeCode():g}..{stage.GetEndTimeCode():g} at "
                     f"{stage.GetTimeCodesPerSecond():g} fps")
    rows = []
    for prim in stage.GetDefaultPrim().GetChildren():
        kind = prim.GetTypeName()
        points = prim.GetAttribute("positions" if kind == "PointInstancer" else "points")
        counts = []
        if points and points.HasValue():
            noun = "instances" if kind == "PointInstancer" else "points"
            counts.append(f"{len(_sample(points, t) or []):,} {noun}")
        faces = prim.GetAttribute("faceVertexCounts") if kind == "Mesh" else None
        if faces and faces.HasValue():
            n = len(_sample(faces, t) or [])
            counts.append(f"{n:,} face{'s' if n != 1 else ''}")
        curves = prim.GetAttribute("curveVertexCounts") if kind == "BasisCurves" else None
        if curves and curves.HasValue():
            counts.insert(0, f"{len(_sample(curves, t) or []):,} curves")
        opacity = UsdGeom.PrimvarsAPI(prim).GetPrimvar("displayOpacity")
        if opacity and opacity.HasValue() and len(opacity.Get(t) or []) == 1 and opacity.Get(t)[0] < 1.0:
            counts.append(f"opacity {opacity.Get(t)[0]:g}")
        rows.append((prim.GetName(), kind, ", ".join(counts)))
    width = [max((len(r[k]) for r in rows), default=0) for k in range(2)]
    lines += [f"{name:<{width[0]}}  {kind:<{width[1]}}  {counts}".rstrip() for name, kind, counts in rows]
    return lines


def run(args, out, err):

    from ..usd.pxr_errors import error_line

    return report(args, out, lambda: pick_world(args.root, args.world, args.out, flatten=args.flatten,
                                                allow_damaged=args.allow_damaged))


def report(args, out, pick):
    """Run ``pick()`` (a path) for ``warpsim pick``'s ``args``: one line for bad input (exit 2), a
    damaged sweep raised (exit 1), else the line naming the file written and what it holds
    (:func:`describe`)."""
    from ..usd.pxr_errors import error_line

    try:
        path = pick()
    except (OSError, ValueError) as exc:
        if getattr(exc, "exit_status", 2) != 2:
            raise  # a damaged sweep: exit 1
        raise UsageError(error_line(exc)) from None
    print(f"world {args.world} of {os.path.relpath(os.path.abspath(args.root))}: {os.path.relpath(path)}"
          f"{' (flattened)' if args.flatten else ''}: the world alone, as a lone run writes it:", file=out)
    for line in describe(path):
        print(f"  {line}", file=out)
    return 0
