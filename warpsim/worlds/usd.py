"""USD output of many worlds: batch layers, and a root with a ``world`` variant set or a gallery.

Batch layer (one per batch, ``.usdc``): every world of the batch under
``/Worlds/world_GGGGGG`` (G: the world's global index), holding the scene's own prims (declared
once by ``scene.declare`` on a :class:`warpsim.usd.writer.UsdCacheWriter`, never described twice)
with a time sample per frame. ``customLayerData["warpsim"]`` records ``firstWorld``,
``worldCount``, ``scene``, ``span`` (the largest extent of a world [m], for galleries) and ``lo`` /
``hi`` (the corners of the worlds' extent [m]: a root over several layers spans their union).

Root (``write_sweep_root``): ``/World`` (the default prim) either carries a variant set ``world``
with one variant per world (``world_GGGGGG``, referencing that world's prim; the first is
selected), or (``layout="grid"``) holds every world side by side on a grid in the x-z plane.
``pxr`` is imported lazily.
"""
from __future__ import annotations

import math
import operator
import os

import numpy as np

from ..usd.writer import UsdCacheWriter

__all__ = ["BatchLayerWriter", "world_prim_name", "write_sweep_root"]

LAYOUTS = ("variants", "grid")


def world_prim_name(world: int) -> str:
    return f"world_{int(world):06d}"


