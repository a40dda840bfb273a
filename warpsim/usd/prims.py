"""Prim declarations for the USD cache writer (pure NumPy; no ``pxr`` import).

Each declaration knows the USD prim type it becomes, its static attributes (written once in the
root layer), its time-varying attributes (written into the chunk files and declared in the clip
manifest) and how to turn one frame of user arrays into validated attribute samples (computing
``extent`` on the way). :class:`warpsim.usd.writer.UsdCacheWriter` owns the file layout.
"""
from __future__ import annotations

import numpy as np

from ..core.names import close_matches
from .value_types import ARRAY_TYPES, SCALAR_TYPES

INTERPOLATIONS = ("constant", "uniform", "varying", "vertex", "faceVarying")


def as_numpy(value):
    """NumPy view of a NumPy array, a ``wp.array`` (copied to the host) or a sequence."""
    if isinstance(value, np.ndarray):
        return value
    if hasattr(value, "numpy") and callable(value.numpy):
        return value.numpy()
    return np.asarray(value)


def coerce(type_name, value, what):
    """Convert ``value`` to the NumPy layout of USD type ``type_name``; ValueError naming ``what``."""
    if type_name == "token[]":
        return [str(v) for v in value]
    if type_name in ARRAY_TYPES:
        dtype, comps = ARRAY_TYPES[type_name]
        a = as_numpy(value)
        try:
            a = np.ascontiguousarray(a, dtype=dtype)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{what}: cannot convert to {type_name} ({exc})") from None
        if comps == 0:
            if a.ndim != 1:
                raise ValueError(f"{what}: expected a 1-D array for {type_name}, got shape {a.shape}")
        elif a.ndim != 2 or a.shape[1] != comps:
            if a.size == 0:
                a = a.reshape(0, comps)
            else:
                raise ValueError(f"{what}: expected shape (n, {comps}) for {type_name}, got {a.shape}")
        return a
    if type_name in SCALAR_TYPES:
        dtype, comps = SCALAR_TYPES[type_name]
        if dtype is None:
            return str(value)
        a = np.asarray(as_numpy(value), dtype=dtype)
        if comps == 0:
            if a.size != 1:
                raise ValueError(f"{what}: expected one {type_name} value, got shape {a.shape}")
            return a.reshape(()).item()
        if a.shape != (comps,):
            raise ValueError(f"{what}: expected {comps} components for {type_name}, got shape {a.shape}")
        return tuple(a.tolist())
    raise ValueError(f"{what}: unsupported USD type {type_name!r}; use one of "
                     f"{sorted(ARRAY_TYPES) + sorted(SCALAR_TYPES)}")


def _extent(points, pad):
    """Axis-aligned bounds (2, 3) float32 of ``points`` grown by ``pad`` (scalar or per point)."""
    if len(points) == 0:
        return np.zeros((2, 3), np.float32)
    pad = np.asarray(pad, np.float32)
    out = np.empty((2, 3), np.float32)
    for k in range(3):  # per column: a strided 1-D reduction is ~10x faster than min(axis=0) on (n, 3)
        col = points[:, k]
        if pad.ndim == 1:
            out[0, k] = (col - pad).min()
            out[1, k] = (col + pad).max()
        else:
            out[0, k] = col.min() - pad
            out[1, k] = col.max() + pad
    return out


class Attr:
    """One attribute of a declared prim: static (``value`` set) or sampled per frame."""

    def __init__(self, name, type_name, value=None, dynamic=False, on_change=False, custom=False,
                 metadata=None, uniform=False, derived=False, connection=None):
        self.name = name
        self.connection = connection  # relative path of the attribute this one reads (shader outputs)
        self.type_name = type_name
        self.value = value
        self.dynamic = dynamic
        self.on_change = on_change  # sampled only when the value changes (and at each chunk start)
        self.custom = custom
        self.uniform = uniform
        self.metadata = dict(metadata or {})
        self.derived = derived  # sampled per frame but computed by the prim's prepare (e.g. extent)


