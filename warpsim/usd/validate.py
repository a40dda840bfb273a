"""Reading warpsim USD caches back: validation and summaries (``pxr`` imported lazily).

* :func:`validate_cache` runs ``pxr.UsdValidation`` (every registered validator except the
  usdz-packaging ones; ``UsdUtils.ComplianceChecker`` on older usd-core), checks every mesh
  sample with ``UsdGeom.Mesh.ValidateTopology`` and checks warpsim's conventions (stage
  metadata, extent at every sample containing the padded points, velocities with the same
  length and time samples as points). It returns a list of error strings (empty = valid).
* :func:`cache_info` summarises a cache: frame range, prims, element counts and bounds, and for
  chunked caches which chunk files are damaged and which frames stay readable
  (:func:`chunk_health`, from the root layer and the chunk index alone).
"""
from __future__ import annotations

import math
import os

from .pxr_errors import pxr_reason

import numpy as np

__all__ = ["DamagedCacheError", "cache_info", "check_damage", "chunk_health", "damage_report", "open_stage",
           "root_chunks", "sweep_layers", "validate_cache"]

_POINT_ATTR = {"Points": "points", "Mesh": "points", "BasisCurves": "points", "PointInstancer": "positions"}


def open_path(path):
    """``path`` as a str if a file exists there; MissingFileError (a ValueError) naming it otherwise."""
    path = os.fspath(path)
    if os.path.isfile(path) and os.access(path, os.R_OK):
        return path  # the common case without importing warpsim.core (and Warp): 'warpsim info' stays fast
    if os.path.exists(path) and not os.path.isdir(path):  # a FIFO, socket or device would block or never end
        raise ValueError(f"USD cache {path!r} is not a regular file (a pipe, socket or device); give the cache "
                         "file itself (.usd, .usda or .usdc)")
    from ..core.checks import existing_file

    return existing_file(path, "USD cache")


def _not_usd(path, exc):
    """ValueError for a file that does not open as USD: warpsim's words, pxr's reason trailing."""
    path = os.fspath(path)
    try:
        size = os.path.getsize(path)
    except OSError:
        size = None
    what = "is empty (0 bytes)" if size == 0 else "is not a readable USD file (truncated, damaged or another format)"
    return ValueError(f"USD cache {path!r} {what}; write it again with 'warpsim run' (USD says: {pxr_reason(exc)})")


def open_stage(path_or_stage):
    """``Usd.Stage`` for a path (ValueError if it does not open) or an already open stage."""
    from pxr import Usd

    if isinstance(path_or_stage, Usd.Stage):
        return path_or_stage
    path = open_path(path_or_stage)
    try:
        stage = Usd.Stage.Open(path)
    except Exception as exc:  # noqa: BLE001  (pxr raises Tf.ErrorException)
        raise _not_usd(path, exc) from None
    if stage is None:
        raise ValueError(f"USD cache {path!r} does not open")
    return stage


def frame_codes(stage):
    """Integer time codes from startTimeCode to endTimeCode (empty when the stage has none)."""
    if not stage.HasAuthoredTimeCodeRange():
        return []
    return list(range(math.ceil(stage.GetStartTimeCode()), math.floor(stage.GetEndTimeCode()) + 1))


def _usd_validation_errors(stage):
    try:
        from pxr import UsdValidation
    except ImportError:  # older usd-core
        from pxr import UsdUtils

        checker = UsdUtils.ComplianceChecker(skipARKitRootLayerCheck=True)
        checker.CheckCompliance(stage.GetRootLayer().identifier)
        return [f"ComplianceChecker: {e}" for e in checker.GetErrors() + checker.GetFailedChecks()]
    registry = UsdValidation.ValidationRegistry()
    validators = [v for v in registry.GetOrLoadAllValidators()
                  if "UsdzValidators" not in v.GetMetadata().GetKeywords()]
    context = UsdValidation.ValidationContext(validators)
    out = []
    for err in context.Validate(stage):
        if err.GetType() == UsdValidation.ValidationErrorType.Error:
            out.append(f"UsdValidation {err.GetName()}: {err.GetMessage()}")
    return out