class BatchLayerWriter(UsdCacheWriter):
    """Streams the frames of ``world_count`` worlds (global indices ``first_world ..``) into one
    crash-safe chunked layer (:class:`warpsim.usd.writer.UsdCacheWriter` with root prim
    ``/Worlds``): frames go to chunk files of ``chunk_size`` frames beside ``path``, each world
    prim lists them as value clips (clips do not reach through a reference to a prim below the
    one that carries them), and a process killed at any moment leaves a layer holding every
    completed chunk. ``resume_frame``: keep the completed chunks before that frame and go on."""

    def __init__(self, path, scene, first_world, world_count, fps, save_bytes=64 << 20, *, chunk_size=24,
                 resume_frame=None, durable=True):
        path = os.path.abspath(os.fspath(path))
        if os.path.splitext(path)[1] not in (".usd", ".usdc", ".usda"):
            raise ValueError(f"batch layer {path!r} must end in .usd, .usdc or .usda")
        super().__init__(path, fps=fps, chunk_size=chunk_size, resume_frame=resume_frame, root_prim="Worlds",
                         durable=durable, save_bytes=save_bytes)
        scene.declare(self)
        self.first_world, self.world_count = int(first_world), int(world_count)
        self.scene_name = ""
        self.world_params = {}
        self.dynamic = {name: d for name, d in self.prims.items() if d.is_dynamic}
        self.lo = np.full(3, np.inf)
        self.hi = np.full(3, -np.inf)
        for decl in self.prims.values():  # static geometry counts in a world's extent
            pts = getattr(decl.attrs.get("points"), "value", None)
            if pts is not None and not decl.is_dynamic:
                self._grow_bounds(pts)

    def set_world_params(self, local, params):
        """Author world ``local``'s parameters on its prim: ``customData["warpsim"]`` holds
        ``world`` (the global index) and ``params`` {name: value}, so a root or a picked file that
        references the prim carries them (not only the CSV)."""
        self.world_params[int(local)] = dict(params)

    def _world_path(self, local):
        return f"/Worlds/{world_prim_name(self.first_world + local)}"

    def observe(self, datas):
        """Widen the worlds' extent by one frame's data without writing it (frames a resumed
        run re-simulates before its first new chunk)."""
        for data in datas:
            for name in self.dynamic:
                value = (data.get(name) or {}).get("points")
                if value is None:
                    continue
                self._grow_bounds(getattr(value, "numpy", lambda: value)())

    def write_worlds(self, frame, datas):
        """One frame of every world: ``datas[local]`` is world ``local``'s frame data
        (``{prim name: {key: array}}``, as ``scene.frame_data()`` gives it)."""
        if self._closed:
            raise ValueError("the writer is closed")
        frame = operator.index(frame)
        if len(datas) != self.world_count:
            raise ValueError(f"frame {frame}: data for {len(datas)} worlds, the layer holds {self.world_count}")
        if not self._sealed:
            self._seal()
        if self.last_frame is not None and frame <= self.last_frame:
            raise ValueError(f"frames must increase: got frame {frame} after {self.last_frame}")
        samples = [{name: decl.frame_samples(data.get(name), frame) for name, decl in self.dynamic.items()}
                   for data in datas]
        if self._chunk is not None and frame // self.chunk_size != self._chunk.start // self.chunk_size:
            self._finish_chunk()
        if self._chunk is None:
            self._open_chunk(frame)
        self._write_samples(frame, samples)
        self.last_frame = frame

    def _write_samples(self, frame, samples):
        for local, world in enumerate(samples):
            self._set_prim_samples(frame, self._world_path(local), world)
            self._chunk.stats.add_frame(world)
        self._end_frame_samples(frame)

    def _authored(self, attr_name, value):
        if attr_name == "points":  # the bounds of every world's points, for the root's extent
            self._grow_bounds(value)

    def _grow_bounds(self, points):
        """Widen ``lo``/``hi`` [m] by these points (N, 3) when they are all finite."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if len(pts) and np.isfinite(pts).all():
            self.lo, self.hi = np.minimum(self.lo, pts.min(0)), np.maximum(self.hi, pts.max(0))

    def _dynamic_paths(self):
        return [f"{self._world_path(k)}/{name}.{a.name}" for k in range(self.world_count)
                for name, d in self.dynamic.items() for a in d.dynamic_attrs()]

    def _clip_prim(self, layer):
        return layer.GetPrimAtPath(self._world_path(0))

    def _declare_specs(self, layer, manifest):
        from pxr import Sdf

        root = Sdf.CreatePrimInLayer(layer, "/Worlds")
        root.specifier = Sdf.SpecifierDef
        root.typeName = "Scope"
        for k in range(self.world_count):
            spec = Sdf.CreatePrimInLayer(layer, self._world_path(k))
            spec.specifier = Sdf.SpecifierDef
            spec.typeName = "Xform"
            if not manifest and k in self.world_params:
                spec.customData = {"warpsim": {"world": self.first_world + k, "params": {
                    str(key): _custom_value(v) for key, v in self.world_params[k].items()}}}
            for name, decl in self.prims.items():
                if manifest and not decl.is_dynamic:
                    continue
                self._declare_prim(layer, spec.path.AppendChild(name), decl, manifest)
        return root

    def _build_layer(self, manifest):
        from pxr import Vt

        layer = super()._build_layer(manifest)
        if manifest:
            return layer
        root = layer.GetPrimAtPath("/Worlds")
        if root.HasInfo("clips"):  # on every world prim instead, each with its own primPath
            clips = dict(dict(root.GetInfo("clips"))["default"])
            root.ClearInfo("clips")
            for k in range(self.world_count):
                path = self._world_path(k)
                layer.GetPrimAtPath(path).SetInfo("clips", {"default": {**clips, "primPath": path}})
        finite = np.isfinite(self.hi - self.lo).all()
        span = float(np.max(self.hi - self.lo)) if finite else 1.0
        data = dict(layer.customLayerData.get("warpsim", {}))
        data.update(firstWorld=self.first_world, worldCount=self.world_count, scene=self.scene_name, span=span,
                    center=Vt.DoubleArray(list(0.5 * (self.lo + self.hi)) if finite else [0.0, 0.0, 0.0]))
        if finite:
            data.update(lo=Vt.DoubleArray(list(self.lo)), hi=Vt.DoubleArray(list(self.hi)))
        layer.customLayerData = {"warpsim": data}
        return layer

    def close(self, scene_name=""):
        """Complete the last chunk and rewrite the layer; returns its path."""
        self.scene_name = scene_name or self.scene_name
        if self._closed:
            return self.path
        if not self._sealed:
            self._seal()
        self.flush()
        self._write_root()  # the final extent (span) even when the last chunk came before it
        self._closed = True
        self._release_lock()  # the layer's lock file (warpsim.usd.lock) goes with the writer
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

    from ..core import checks

    if layout not in LAYOUTS:
        raise ValueError(f"layout {layout!r} is unknown; use one of {', '.join(LAYOUTS)}")
    world_count = checks.integer(world_count, "write_sweep_root world_count", lo=1, fix="worlds in the sweep")
    out_path = os.path.abspath(os.fspath(out_path))
    if os.path.splitext(out_path)[1] not in (".usd", ".usda", ".usdc"):
        raise ValueError(f"root {out_path!r} must end in .usd, .usda or .usdc")
    layer_paths = [os.path.abspath(os.fspath(p)) for p in layer_paths]
    if out_path in layer_paths:
        raise ValueError(f"root {out_path!r} is also one of the batch layers it would reference; writing it would "
                         "overwrite that layer's worlds: give the root another name")
    owner, fps, start, end, span = {}, None, None, None, 0.0
    corners = []  # the layers' extents: the union's span, as one layer of every world would have
    for p in layer_paths:
        layer, info = _layer_info(p)
        for g in range(int(info["firstWorld"]), int(info["firstWorld"]) + int(info["worldCount"])):
            owner[g] = os.path.abspath(os.fspath(p))
        fps = fps or layer.timeCodesPerSecond
        if layer.HasStartTimeCode():
            start = layer.startTimeCode if start is None else min(start, layer.startTimeCode)
            end = layer.endTimeCode if end is None else max(end, layer.endTimeCode)
        span = max(span, float(info.get("span", 1.0)))
        corners.append(np.array([list(info["lo"]), list(info["hi"])]) if "lo" in info and "hi" in info else None)
    known = [c for c in corners if c is not None]
    if known and len(known) == len(corners):
        span = float(np.max(np.max([c[1] for c in known], axis=0) - np.min([c[0] for c in known], axis=0)))
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