class PrimDecl:
    """A prim under the cache's root prim: USD type, attributes and per-frame sample preparation."""

    type_name = "Xform"
    api_schemas: list = []  # applied API schemas (e.g. MaterialBindingAPI), authored as prim metadata

    def __init__(self, name, **_):
        self.name = name
        self.attrs = {}  # attribute name -> Attr, in authoring order
        self.children = []  # (relative path, PrimDecl) static child prims (e.g. instancer prototypes)
        self.relationships = {}  # relationship name -> list of relative target paths
        self.from_state = False  # filled from a warpsim State by UsdCacheWriter.write
        self.aliases = {}  # frame-data key -> attribute name (e.g. "state" -> "primvars:state")
        self.count = None  # element count of the main per-frame array once known (fixed counts)

    # -- declaration helpers -------------------------------------------------------------
    def static(self, name, type_name, value, **kw):
        value = None if value is None else coerce(type_name, value, f"{self.name}.{name}")
        self.attrs[name] = Attr(name, type_name, value=value, **kw)  # None: declared without a value

    def dynamic(self, name, type_name, **kw):
        self.attrs[name] = Attr(name, type_name, dynamic=True, **kw)

    def add_primvar(self, name, type_name, interpolation="vertex", value=None):
        if interpolation not in INTERPOLATIONS:
            raise ValueError(f"primvar {name!r} of {self.name!r}: interpolation {interpolation!r} is not one of "
                             f"{INTERPOLATIONS}.{close_matches(interpolation, INTERPOLATIONS)}")
        full = name if name.startswith("primvars:") else f"primvars:{name}"
        meta = {"interpolation": interpolation}
        if value is None:
            self.dynamic(full, type_name, metadata=meta)
        else:
            self.static(full, type_name, value, metadata=meta)
        self.aliases[full.split(":", 1)[1]] = full

    def add_attribute(self, name, type_name, value=None, unit=None):
        if unit is not None and not (isinstance(unit, str) and unit.strip()):
            raise ValueError(f"attribute {name!r} of {self.name!r}: unit {unit!r} is not a unit name; give e.g. "
                             "unit='rad' or leave it out")
        meta = {"customData": {"unit": unit}} if unit is not None else None
        if value is None:
            self.dynamic(name, type_name, custom=True, metadata=meta)
        else:
            self.static(name, type_name, value, custom=True, metadata=meta)

    @property
    def is_dynamic(self):
        return any(a.dynamic for a in self.attrs.values())

    def dynamic_attrs(self):
        return [a for a in self.attrs.values() if a.dynamic]

    # -- per frame ------------------------------------------------------------------------
    def frame_samples(self, data, frame):
        """Validated samples {attribute name: value} for one frame of ``data`` (a mapping)."""
        where = f"prim {self.name!r} at frame {frame}"
        if data is None:
            raise ValueError(f"{where}: no data given; every time-varying prim needs data every frame")
        out = {}
        for key, value in data.items():
            name = self.aliases.get(key, key)
            attr = self.attrs.get(name)
            if attr is None or not (attr.dynamic or name in self.inputs()):
                valid = sorted(set(self.inputs()) | {a.name for a in self.dynamic_attrs()} | set(self.aliases))
                raise ValueError(f"{where}: unknown key {key!r}; valid keys are {valid}."
                                 f"{close_matches(key, valid)}")
            out[name] = value
        return self.prepare(out, where)

    def inputs(self):
        """Extra per-frame keys that are not attributes themselves (e.g. curve particle positions)."""
        return ()

    def prepare(self, data, where):
        out = {}
        for attr in self.dynamic_attrs():
            if attr.derived:
                continue
            if attr.name not in data:
                raise ValueError(f"{where}: missing {attr.name!r} (declared time-varying, so it is needed "
                                 "every frame)")
            out[attr.name] = coerce(attr.type_name, data[attr.name], f"{where}, {attr.name!r}")
        return out

    def _check_count(self, n, where, what, fixed):
        if fixed:
            if self.count is None:
                self.count = n
            elif n != self.count:
                raise ValueError(f"{where}: {what} has {n} elements but the prim was declared with a fixed "
                                 f"count of {self.count}; declare it with count_changes=True")


def _check_finite(extent, where, what):
    if not np.isfinite(extent).all():
        raise ValueError(f"{where}: {what} contain NaN or infinite values")