def _check_metadata(stage):
    from pxr import UsdGeom

    out = []
    if UsdGeom.GetStageUpAxis(stage) != UsdGeom.Tokens.y:
        out.append(f"upAxis is {UsdGeom.GetStageUpAxis(stage)!r}, expected 'Y'")
    if UsdGeom.GetStageMetersPerUnit(stage) != 1.0:
        out.append(f"metersPerUnit is {UsdGeom.GetStageMetersPerUnit(stage)}, expected 1")
    if stage.GetTimeCodesPerSecond() != stage.GetFramesPerSecond():
        out.append(f"timeCodesPerSecond {stage.GetTimeCodesPerSecond()} != framesPerSecond "
                   f"{stage.GetFramesPerSecond()}")
    if not stage.GetDefaultPrim():
        out.append("no defaultPrim")
    return out


def _check_prim(prim, frames):
    """Mesh topology and warpsim conventions at every frame of one prim."""
    from pxr import UsdGeom

    out = []
    type_name = prim.GetTypeName()
    where = str(prim.GetPath())
    pattr = prim.GetAttribute(_POINT_ATTR[type_name])
    vattr = prim.GetAttribute("velocities")
    eattr = prim.GetAttribute("extent")
    varying = pattr.ValueMightBeTimeVarying()
    if vattr and vattr.HasAuthoredValue() and vattr.GetTimeSamples() != pattr.GetTimeSamples():
        out.append(f"{where}: velocities and {pattr.GetName()} have different time samples")
    if varying and eattr.GetTimeSamples() != pattr.GetTimeSamples():
        out.append(f"{where}: extent is not authored at every {pattr.GetName()} sample")
    for t in frames if varying else [None]:
        code = t if t is not None else 0.0
        pts = pattr.Get(code)
        n = 0 if pts is None else len(pts)
        pad = 0.0
        if type_name in ("Points", "BasisCurves"):
            widths = prim.GetAttribute("widths").Get(code)
            if widths is not None and len(widths) == 1:
                pad = 0.5 * float(widths[0])
            elif widths is not None and len(widths) == n:  # per point (curves: per vertex, e.g. hair)
                pad = 0.5 * np.asarray(widths, np.float64)[:, None]
            elif widths is not None and len(widths):
                out.append(f"{where} at {t}: {len(widths)} widths for {n} points")
        elif type_name == "PointInstancer":
            pad = None  # prototype bounds: check only that the positions lie inside
        if vattr and vattr.HasAuthoredValue():
            vel = vattr.Get(code)
            if vel is None or len(vel) != n:
                out.append(f"{where} at {t}: {0 if vel is None else len(vel)} velocities for {n} points")
        ext = eattr.Get(code)
        if ext is None or len(ext) != 2:
            out.append(f"{where} at {t}: no extent")
        elif n:
            p = np.asarray(pts, np.float64)
            lo = (p - (0.0 if pad is None else pad)).min(0)
            hi = (p + (0.0 if pad is None else pad)).max(0)
            e = np.asarray(ext, np.float64)
            tol = 1e-5 * (1.0 + np.abs(e).max())
            if (lo < e[0] - tol).any() or (hi > e[1] + tol).any():
                out.append(f"{where} at {t}: extent {e.tolist()} does not contain the points")
            if pad is not None and type_name != "Mesh" and ((lo > e[0] + tol).any() or (hi < e[1] - tol).any()):
                out.append(f"{where} at {t}: extent {e.tolist()} is looser than the padded points")
        if type_name == "Mesh":
            mesh = UsdGeom.Mesh(prim)
            ok, why = UsdGeom.Mesh.ValidateTopology(mesh.GetFaceVertexIndicesAttr().Get(code),
                                                    mesh.GetFaceVertexCountsAttr().Get(code), n)
            if not ok:
                out.append(f"{where} at {t}: invalid topology: {why}")
        if type_name == "PointInstancer":
            for name in ("protoIndices", "ids", "orientations"):
                a = prim.GetAttribute(name)
                if a and a.HasAuthoredValue() and len(a.Get(code)) != n:
                    out.append(f"{where} at {t}: {name} has {len(a.Get(code))} entries for {n} positions")
        ids = prim.GetAttribute("ids") if type_name == "Points" else None
        if ids and ids.HasAuthoredValue() and len(ids.Get(code)) != n:
            out.append(f"{where} at {t}: {len(ids.Get(code))} ids for {n} points")
    return out


