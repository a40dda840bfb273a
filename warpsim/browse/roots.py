"""The root of a sweep, written over its batch layers (:mod:`warpsim.sweeps.usd`) and read back:
its worlds, the batch layers holding them and the files kept beside it (table, occupancy record).

Root (:func:`write_sweep_root`): ``/World`` (the default prim) either carries a variant set
``world`` with one variant per world (``world_GGGGGG``, referencing that world's prim; the first
is selected), or (``layout="grid"``) holds every world side by side on a grid in the x-z plane.
``pxr`` is imported lazily."""
from __future__ import annotations

import math
import os

import numpy as np

from ..core.safe_files import clear_temporary

__all__ = ["LAYOUTS", "root_worlds", "sweep_root_files", "unstored_root_files", "unstored_sweep", "world_prim_name",
           "write_sweep_root", "write_unstored_root"]

LAYOUTS = ("variants", "grid")


def world_prim_name(world: int) -> str:
    """The prim name of world ``world`` (its global index) in batch layers and roots."""
    return f"world_{int(world):06d}"


def root_worlds(path):
    """(layout, [(world index, batch layer path)]) of a sweep root ("variants" or "grid"), or None
    if ``path`` is USD but not a sweep root."""
    from pxr import Sdf

    layer = Sdf.Layer.FindOrOpen(os.fspath(path))
    spec = layer.GetPrimAtPath("/World") if layer is not None else None
    if spec is None:
        return None
    folder = os.path.dirname(os.path.abspath(os.fspath(path)))
    found = []

    def add(prim_spec, name):
        refs = prim_spec.referenceList.prependedItems
        if name.startswith("world_") and len(refs) == 1:
            found.append((int(name[6:]), os.path.normpath(os.path.join(folder, refs[0].assetPath))))

    vset = spec.variantSets.get("world")
    if vset is not None:
        for name, variant in vset.variants.items():
            add(variant.primSpec, name)
        return ("variants", sorted(found)) if found else None
    for name, child in spec.nameChildren.items():
        add(child, name)
    return ("grid", sorted(found)) if found else None


def sweep_root_files(root, table=None):
    """{"layout", "worlds" [(world, layer)], "table", "record"} of the sweep root ``root`` (the
    table and record default to ``<stem>.csv`` and ``<stem>.occupancy.npz``). FileNotFoundError /
    ValueError (one line, naming the fix) when the root is missing or not a sweep root."""
    from .occupancy import occupancy_path

    root = os.fspath(root)
    if os.path.isdir(root):
        raise ValueError(f"{root!r} is a folder; give the sweep's root file (.usda) written by 'warpsim sweep'")
    if not os.path.exists(root):
        raise FileNotFoundError(f"no sweep root {root}; give the --out of 'warpsim sweep'")
    if not os.path.isfile(root):  # USD would wait on a FIFO for ever
        raise ValueError(f"{root} is not a regular file (a pipe, socket or device); give the sweep's root file "
                         "(.usda) written by 'warpsim sweep'")
    try:
        found = root_worlds(root)
    except Exception as exc:  # noqa: BLE001  (pxr raises Tf errors for files that are not USD)
        from ..usd.pxr_errors import pxr_reason

        why = pxr_reason(exc, 100) if str(exc).strip() else "USD gave no reason"
        raise ValueError(f"{root} is not a readable USD file ({why}); give the root of 'warpsim sweep'") from None
    if found is None:
        unstored = unstored_sweep(root)
        if unstored is not None:
            raise ValueError(f"{root} is a sweep run with --store none: it holds no frames; every world re-runs "
                             f"exactly: warpsim pick {root} --world N --out FILE (or warpsim run "
                             f"{unstored.get('scene') or 'SCENE'} --from-sweep {root} --world N)")
        raise ValueError(f"{root} is not a sweep root (no 'world' variant set or world_ prims under /World); give "
                         "the --out of 'warpsim sweep'")
    stem = os.path.splitext(os.path.abspath(root))[0]
    return {"layout": found[0], "worlds": found[1], "table": os.fspath(table) if table else stem + ".csv",
            "record": occupancy_path(root)}


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


