"""USD output of many worlds: batch layers, and a root with a ``world`` variant set or a gallery.

Batch layer (one per batch, ``.usdc``): every world of the batch under
``/Worlds/world_GGGGGG`` (G: the world's global index), holding the scene's own prims (declared
once by ``scene.declare`` on a :class:`warpsim.usd.writer.UsdCacheWriter`, never described twice)
with a time sample per frame. ``customLayerData["warpsim"]`` records ``firstWorld``,
``worldCount``, ``scene`` and ``span`` (the largest extent of a world [m], for galleries).

Root (``write_sweep_root``): ``/World`` (the default prim) either carries a variant set ``world``
with one variant per world (``world_GGGGGG``, referencing that world's prim; the first is
selected), or (``layout="grid"``) holds every world side by side on a grid in the x-z plane.
``pxr`` is imported lazily.
"""
from __future__ import annotations

import math
import os

import numpy as np

__all__ = ["BatchLayerWriter", "world_prim_name", "write_sweep_root"]

LAYOUTS = ("variants", "grid")


def world_prim_name(world: int) -> str:
    return f"world_{int(world):06d}"


class BatchLayerWriter:
    """Streams the frames of ``world_count`` worlds (global indices ``first_world ..``) into one layer."""

    def __init__(self, path, scene, first_world, world_count, fps, save_bytes=64 << 20):
        from pxr import Sdf

        from ..usd.writer import UsdCacheWriter

        path = os.path.abspath(os.fspath(path))
        if os.path.splitext(path)[1] not in (".usd", ".usdc", ".usda"):
            raise ValueError(f"batch layer {path!r} must end in .usd, .usdc or .usda")
        os.makedirs(os.path.dirname(path), exist_ok=True)
        self.decls = UsdCacheWriter(path, fps=fps)  # collects the scene's declarations; writes nothing
        scene.declare(self.decls)
        self.path, self.first_world, self.world_count, self.fps = path, int(first_world), int(world_count), fps
        self.layer = Sdf.Layer.Find(path)  # open in this process already (a rerun): start it afresh
        if self.layer is not None:
            self.layer.Clear()
        else:
            if os.path.exists(path):
                os.remove(path)
            self.layer = Sdf.Layer.CreateNew(path)
        if self.layer is None:
            raise PermissionError(f"could not create the batch layer {path}; check the folder is writable")
        root = Sdf.CreatePrimInLayer(self.layer, "/Worlds")
        root.specifier = Sdf.SpecifierDef
        root.typeName = "Scope"
        self.dynamic = {name: d for name, d in self.decls.prims.items() if d.is_dynamic}
        for k in range(self.world_count):
            spec = Sdf.CreatePrimInLayer(self.layer, f"/Worlds/{world_prim_name(self.first_world + k)}")
            spec.specifier = Sdf.SpecifierDef
            spec.typeName = "Xform"
            for name, decl in self.decls.prims.items():
                self.decls._declare_prim(self.layer, spec.path.AppendChild(name), decl, False)
        self.lo = np.full(3, np.inf)
        self.hi = np.full(3, -np.inf)
        for decl in self.decls.prims.values():  # static geometry counts in a world's extent
            pts = getattr(decl.attrs.get("points"), "value", None)
            if pts is not None and not decl.is_dynamic:
                pts = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
                self.lo, self.hi = np.minimum(self.lo, pts.min(0)), np.maximum(self.hi, pts.max(0))
        self.first_frame = self.last_frame = None
        self._pending = 0
        self._save_bytes = save_bytes
        self._last = {}

    def set_world_params(self, local, params):
        """Author world ``local``'s parameters on its prim: ``customData["warpsim"]`` holds
        ``world`` (the global index) and ``params`` {name: value}, so a root or a picked file that
        references the prim carries them (not only the CSV)."""
        spec = self.layer.GetPrimAtPath(f"/Worlds/{world_prim_name(self.first_world + local)}")
        spec.customData = {"warpsim": {"world": self.first_world + int(local),
                                       "params": {str(k): _custom_value(v) for k, v in params.items()}}}

    def write_world(self, local, frame, data):
        """Samples of one world (``local`` in 0..world_count-1) at ``frame`` from the scene's frame data."""
        from ..usd.writer import to_vt

        base = f"/Worlds/{world_prim_name(self.first_world + local)}"
        for name, decl in self.dynamic.items():
            for attr_name, value in decl.frame_samples(data.get(name), frame).items():
                attr = decl.attrs[attr_name]
                path = f"{base}/{name}.{attr_name}"
                if attr.on_change:
                    prev = self._last.get(path)
                    if prev is not None and np.array_equal(prev, value):
                        continue
                    self._last[path] = np.array(value, copy=True)
                if attr_name == "points":
                    pts = np.asarray(value, dtype=np.float64).reshape(-1, 3)
                    if len(pts) and np.isfinite(pts).all():
                        self.lo, self.hi = np.minimum(self.lo, pts.min(0)), np.maximum(self.hi, pts.max(0))
                self.layer.SetTimeSample(path, float(frame), to_vt(attr.type_name, value))
                self._pending += getattr(value, "nbytes", 8)
        self.first_frame = frame if self.first_frame is None else min(self.first_frame, frame)
        self.last_frame = frame if self.last_frame is None else max(self.last_frame, frame)
        if self._pending >= self._save_bytes:
            self.layer.Save()
            self._pending = 0

    def close(self, scene_name=""):
        from pxr import Vt

        layer = self.layer
        layer.defaultPrim = "Worlds"
        layer.timeCodesPerSecond = self.fps
        layer.framesPerSecond = self.fps
        layer.pseudoRoot.SetInfo("upAxis", "Y")
        layer.pseudoRoot.SetInfo("metersPerUnit", 1.0)
        if self.first_frame is not None:
            layer.startTimeCode, layer.endTimeCode = float(self.first_frame), float(self.last_frame)
        span = float(np.max(self.hi - self.lo)) if np.isfinite(self.hi - self.lo).all() else 1.0
        layer.customLayerData = {"warpsim": {"firstWorld": self.first_world, "worldCount": self.world_count,
                                             "scene": scene_name, "span": span,
                                             "center": Vt.DoubleArray(list(0.5 * (self.lo + self.hi)) if
                                                                      math.isfinite(span) else [0.0, 0.0, 0.0])}}
        if not layer.Save():
            raise OSError(f"could not save {self.path}")
        return self.path