def validate_cache(path_or_stage):
    """List of validation errors of a cache (empty when it is valid); see the module docstring."""
    stage = open_stage(path_or_stage)
    errors = _usd_validation_errors(stage) + _check_metadata(stage)
    frames = frame_codes(stage)
    for prim in stage.Traverse():
        if prim.GetTypeName() in _POINT_ATTR:
            errors += _check_prim(prim, frames)
    return errors


def root_chunks(layer, root_prim=None):
    """[[start, end, file], ...] listed by a warpsim root layer, or None if it lists none."""
    data = dict(layer.customLayerData.get("warpsim", {}))
    world = layer.GetPrimAtPath("/" + (root_prim or layer.defaultPrim or "World"))
    if world and not world.HasInfo("clips"):  # a sweep's batch layer: the same clips on every world prim
        world = next((c for c in world.nameChildren if c.HasInfo("clips")), world)
    clips = dict(world.GetInfo("clips")).get("default") if world and world.HasInfo("clips") else None
    if not clips or "chunkEnds" not in data:
        return None
    starts = [int(a[0]) for a in clips["active"]]
    files = [os.path.basename(p.path) for p in clips["assetPaths"]]
    return [[s, int(e), f] for s, e, f in zip(starts, data["chunkEnds"], files)]


def chunk_health(path, verify=None):
    """Damage report of a chunked cache from its root layer and chunk index (no chunk is opened
    in USD unless the cache has no index): dict with ``chunks`` [[start, end, file], ...],
    ``records`` (the index, None if absent), ``damaged`` [(file, start, end, why)], ``readable``
    merged frame ranges [(start, end)] and ``checked`` (what was compared). ``verify`` (None:
    only when the chunks total <= 256 MiB) also compares every chunk's CRC-32, reading its
    bytes. None for a cache that is not chunked (e.g. flattened)."""
    from pxr import Sdf

    from . import chunk_index

    path = os.path.abspath(os.fspath(path))
    try:
        layer = Sdf.Layer.OpenAsAnonymous(path)
    except Exception as exc:  # noqa: BLE001  (Tf.ErrorException)
        raise _not_usd(path, exc) from None
    if layer is None:
        raise ValueError(f"USD cache {path!r} does not open")
    chunks = root_chunks(layer)
    if chunks is None:
        return None
    dirname, base = os.path.split(path)
    named = dict(layer.customLayerData.get("warpsim", {})).get("chunkIndex")
    index_file = os.path.join(dirname, os.path.basename(str(named))) if named else \
        chunk_index.index_path(dirname, os.path.splitext(base)[0])
    records = chunk_index.read_index(index_file)
    if records is not None and verify is None:
        verify = sum(r.get("bytes", 0) for r in records.values()) <= 256 << 20
    run = dict(layer.customLayerData.get("warpsim", {})).get("run")
    damaged = []
    for start, end, fname in chunks:
        rec = None if records is None else records.get(fname)
        why = chunk_index.chunk_problem(dirname, fname, rec, verify=bool(verify))
        if why is None and records is not None and rec is None:
            why = "not in the chunk index"
        if why is None and rec is not None and run and rec.get("run") not in (None, run):
            why = (f"written by another run ({rec['run']}; the root layer's is {run}): two processes wrote this "
                   "cache at once; run it again")
        if why:
            damaged.append((fname, start, end, why))
    checked = "opened in USD" if records is None else "size and CRC-32" if verify else "size"
    return {"chunks": chunks, "records": records, "damaged": damaged, "checked": checked,
            "readable": chunk_index.readable_ranges(chunks, {d[0] for d in damaged})}