def _layers_summary(layer_paths):
    """(owner {world: its batch layer}, fps, first and last time codes (None: none), span [m]: the
    largest extent of a world, or of the union of the layers' extents when they all record one)."""
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
    return owner, fps, start, end, span


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
    owner, fps, start, end, span = _layers_summary(layer_paths)
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

    assets = {p: "./" + os.path.relpath(p, folder).replace(os.sep, "/") for p in set(owner.values())}

    def reference(spec, g, name):  # (one list op authored: a proxy's Prepend costs more with many worlds)
        ref = Sdf.Reference(assets[owner[g]], f"/Worlds/{name}")
        spec.SetInfo("references", Sdf.ReferenceListOp.Create(prependedItems=[ref]))

    if layout == "variants":
        vset = Sdf.VariantSetSpec(root, "world")
        with Sdf.ChangeBlock():
            for g in chosen:
                name = world_prim_name(g)
                reference(Sdf.VariantSpec(vset, name).primSpec, g, name)
        root.variantSetNameList.Prepend("world")
        if chosen:
            root.variantSelections["world"] = world_prim_name(chosen[0])
    else:
        step = float(spacing) if spacing is not None else 1.25 * max(span, 1e-3)
        if not (math.isfinite(step) and step > 0):
            raise ValueError(f"spacing {spacing} must be > 0 [m]")
        columns = max(1, math.ceil(math.sqrt(len(chosen))))
        for k, g in enumerate(chosen):
            name = world_prim_name(g)
            spec = Sdf.CreatePrimInLayer(layer, f"/World/{name}")
            spec.specifier = Sdf.SpecifierDef
            spec.typeName = "Xform"
            reference(spec, g, name)
            op = Sdf.AttributeSpec(spec, "xformOp:translate", Sdf.ValueTypeNames.Double3)
            op.default = Gf.Vec3d((k % columns) * step, 0.0, (k // columns) * step)
            order = Sdf.AttributeSpec(spec, "xformOpOrder", Sdf.ValueTypeNames.TokenArray, Sdf.VariabilityUniform)
            order.default = ["xformOp:translate"]
    tmp = out_path + ".tmp" + os.path.splitext(out_path)[1]
    clear_temporary(tmp)  # never through a link planted at the temporary name
    if not layer.Export(tmp):
        raise PermissionError(f"could not write {out_path}; check the folder is writable")
    os.replace(tmp, out_path)
    return out_path


def unstored_sweep(path):
    """The ``customLayerData["warpsim"]`` of a sweep root written with ``--store none``
    (:func:`write_unstored_root`: ``store``, ``worldCount``, ``scene``, ``frames``), or None for any
    other file."""
    from pxr import Sdf

    try:
        layer = Sdf.Layer.FindOrOpen(os.fspath(path))
    except Exception:  # noqa: BLE001  (not USD)
        return None
    data = dict(layer.customLayerData.get("warpsim", {})) if layer is not None else {}
    return data if data.get("store") == "none" else None


def unstored_root_files(root, table=None):
    """:func:`sweep_root_files` of a root written with ``--store none`` (``"worlds"`` empty: no
    batch layer holds them; the table and record beside it as usual), None for any other file."""
    from .occupancy import occupancy_path

    root = os.fspath(root)
    if not os.path.isfile(root) or unstored_sweep(root) is None:
        return None
    stem = os.path.splitext(os.path.abspath(root))[0]
    return {"layout": None, "worlds": [], "table": os.fspath(table) if table else stem + ".csv",
            "record": occupancy_path(root)}


def write_unstored_root(out_path, world_count, *, scene, frames, fps) -> str:
    """The root of a sweep run with ``--store none`` (no batch layer: the table, the occupancy
    record, the manifest and the thumbnails are beside it): ``/World`` an empty Xform, the stage
    settings and frame range of the sweep, and ``customLayerData["warpsim"]`` saying ``store`` =
    "none", ``worldCount``, ``scene`` and ``frames``, so ``warpsim pick`` re-runs a world instead
    of reading it. Returns its path."""
    from pxr import Sdf

    out_path = os.path.abspath(os.fspath(out_path))
    if os.path.splitext(out_path)[1] not in (".usd", ".usda", ".usdc"):
        raise ValueError(f"root {out_path!r} must end in .usd, .usda or .usdc")
    os.makedirs(os.path.dirname(out_path), exist_ok=True)
    layer = Sdf.Layer.CreateAnonymous(".usda")
    layer.defaultPrim = "World"
    layer.timeCodesPerSecond = float(fps)
    layer.framesPerSecond = float(fps)
    layer.pseudoRoot.SetInfo("upAxis", "Y")
    layer.pseudoRoot.SetInfo("metersPerUnit", 1.0)
    layer.startTimeCode, layer.endTimeCode = 0.0, float(frames)
    root = Sdf.CreatePrimInLayer(layer, "/World")
    root.specifier = Sdf.SpecifierDef
    root.typeName = "Xform"
    layer.customLayerData = {"warpsim": {"store": "none", "worldCount": int(world_count), "scene": str(scene),
                                         "frames": int(frames)}}
    tmp = out_path + ".tmp" + os.path.splitext(out_path)[1]
    clear_temporary(tmp)  # never through a link planted at the temporary name
    if not layer.Export(tmp):
        raise PermissionError(f"could not write {out_path}; check the folder is writable")
    os.replace(tmp, out_path)
    return out_path