class PointsDecl(PrimDecl):
    """``UsdGeom.Points``: points, velocities, widths (= 2 * radius), ids when counts change."""

    type_name = "Points"

    def __init__(self, name, *, count_changes=False, radius=0.01, dynamic_widths=False, color=None,
                 velocities=True, from_state=False):
        super().__init__(name)
        self.count_changes = bool(count_changes)
        self.dynamic_widths = bool(dynamic_widths)
        self.has_velocities = bool(velocities)
        self.from_state = bool(from_state)
        self.dynamic("points", "point3f[]")
        if self.has_velocities:
            self.dynamic("velocities", "vector3f[]")
        if self.count_changes:
            self.dynamic("ids", "int64[]")
        self.pad = 0.0
        if self.dynamic_widths:
            self.dynamic("widths", "float[]", metadata={"interpolation": "vertex"})
        else:
            r = np.asarray(as_numpy(radius), np.float64)
            if not np.isfinite(r).all() or (r < 0).any():
                raise ValueError(f"points {name!r}: radius must be finite and >= 0, got {radius!r}")
            if r.ndim == 0:
                self.static("widths", "float[]", [2.0 * float(r)], metadata={"interpolation": "constant"})
                self.pad = float(r)
            else:
                if self.count_changes:
                    raise ValueError(f"points {name!r}: a per-point radius array needs a fixed count; with "
                                     "count_changes=True pass dynamic_widths=True and 'widths' every frame")
                self.static("widths", "float[]", 2.0 * r, metadata={"interpolation": "vertex"})
                self.pad = r.astype(np.float32)
                self.count = len(r)
        if color is not None:
            self.add_primvar("displayColor", "color3f[]", "constant", [color])
        self.dynamic("extent", "float3[]", derived=True)

    def prepare(self, data, where):
        out = super().prepare(data, where)
        p = out["points"]
        n = len(p)
        self._check_count(n, where, "points", not self.count_changes)
        for key in ("velocities", "ids", "widths"):
            if key in out and len(out[key]) != n:
                raise ValueError(f"{where}: {key!r} has {len(out[key])} elements but points has {n}; they must "
                                 "have the same length")
        pad = out["widths"] * 0.5 if self.dynamic_widths else self.pad
        out["extent"] = _extent(p, pad)
        _check_finite(out["extent"], where, "points")
        return out


class MeshDecl(PrimDecl):
    """``UsdGeom.Mesh``: fixed topology written once, or counts/indices sampled when they change."""

    type_name = "Mesh"

    def __init__(self, name, face_vertex_counts=None, face_vertex_indices=None, *, topology_changes=False,
                 velocities=True, color=None, double_sided=False, points=None):
        super().__init__(name)
        self.topology_changes = bool(topology_changes)
        self.has_velocities = bool(velocities)
        self.static("subdivisionScheme", "token", "none", uniform=True)
        if double_sided:
            self.static("doubleSided", "bool", True, uniform=True)
        if self.topology_changes:
            self.dynamic("faceVertexCounts", "int[]", on_change=True)
            self.dynamic("faceVertexIndices", "int[]", on_change=True)
        else:
            if face_vertex_counts is None or face_vertex_indices is None:
                raise ValueError(f"mesh {name!r}: give face_vertex_counts and face_vertex_indices, or "
                                 "topology_changes=True to pass them every frame")
            counts = coerce("int[]", np.asarray(as_numpy(face_vertex_counts)).reshape(-1), f"mesh {name!r} counts")
            indices = coerce("int[]", np.asarray(as_numpy(face_vertex_indices)).reshape(-1),
                             f"mesh {name!r} indices")
            check_topology(counts, indices, None, f"mesh {name!r}")
            self.static("faceVertexCounts", "int[]", counts)
            self.static("faceVertexIndices", "int[]", indices)
            self.index_max = int(indices.max()) if len(indices) else -1
        if points is not None:  # static mesh
            p = coerce("point3f[]", points, f"mesh {name!r} points")
            if not self.topology_changes and self.index_max >= len(p):
                raise ValueError(f"mesh {name!r}: face_vertex_indices reach {self.index_max} but there are "
                                 f"only {len(p)} points")
            self.static("points", "point3f[]", p)
            ext = _extent(p, 0.0)
            _check_finite(ext, f"mesh {name!r}", "points")
            self.static("extent", "float3[]", ext)
        else:
            self.dynamic("points", "point3f[]")
            if self.has_velocities:
                self.dynamic("velocities", "vector3f[]")
            self.dynamic("extent", "float3[]", derived=True)
        if color is not None:
            self.add_primvar("displayColor", "color3f[]", "constant", [color])

    def prepare(self, data, where):
        out = super().prepare(data, where)
        p = out["points"]
        n = len(p)
        if "velocities" in out and len(out["velocities"]) != n:
            raise ValueError(f"{where}: 'velocities' has {len(out['velocities'])} elements but points has {n}")
        if self.topology_changes:
            check_topology(out["faceVertexCounts"], out["faceVertexIndices"], n, where)
        else:
            self._check_count(n, where, "points", True)
            if self.index_max >= n:
                raise ValueError(f"{where}: face_vertex_indices reach {self.index_max} but points has {n}")
        out["extent"] = _extent(p, 0.0)
        _check_finite(out["extent"], where, "points")
        return out