class DamagedCacheError(ValueError):
    """A cache with damaged chunk files, read without ``allow_damaged`` (exit status 1 on the
    command line). ``report`` holds ``damaged`` [(file, start, end, why)] and ``readable``."""

    exit_status = 1

    def __init__(self, message, report):
        super().__init__(message)
        self.report = report


def sweep_layers(path):
    """Absolute paths of the layers a sweep root references (its batch layers); [] for a cache
    that references none. ValueError when the root itself does not open."""
    from pxr import Sdf

    path = os.path.abspath(os.fspath(path))
    try:
        layer = Sdf.Layer.OpenAsAnonymous(path)
    except Exception as exc:  # noqa: BLE001  (Tf.ErrorException)
        raise _not_usd(path, exc) from None
    if layer is None:
        raise ValueError(f"USD cache {path!r} does not open")
    folder = os.path.dirname(path)
    out = []
    for asset in layer.GetCompositionAssetDependencies():
        target = os.path.normpath(os.path.join(folder, str(asset)))
        if target not in out and os.path.splitext(target)[1] in (".usd", ".usda", ".usdc"):
            out.append(target)
    return out


def damage_report(path, verify=None):
    """``{"damaged", "readable", "checked", "start", "end"}`` of a chunked cache or of a sweep
    root (every batch layer it references, each checked like :func:`chunk_health`; a missing or
    unopenable layer damages every frame); None for a cache with neither (nothing to check)."""
    from pxr import Sdf

    path = os.path.abspath(os.fspath(path))
    health = chunk_health(path, verify)
    if health is not None:
        chunks = health["chunks"]
        return {"damaged": health["damaged"], "readable": health["readable"], "checked": health["checked"],
                "start": chunks[0][0] if chunks else None, "end": chunks[-1][1] if chunks else None}
    layers = sweep_layers(path)
    if not layers:
        return None
    root = Sdf.Layer.OpenAsAnonymous(path)
    start = int(root.startTimeCode) if root.HasStartTimeCode() else None
    end = int(root.endTimeCode) if root.HasEndTimeCode() else None
    damaged, checked = [], set()
    for layer_path in layers:
        name = os.path.basename(layer_path)
        if not os.path.isfile(layer_path):
            damaged.append((name, start, end, "missing (a batch layer of this sweep)"))
            continue
        try:
            sub = chunk_health(layer_path, verify)
        except ValueError as exc:
            why = str(exc).rsplit("(USD says: ", 1)[-1].rstrip(")") if "USD says" in str(exc) else str(exc)
            damaged.append((name, start, end, f"damaged (does not open in USD: {why[:100]})"))
            continue
        if sub is None:  # one self-contained layer: it must open
            checked.add("opened in USD")
            continue
        checked.add(sub["checked"])
        damaged += [(f"{name}: {f}", a, b, why) for f, a, b, why in sub["damaged"]]
        if sub["chunks"]:
            start = sub["chunks"][0][0] if start is None else min(start, sub["chunks"][0][0])
            end = sub["chunks"][-1][1] if end is None else max(end, sub["chunks"][-1][1])
    return {"damaged": damaged, "readable": _readable(start, end, damaged),
            "checked": ", ".join(sorted(checked)) or "layers exist", "start": start, "end": end}


def _readable(start, end, damaged):
    """Frame ranges of start..end outside every damaged (file, a, b, why) range."""
    if start is None or end is None:
        return []
    bad = sorted((a if a is not None else start, b if b is not None else end) for _, a, b, _ in damaged)
    out, t = [], start
    for a, b in bad:
        if a > t:
            out.append((t, min(a - 1, end)))
        t = max(t, b + 1)
    if t <= end:
        out.append((t, end))
    return out


