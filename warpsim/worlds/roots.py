"""Reading a sweep root back: its worlds, the batch layers holding them and the files kept beside
it (table, occupancy record). ``pxr`` is imported lazily."""
from __future__ import annotations

import os

__all__ = ["root_worlds", "sweep_root_files"]


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
        raise ValueError(f"{root} is not a sweep root (no 'world' variant set or world_ prims under /World); give "
                         "the --out of 'warpsim sweep'")
    stem = os.path.splitext(os.path.abspath(root))[0]
    return {"layout": found[0], "worlds": found[1], "table": os.fspath(table) if table else stem + ".csv",
            "record": occupancy_path(root)}