def _custom_value(value):
    """A parameter value as USD customData holds it (vectors as double arrays)."""
    from pxr import Vt

    if isinstance(value, (bool, int, float, str)):
        return value
    if isinstance(value, (tuple, list, np.ndarray)):
        return Vt.DoubleArray([float(v) for v in value])
    return str(value)


def _layer_info(path):
    from pxr import Sdf

    layer = Sdf.Layer.Find(os.path.abspath(os.fspath(path)))
    if layer is not None:
        layer.Reload()  # another process may have rewritten it
    else:
        layer = Sdf.Layer.FindOrOpen(os.fspath(path))
    if layer is None:
        raise FileNotFoundError(f"batch layer {path} does not exist or is not USD; run the batch first")
    info = dict(layer.customLayerData.get("warpsim", {}))
    if "firstWorld" not in info:
        raise ValueError(f"{path} is not a warpsim batch layer (no customLayerData warpsim.firstWorld)")
    return layer, info


def write_sweep_root(out_path, layer_paths, world_count, layout="variants", *, worlds=None, spacing=None) -> str:
    """Write the root USD of a sweep and return its path.

    ``layer_paths``: batch layers covering worlds ``0 .. world_count - 1``; ``layout``: "variants"
    (``/World`` with a variant set ``world``, one variant per world, the first selected) or
    "grid" (a gallery: the worlds side by side, ``spacing`` [m] apart, default 1.25 x the largest
    world extent). ``worlds``: only these global indices (a picked subset), in this order."""
    from pxr import Gf, Sdf

    if layout not in LAYOUTS:
        raise ValueError(f"layout {layout!r} is unknown; use one of {', '.join(LAYOUTS)}")
    out_path = os.path.abspath(os.fspath(out_path))
    if os.path.splitext(out_path)[1] not in (".usd", ".usda", ".usdc"):
        raise ValueError(f"root {out_path!r} must end in .usd, .usda or .usdc")
    layer_paths = [os.path.abspath(os.fspath(p)) for p in layer_paths]
    if out_path in layer_paths:
        raise ValueError(f"root {out_path!r} is also one of the batch layers it would reference; writing it would "
                         "overwrite that layer's worlds: give the root another name")
    owner, fps, start, end, span = {}, None, None, None, 0.0
    for p in layer_paths:
        layer, info = _layer_info(p)
        for g in range(int(info["firstWorld"]), int(info["firstWorld"]) + int(info["worldCount"])):
            owner[g] = os.path.abspath(os.fspath(p))
        fps = fps or layer.timeCodesPerSecond
        if layer.HasStartTimeCode():
            start = layer.startTimeCode if start is None else min(start, layer.startTimeCode)
            end = layer.endTimeCode if end is None else max(end, layer.endTimeCode)
        span = max(span, float(info.get("span", 1.0)))
    missing = [g for g in range(int(world_count)) if g not in owner]
    if missing and worlds is None:  # a chosen subset (``worlds``) may skip batches without a layer
        raise ValueError(f"world {missing[0]} is in none of the {len(layer_paths)} batch layers; run its batch")
    chosen = list(range(int(world_count))) if worlds is None else [int(w) for w in worlds]
    for g in chosen:
        if g not in owner:
            raise ValueError(f"world {g} is out of range [0, {world_count})")
    folder = os.path.dirname(out_path)
    os.makedirs(folder, exist_ok=True)
    layer = Sdf.Layer.CreateAnonymous(".usda")
    layer.defaultPrim = "World"
    layer.timeCodesPerSecond = fps or 60.0
    layer.framesPerSecond = fps or 60.0
    layer.pseudoRoot.SetInfo("upAxis", "Y")
    layer.pseudoRoot.SetInfo("metersPerUnit", 1.0)
    if start is not None:
        layer.startTimeCode, layer.endTimeCode = start, end
    root = Sdf.CreatePrimInLayer(layer, "/World")
    root.specifier = Sdf.SpecifierDef
    root.typeName = "Xform"

    def reference(spec, g):
        asset = "./" + os.path.relpath(owner[g], folder).replace(os.sep, "/")
        spec.referenceList.Prepend(Sdf.Reference(asset, f"/Worlds/{world_prim_name(g)}"))

    if layout == "variants":
        vset = Sdf.VariantSetSpec(root, "world")
        for g in chosen:
            reference(Sdf.VariantSpec(vset, world_prim_name(g)).primSpec, g)
        root.variantSetNameList.Prepend("world")
        if chosen:
            root.variantSelections["world"] = world_prim_name(chosen[0])
    else:
        step = float(spacing) if spacing is not None else 1.25 * max(span, 1e-3)
        if not (math.isfinite(step) and step > 0):
            raise ValueError(f"spacing {spacing} must be > 0 [m]")
        columns = max(1, math.ceil(math.sqrt(len(chosen))))
        for k, g in enumerate(chosen):
            spec = Sdf.CreatePrimInLayer(layer, f"/World/{world_prim_name(g)}")
            spec.specifier = Sdf.SpecifierDef
            spec.typeName = "Xform"
            reference(spec, g)
            op = Sdf.AttributeSpec(spec, "xformOp:translate", Sdf.ValueTypeNames.Double3)
            op.default = Gf.Vec3d((k % columns) * step, 0.0, (k // columns) * step)
            order = Sdf.AttributeSpec(spec, "xformOpOrder", Sdf.ValueTypeNames.TokenArray, Sdf.VariabilityUniform)
            order.default = ["xformOp:translate"]
    tmp = out_path + ".tmp" + os.path.splitext(out_path)[1]
    if not layer.Export(tmp):
        raise PermissionError(f"could not write {out_path}; check the folder is writable")
    os.replace(tmp, out_path)
    return out_path