def check_topology(counts, indices, point_count, where):
    """ValueError unless counts >= 3, sum(counts) == len(indices) and 0 <= indices < point_count."""
    if len(counts) and counts.min() < 3:
        raise ValueError(f"{where}: face {int(np.argmin(counts))} has {int(counts.min())} vertices; faces need >= 3")
    if int(counts.sum()) != len(indices):
        raise ValueError(f"{where}: face_vertex_counts sum to {int(counts.sum())} but there are {len(indices)} "
                         "face_vertex_indices")
    if len(indices) and (indices.min() < 0 or (point_count is not None and indices.max() >= point_count)):
        raise ValueError(f"{where}: face_vertex_indices span [{int(indices.min())}, {int(indices.max())}], "
                         f"outside [0, {point_count})")


class CurvesDecl(PrimDecl):
    """Linear ``UsdGeom.BasisCurves``; with ``indices`` (pairs of particle indices, e.g. springs) each
    frame's ``points`` are particle positions and the writer gathers the segment end points.
    ``width`` [m]: one diameter for every curve, or one per curve vertex (vertex interpolation)."""

    type_name = "BasisCurves"

    def __init__(self, name, indices=None, *, curve_vertex_counts=None, width=0.005, color=None,
                 velocities=False):
        super().__init__(name)
        self.static("type", "token", "linear", uniform=True)
        self.has_velocities = bool(velocities)
        if indices is not None:
            idx = np.asarray(as_numpy(indices)).reshape(-1)
            if len(idx) % 2:
                raise ValueError(f"curves {name!r}: indices must hold pairs (2 * segment count), got {len(idx)}")
            if len(idx) and idx.min() < 0:
                raise ValueError(f"curves {name!r}: negative particle index {int(idx.min())}")
            self.gather = idx.astype(np.int64)
            counts = np.full(len(idx) // 2, 2, np.int32)
        else:
            if curve_vertex_counts is None:
                raise ValueError(f"curves {name!r}: give indices (pairs of particles) or curve_vertex_counts")
            self.gather = None
            counts = np.asarray(as_numpy(curve_vertex_counts)).reshape(-1)
            if len(counts) and counts.min() < 2:
                raise ValueError(f"curves {name!r}: every curve needs >= 2 vertices")
        self.static("curveVertexCounts", "int[]", counts)
        self.vertex_count = int(counts.sum())
        w = np.asarray(as_numpy(width), np.float64)
        if not np.isfinite(w).all() or (w < 0).any():
            raise ValueError(f"curves {name!r}: width must be finite and >= 0, got {width!r}")
        if w.ndim == 0:
            self.static("widths", "float[]", [float(w)], metadata={"interpolation": "constant"})
        else:  # one width per curve vertex (e.g. hair tapering to the tip)
            if w.shape != (self.vertex_count,):
                raise ValueError(f"curves {name!r}: width has shape {w.shape}; give one number or one per curve "
                                 f"vertex ({self.vertex_count},)")
            self.static("widths", "float[]", w.astype(np.float32), metadata={"interpolation": "vertex"})
        self.pad = 0.5 * float(w) if w.ndim == 0 else (0.5 * w).astype(np.float32)
        self.dynamic("points", "point3f[]")
        if self.has_velocities:
            self.dynamic("velocities", "vector3f[]")
        self.dynamic("extent", "float3[]", derived=True)
        if color is not None:
            self.add_primvar("displayColor", "color3f[]", "constant", [color])

    def prepare(self, data, where):
        data = dict(data)
        if self.gather is not None:
            for key in ("points", "velocities"):
                if key in data:
                    a = coerce("point3f[]", data[key], f"{where}, {key!r}")
                    if len(self.gather) and self.gather.max() >= len(a):
                        raise ValueError(f"{where}: curve indices reach {int(self.gather.max())} but {key!r} "
                                         f"has {len(a)} particles")
                    data[key] = a[self.gather]
        out = super().prepare(data, where)
        for key in ("points", "velocities"):
            if key in out and len(out[key]) != self.vertex_count:
                raise ValueError(f"{where}: {key!r} has {len(out[key])} vertices but the curves need "
                                 f"{self.vertex_count}")
        out["extent"] = _extent(out["points"], self.pad)
        _check_finite(out["extent"], where, "points")
        return out


SEGMENTS_ATTR = "warpsim:segments"
"""Custom ``int[]`` attribute of a :class:`JoinedPointsDecl` prim: the point index pairs its curves join."""


class JoinedPointsDecl(PointsDecl):
    """``UsdGeom.Points`` standing for linear curves between particles: the compact form of a
    :class:`CurvesDecl` declared with ``indices`` (e.g. springs) that a sweep writes. ``points``
    are the particles' positions (n, 3) [m] every frame (as given to the curves), and
    ``warpsim:segments`` (int[], written once) the pairs of points each curve joins: a reader
    draws the curves from the points (:func:`segment_pairs`) instead of the file holding both
    ends of every curve every frame (two points per curve instead of one per particle). Widths
    (the curves' diameter) and colour carry over."""

    def __init__(self, curves):
        width = np.asarray(curves.attrs["widths"].value, np.float64).reshape(-1)
        color = curves.attrs.get("primvars:displayColor")
        super().__init__(curves.name, radius=0.5 * float(width[0]), velocities=curves.has_velocities,
                         color=None if color is None else tuple(np.asarray(color.value).reshape(-1, 3)[0]))
        self.static(SEGMENTS_ATTR, "int[]", curves.gather.astype(np.int32), custom=True, uniform=True)
        self.index_max = int(curves.gather.max()) if len(curves.gather) else -1

    def prepare(self, data, where):
        out = super().prepare(data, where)
        if self.index_max >= len(out["points"]):
            raise ValueError(f"{where}: curve indices reach {self.index_max} but 'points' has {len(out['points'])} "
                             "particles")
        return out


_CURVE_ATTRS = {"type", "curveVertexCounts", "widths", "points", "velocities", "extent", "primvars:displayColor"}


def joined_form(decl):
    """:class:`JoinedPointsDecl` for curves between particles (``add_curves(name, indices)`` with
    one width and at most a constant colour); any other declaration unchanged."""
    if not isinstance(decl, CurvesDecl) or decl.gather is None or not set(decl.attrs) <= _CURVE_ATTRS:
        return decl
    widths = decl.attrs["widths"]
    if widths.metadata.get("interpolation") != "constant" or decl.children or decl.relationships:
        return decl
    return JoinedPointsDecl(decl)


def curve_samples(points, pairs, width):
    """The samples a :class:`CurvesDecl` with ``indices = pairs`` writes for particle positions
    ``points`` (n, 3) and diameter ``width`` [m]: ``{"points": (2 S, 3) segment ends, "extent"}``
    (the full cache's form of a sweep's :class:`JoinedPointsDecl` frame, bit for bit)."""
    ends = np.asarray(points, np.float32).reshape(-1, 3)[np.asarray(pairs, np.int64).reshape(-1)]
    return {"points": ends, "extent": _extent(ends, 0.5 * float(width))}


def segment_pairs(prim):
    """(S, 2) int64 point index pairs of a USD prim written by :class:`JoinedPointsDecl` (its
    ``warpsim:segments``), or None for any other prim; readers draw its curves as
    ``points[pairs]``."""
    attr = prim.GetAttribute(SEGMENTS_ATTR) if prim.GetTypeName() == "Points" else None
    if not attr or not attr.HasValue():
        return None
    pairs = np.asarray(attr.Get(), np.int64)
    return pairs[: len(pairs) // 2 * 2].reshape(-1, 2)


def curves_decl(prim):
    """The :class:`CurvesDecl` a lone run declares for a USD prim a sweep wrote by
    :class:`JoinedPointsDecl` (the inverse of :func:`joined_form`: the same segments, width,
    colour and velocities), or None for any other prim. Its ``frame_samples({"points": x}, frame)``
    with the prim's particle positions ``x`` (n, 3) [m] are the samples a lone run writes, bit for
    bit: a picked world is written in this full form (BasisCurves, which every USD tool draws)."""
    pairs = segment_pairs(prim)
    if pairs is None:
        return None
    width = float(np.asarray(prim.GetAttribute("widths").Get(), np.float64).reshape(-1)[0])
    color = prim.GetAttribute("primvars:displayColor")
    if color and color.HasValue():
        color = tuple(np.asarray(color.Get(), np.float64).reshape(-1, 3)[0])
    else:
        color = None
    velocities = prim.GetAttribute("velocities")
    return CurvesDecl(prim.GetName(), pairs, width=width, color=color,
                      velocities=bool(velocities and velocities.HasAuthoredValue()))


PROTOTYPE_KINDS = ("sphere", "cube", "cone", "capsule", "mesh")


class GeomDecl(PrimDecl):
    """Static geometry (colliders, instancer prototypes): a UsdGeom gprim with fixed attributes."""

    def __init__(self, name, type_name, attrs, color=None, translate=None):
        super().__init__(name)
        self.type_name = type_name
        for attr_name, (type_str, value) in attrs.items():
            self.static(attr_name, type_str, value, uniform=attr_name in ("axis", "subdivisionScheme"))
        if translate is not None:
            self.static("xformOp:translate", "double3", translate)
            self.static("xformOpOrder", "token[]", ["xformOp:translate"], uniform=True)
        if color is not None:
            self.add_primvar("displayColor", "color3f[]", "constant", [color])


def prototype_decl(index, spec):
    """GeomDecl and bounding radius [m] for an instancer prototype ``(kind, params)``."""
    if isinstance(spec, str):
        kind, params = spec, {}
    else:
        kind, params = spec
        params = dict(params or {})
    color = params.pop("color", None)
    name = f"proto{index}"
    if kind == "sphere":
        r = float(params.pop("radius", 0.05))
        decl = GeomDecl(name, "Sphere", {"radius": ("double", r), "extent": ("float3[]", [[-r] * 3, [r] * 3])}, color)
    elif kind == "cube":
        s = float(params.pop("size", 0.1))
        decl = GeomDecl(name, "Cube", {"size": ("double", s), "extent": ("float3[]", [[-s / 2] * 3, [s / 2] * 3])},
                        color)
    elif kind in ("cone", "capsule"):
        r = float(params.pop("radius", 0.05))
        h = float(params.pop("height", 0.2))
        axis = params.pop("axis", "Z")
        if axis not in ("X", "Y", "Z"):
            raise ValueError(f"prototype {index}: axis must be 'X', 'Y' or 'Z', got {axis!r}")
        half = h / 2 + (r if kind == "capsule" else 0.0)
        lo = [-r, -r, -r]
        hi = [r, r, r]
        k = "XYZ".index(axis)
        lo[k], hi[k] = -half, half
        decl = GeomDecl(name, kind.capitalize(), {"radius": ("double", r), "height": ("double", h),
                                                  "axis": ("token", axis), "extent": ("float3[]", [lo, hi])},
                        color)
    elif kind == "mesh":
        pts = coerce("point3f[]", params.pop("points"), f"prototype {index} points")
        counts = coerce("int[]", np.asarray(params.pop("face_vertex_counts")).reshape(-1), f"prototype {index}")
        idx = coerce("int[]", np.asarray(params.pop("face_vertex_indices")).reshape(-1), f"prototype {index}")
        check_topology(counts, idx, len(pts), f"prototype {index}")
        decl = GeomDecl(name, "Mesh", {"points": ("point3f[]", pts), "faceVertexCounts": ("int[]", counts),
                                       "faceVertexIndices": ("int[]", idx),
                                       "subdivisionScheme": ("token", "none"),
                                       "extent": ("float3[]", _extent(pts, 0.0))}, color)
    else:
        raise ValueError(f"prototype {index}: unknown kind {kind!r}; use one of {PROTOTYPE_KINDS}."
                         f"{close_matches(kind, PROTOTYPE_KINDS)}")
    if params:
        raise ValueError(f"prototype {index} ({kind}): unknown parameters {sorted(params)}")
    # Bound [m]: farthest corner of the prototype's extent box from its origin, so any rotated
    # instance's box (what UsdGeom.PointInstancer.ComputeExtentAtTime uses) stays inside.
    lo, hi = np.asarray(decl.attrs["extent"].value, np.float64)
    bound = float(np.linalg.norm(np.maximum(np.abs(lo), np.abs(hi))))
    return decl, bound


class InstancerDecl(PrimDecl):
    """``UsdGeom.PointInstancer``: positions, orientations, protoIndices, ids, velocities every frame."""

    type_name = "PointInstancer"

    def __init__(self, name, prototypes, *, count_changes=True, orientations=True, velocities=True):
        super().__init__(name)
        if not prototypes:
            raise ValueError(f"instancer {name!r}: give at least one prototype, e.g. [('cone', "
                             "{'radius': 0.05, 'height': 0.2})]")
        self.count_changes = bool(count_changes)
        self.bound = 0.0
        targets = []
        for i, spec in enumerate(prototypes):
            decl, bound = prototype_decl(i, spec)
            self.children.append((f"Prototypes/{decl.name}", decl))
            targets.append(f"Prototypes/{decl.name}")
            self.bound = max(self.bound, bound)
        self.prototype_count = len(prototypes)
        self.relationships["prototypes"] = targets
        self.has_orientations = bool(orientations)
        self.has_velocities = bool(velocities)
        self.dynamic("positions", "point3f[]")
        if self.has_orientations:
            self.dynamic("orientations", "quath[]")
        self.dynamic("protoIndices", "int[]")
        self.dynamic("ids", "int64[]")
        if self.has_velocities:
            self.dynamic("velocities", "vector3f[]")
        self.dynamic("extent", "float3[]", derived=True)

    def prepare(self, data, where):
        data = dict(data)
        pos = coerce("point3f[]", data.get("positions", np.zeros((0, 3))), f"{where}, 'positions'")
        n = len(pos)
        if "protoIndices" not in data:
            if self.prototype_count != 1:
                raise ValueError(f"{where}: 'protoIndices' is needed every frame with several prototypes")
            data["protoIndices"] = np.zeros(n, np.int32)
        if "ids" not in data:
            if self.count_changes:
                raise ValueError(f"{where}: 'ids' is needed every frame when counts change")
            data["ids"] = np.arange(n, dtype=np.int64)
        out = super().prepare(data, where)
        self._check_count(n, where, "positions", not self.count_changes)
        for key in ("orientations", "protoIndices", "ids", "velocities"):
            if key in out and len(out[key]) != n:
                raise ValueError(f"{where}: {key!r} has {len(out[key])} elements but positions has {n}")
        pi = out["protoIndices"]
        if n and (pi.min() < 0 or pi.max() >= self.prototype_count):
            raise ValueError(f"{where}: protoIndices must lie in [0, {self.prototype_count})")
        for key, attr in self.attrs.items():
            if attr.dynamic and attr.metadata.get("interpolation") == "vertex" and len(out[key]) != n:
                raise ValueError(f"{where}: primvar {key!r} has {len(out[key])} elements, expected {n}")
        out["extent"] = _extent(pos, self.bound)
        _check_finite(out["extent"], where, "positions")
        return out


MATERIAL_NAME = "preview_material"


def bind_preview_material(decl, color=(0.6, 0.6, 0.6), opacity=1.0, roughness=0.6) -> None:
    """Give ``decl`` a ``UsdPreviewSurface`` material (a ``Material`` child named
    ``preview_material`` holding a ``Shader``) bound through ``MaterialBindingAPI``: DCC tools
    (Blender's importer, usdview, Houdini) read its ``inputs:opacity``, which ``displayOpacity``
    alone does not carry to them, so a see-through container shows what it holds.
    ``color`` in [0, 1] (3,); ``opacity`` in [0, 1]."""
    shader = PrimDecl("PreviewSurface")
    shader.type_name = "Shader"
    shader.static("info:id", "token", "UsdPreviewSurface", uniform=True)
    shader.static("inputs:diffuseColor", "color3f", tuple(float(c) for c in color))
    shader.static("inputs:opacity", "float", float(opacity))
    shader.static("inputs:roughness", "float", float(roughness))
    shader.static("outputs:surface", "token", None)
    material = PrimDecl(MATERIAL_NAME)
    material.type_name = "Material"
    material.static("outputs:surface", "token", None, connection="PreviewSurface.outputs:surface")
    material.children.append(("PreviewSurface", shader))
    decl.children.append((MATERIAL_NAME, material))
    decl.relationships["material:binding"] = [MATERIAL_NAME]
    decl.api_schemas = ["MaterialBindingAPI"]