def bad_frames(report) -> set:
    """Frames of a :func:`damage_report` that lie in a damaged chunk or layer."""
    if not report or not report["damaged"]:
        return set()
    start, end = report["start"], report["end"]
    out = set()
    for _, a, b, _ in report["damaged"]:
        a = start if a is None else a
        b = end if b is None else b
        if a is not None and b is not None:
            out.update(range(int(a), int(b) + 1))
    return out


def describe_ranges(ranges) -> str:
    return ", ".join(f"{a}..{b}" if a != b else f"{a}" for a, b in ranges) or "none"


def check_damage(path, allow_damaged=False, what="draw", verify=None):
    """Frames to leave out of ``path`` (a set; empty for an intact cache) after checking its
    chunk index like ``warpsim info`` (``verify``: as :func:`chunk_health`; False: sizes only).
    Without ``allow_damaged`` a damaged cache raises :class:`DamagedCacheError` naming the first
    damaged chunk and the readable frames."""
    if isinstance(path, str) or isinstance(path, os.PathLike):
        report = damage_report(path, verify)
    else:
        return set()
    if not report or not report["damaged"]:
        return set()
    first = report["damaged"][0]
    readable = describe_ranges(report["readable"])
    span = f"frames {first[1]}..{first[2]}" if first[1] is not None else "every frame"
    if not allow_damaged or not report["readable"]:
        if not report["readable"]:
            raise DamagedCacheError(f"cache {os.fspath(path)!r} is damaged: {first[0]} ({span}) is {first[3]} and no "
                                    f"frame is readable; nothing to {what}: restore the file or run again", report)
        raise DamagedCacheError(f"cache {os.fspath(path)!r} is damaged: {len(report['damaged'])} chunk file(s), "
                                f"first {first[0]} ({span}) is {first[3]}; readable frames: {readable}; {what} only "
                                "those with --allow-damaged (allow_damaged=True), or restore the file", report)
    return bad_frames(report)


def cache_info(path_or_stage, verify=None):
    """Summary dict: ``fps``, ``start``, ``end``, ``frames`` and ``prims`` (path, type, min/max
    element count, union of extents over all frames as ``bounds`` [[lo], [hi]] in metres).

    For a path to a chunked cache also ``damaged``, ``readable`` and ``checked`` (see
    :func:`chunk_health`); counts and bounds of time-varying prims then come from the chunk
    index of the readable chunks, so no chunk is opened (a 50,000-frame cache in well under a
    second). Caches without an index (older or flattened ones) are read frame by frame."""
    from pxr import Gf, Usd, UsdGeom

    health = None if isinstance(path_or_stage, Usd.Stage) else chunk_health(open_path(path_or_stage), verify)
    if health is not None and (health["records"] is not None or health["damaged"]):
        return _indexed_info(path_or_stage, health)
    sweep = None if isinstance(path_or_stage, Usd.Stage) or health is not None else \
        damage_report(open_path(path_or_stage), verify)
    if sweep is not None and sweep["damaged"]:  # a sweep root with a damaged batch layer: read nothing of them
        from pxr import Sdf

        root = Sdf.Layer.OpenAsAnonymous(os.path.abspath(os.fspath(path_or_stage)))
        frames = sum(b - a + 1 for a, b in _readable(sweep["start"], sweep["end"], []))
        return {"path": os.path.abspath(os.fspath(path_or_stage)), "fps": root.timeCodesPerSecond, "start": sweep["start"], "end": sweep["end"],
                "frames": frames, "prims": [], "damaged": sweep["damaged"], "readable": sweep["readable"],
                "checked": sweep["checked"]}
    if sweep is not None:
        health = {"checked": sweep["checked"]}
    stage = open_stage(path_or_stage)
    frames = frame_codes(stage)
    prims = []
    for prim in stage.Traverse():
        if not prim.IsA(UsdGeom.Boundable):
            continue
        entry = {"path": str(prim.GetPath()), "type": str(prim.GetTypeName())}
        pattr = prim.GetAttribute(_POINT_ATTR.get(prim.GetTypeName(), "points"))
        eattr = UsdGeom.Boundable(prim).GetExtentAttr()
        times = frames if eattr.ValueMightBeTimeVarying() else [Usd.TimeCode.Default()]
        counts, lo, hi = [], np.full(3, np.inf), np.full(3, -np.inf)
        for t in times:
            if pattr:
                value = pattr.Get(t)
                counts.append(0 if value is None else len(value))
            ext = eattr.Get(t)
            if ext is not None and len(ext) == 2:
                box = Gf.BBox3d(Gf.Range3d(Gf.Vec3d(*ext[0]), Gf.Vec3d(*ext[1])),
                                UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(t))
                world = box.ComputeAlignedRange()
                lo = np.minimum(lo, np.asarray(world.GetMin()))
                hi = np.maximum(hi, np.asarray(world.GetMax()))
        if counts:
            entry["count"] = (min(counts), max(counts))
        if np.isfinite(lo).all():
            entry["bounds"] = [lo.tolist(), hi.tolist()]
        entry["animated"] = len(times) > 1
        prims.append(entry)
    out = {"path": stage.GetRootLayer().realPath, "fps": stage.GetTimeCodesPerSecond(),
           "start": frames[0] if frames else None, "end": frames[-1] if frames else None,
           "frames": len(frames), "prims": prims}
    if health is not None:
        out.update(damaged=[], readable=[(out["start"], out["end"])] if frames else [], checked=health["checked"])
    return out


