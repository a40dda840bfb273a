"""Reading warpsim USD caches back: validation and summaries (``pxr`` imported lazily).

* :func:`validate_cache` runs ``pxr.UsdValidation`` (every registered validator except the
  usdz-packaging ones; ``UsdUtils.ComplianceChecker`` on older usd-core), checks every mesh
  sample with ``UsdGeom.Mesh.ValidateTopology`` and checks warpsim's conventions (stage
  metadata, extent at every sample containing the padded points, velocities with the same
  length and time samples as points). It returns a list of error strings (empty = valid).
* :func:`cache_info` summarises a cache: frame range, prims, element counts and bounds.
"""
from __future__ import annotations

import math
import os

import numpy as np

__all__ = ["cache_info", "open_stage", "validate_cache"]

_POINT_ATTR = {"Points": "points", "Mesh": "points", "BasisCurves": "points", "PointInstancer": "positions"}


def open_stage(path_or_stage):
    """``Usd.Stage`` for a path (ValueError if it does not open) or an already open stage."""
    from pxr import Usd

    if isinstance(path_or_stage, Usd.Stage):
        return path_or_stage
    path = os.fspath(path_or_stage)
    if not os.path.exists(path):
        raise ValueError(f"USD cache {path!r} does not exist")
    try:
        stage = Usd.Stage.Open(path)
    except Exception as exc:  # noqa: BLE001  (pxr raises Tf.ErrorException)
        raise ValueError(f"USD cache {path!r} does not open: {exc}") from None
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
            elif widths is not None and len(widths) == n and type_name == "Points":
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


def cache_info(path_or_stage):
    """Summary dict: ``fps``, ``start``, ``end``, ``frames`` and ``prims`` (path, type, min/max
    element count, union of extents over all frames as ``bounds`` [[lo], [hi]] in metres)."""
    from pxr import Gf, Usd, UsdGeom

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
    return {"path": stage.GetRootLayer().realPath, "fps": stage.GetTimeCodesPerSecond(),
            "start": frames[0] if frames else None, "end": frames[-1] if frames else None,
            "frames": len(frames), "prims": prims}
