"""USD value types: the NumPy form of each type a declaration may use, and the USD value made
from it (Vt arrays from NumPy buffers). NumPy only at import (``pxr`` when a value is made), so
the chunk-authoring worker (:mod:`warpsim.usd.chunk_author`) imports it without Warp.
"""
from __future__ import annotations

import numpy as np

__all__ = ["ARRAY_TYPES", "SCALAR_TYPES", "pxr_modules", "to_vt", "vt_maker"]

# USD array type name -> (NumPy dtype, components per element; 0 = scalar elements)
ARRAY_TYPES = {
    "point3f[]": (np.float32, 3),
    "vector3f[]": (np.float32, 3),
    "normal3f[]": (np.float32, 3),
    "color3f[]": (np.float32, 3),
    "float3[]": (np.float32, 3),
    "float2[]": (np.float32, 2),
    "double3[]": (np.float64, 3),
    "float[]": (np.float32, 0),
    "double[]": (np.float64, 0),
    "int[]": (np.int32, 0),
    "int64[]": (np.int64, 0),
    "uint[]": (np.uint32, 0),
    "bool[]": (np.bool_, 0),
    "quath[]": (np.float16, 4),
    "quatf[]": (np.float32, 4),
}
# USD scalar type name -> (NumPy dtype, components)
SCALAR_TYPES = {
    "float": (np.float32, 0),
    "double": (np.float64, 0),
    "int": (np.int32, 0),
    "int64": (np.int64, 0),
    "bool": (np.bool_, 0),
    "float3": (np.float32, 3),
    "double3": (np.float64, 3),
    "color3f": (np.float32, 3),
    "token": (None, 0),
    "string": (None, 0),
}


def pxr_modules():
    try:
        from pxr import Gf, Sdf, Vt
    except ImportError as exc:  # pragma: no cover - usd-core is a dependency
        raise ImportError("warpsim.usd needs usd-core: pip install usd-core") from exc
    return Sdf, Vt, Gf


_VT_ARRAY = {}


def vt_maker(type_name):
    """A function turning a value already coerced to ``type_name`` into its USD value: for array
    types the Vt array class's ``FromNumpy`` (looked up once), else :func:`to_vt`."""
    if type_name in ARRAY_TYPES:
        make = _VT_ARRAY.get(type_name)
        if make is None:
            Sdf, _, _ = pxr_modules()
            make = _VT_ARRAY[type_name] = Sdf.ValueTypeNames.Find(type_name).type.pythonClass.FromNumpy
        return make
    return lambda value: to_vt(type_name, value)


def to_vt(type_name, value):
    """USD value for NumPy/python ``value`` already coerced to ``type_name`` (see usd_prims.coerce)."""
    Sdf, Vt, Gf = pxr_modules()
    if type_name == "token[]":
        return Vt.TokenArray(value)
    if type_name in ARRAY_TYPES:
        return vt_maker(type_name)(value)
    wrap = {"float": Vt.Float, "double": Vt.Double, "int": Vt.Int, "int64": Vt.Int64, "bool": Vt.Bool,
            "token": Vt.Token, "float3": Gf.Vec3f, "color3f": Gf.Vec3f, "double3": Gf.Vec3d}
    if type_name in ("float3", "color3f", "double3"):
        return wrap[type_name](*value)
    if type_name == "string":
        return str(value)
    return wrap[type_name](value)