def _indexed_info(path, health):
    """cache_info from the root layer (static prims) and the chunk index (time-varying ones)."""
    from pxr import Gf, Usd, UsdGeom

    stage = open_stage(path)
    world = stage.GetDefaultPrim()
    records = health["records"] or {}
    bad = {d[0] for d in health["damaged"]}
    good = [records[f] for _, _, f in health["chunks"] if f not in bad and f in records]
    chunks = health["chunks"]
    prims = []
    for prim in stage.Traverse():
        if not prim.IsA(UsdGeom.Boundable):
            continue
        entry = {"path": str(prim.GetPath()), "type": str(prim.GetTypeName())}
        parent = prim.GetParent()
        name = prim.GetName() if world and (parent == world or parent.GetParent() == world) else None
        animated = any(name in r.get("prims", {}) for r in records.values()) if name else False
        if animated:
            stats = [r["prims"][name] for r in good if name in r.get("prims", {})]
            counts = [c for st in stats if "count" in st for c in st["count"]]
            boxes = [st["bounds"] for st in stats if "bounds" in st]
            if counts:
                entry["count"] = (min(counts), max(counts))
            if boxes:
                b = np.asarray(boxes, np.float64)
                entry["bounds"] = [b[:, 0].min(0).tolist(), b[:, 1].max(0).tolist()]
        else:
            t = Usd.TimeCode.Default()
            pattr = prim.GetAttribute(_POINT_ATTR.get(prim.GetTypeName(), "points"))
            value = pattr.Get(t) if pattr else None
            if pattr:
                entry["count"] = (0, 0) if value is None else (len(value), len(value))
            ext = UsdGeom.Boundable(prim).GetExtentAttr().Get(t)
            if ext is not None and len(ext) == 2:
                box = Gf.BBox3d(Gf.Range3d(Gf.Vec3d(*ext[0]), Gf.Vec3d(*ext[1])),
                                UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(t))
                world_box = box.ComputeAlignedRange()
                entry["bounds"] = [list(world_box.GetMin()), list(world_box.GetMax())]
        entry["animated"] = animated
        prims.append(entry)
    return {"path": stage.GetRootLayer().realPath, "fps": stage.GetTimeCodesPerSecond(),
            "start": chunks[0][0] if chunks else None, "end": chunks[-1][1] if chunks else None,
            "frames": sum(e - s + 1 for s, e, _ in chunks), "prims": prims, "damaged": health["damaged"],
            "readable": health["readable"], "checked": health["checked"]}
