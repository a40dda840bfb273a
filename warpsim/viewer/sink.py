"""The viewer's sink: the scene's prim declarations turned into things to draw (pure NumPy).

A scene declares its prims on a :class:`ViewerSink` exactly as on the USD writer (both are
:class:`warpsim.usd.sink.PrimSink`\\ s); :meth:`ViewerSink.draw` validates one frame of
``scene.frame_data()`` through the same declarations (``PrimDecl.frame_samples``: the curves'
particle gathering, counts, extents) and returns :class:`DrawItem`\\ s that the viser front end
(``server``) or a test reads. Static prims (colliders) are drawn once (``static_items``).
"""
from __future__ import annotations

from typing import Optional
from dataclasses import dataclass, field

import numpy as np

from ..usd.prims import CurvesDecl, GeomDecl, InstancerDecl, MeshDecl, PointsDecl
from ..usd.sink import PrimSink
from .geometry import curve_segments, subsample, triangulate, unit_mesh, xyzw_to_wxyz

__all__ = ["DrawItem", "ViewerSink", "decl_color"]

DEFAULT_COLORS = {"points": (0.2, 0.5, 0.9), "mesh": (0.75, 0.75, 0.8), "segments": (0.35, 0.35, 0.35),
                  "instances": (0.9, 0.55, 0.2)}


@dataclass
class DrawItem:
    """One drawable. ``kind``: ``points`` (``points`` (n, 3) [m], ``radius`` [m]), ``mesh``
    (``points`` (v, 3), ``triangles`` (t, 3) uint32), ``segments`` (``points`` (s, 2, 3),
    ``radius`` = half the curve width [m]) or ``instances`` (``points`` (n, 3) positions,
    ``orientations`` (n, 4) w, x, y, z, ``proto`` (n,) prototype index, ``prototypes`` a list
    of (vertices, triangles)). ``color`` RGB in [0, 1]; ``topology`` counts topology changes
    (a new number: redraw the triangles); ``shown`` (n,) indices of the drawn subset of a
    subsampled points prim (None: all); ``opacity`` the prim's constant displayOpacity (None: opaque)."""

    name: str
    kind: str
    points: np.ndarray
    color: tuple = (0.7, 0.7, 0.7)
    radius: float = 0.01
    triangles: Optional[np.ndarray] = None
    orientations: Optional[np.ndarray] = None
    proto: Optional[np.ndarray] = None
    prototypes: list = field(default_factory=list)
    static: bool = False
    topology: int = 0
    shown: Optional[np.ndarray] = None
    opacity: Optional[float] = None


def decl_color(decl, kind):
    """displayColor of a declaration (its static constant primvar) or a default per kind."""
    attr = decl.attrs.get("primvars:displayColor")
    if attr is not None and attr.value is not None and len(attr.value):
        return tuple(float(c) for c in np.asarray(attr.value).reshape(-1, 3)[0])
    return DEFAULT_COLORS.get(kind, (0.7, 0.7, 0.7))


def decl_opacity(decl):
    """Constant displayOpacity of a declaration (containers are written see-through), or None."""
    attr = decl.attrs.get("primvars:displayOpacity")
    if attr is not None and attr.value is not None and len(attr.value):
        return float(np.asarray(attr.value).reshape(-1)[0])
    return None


def _static(decl, name):
    a = decl.attrs.get(name)
    return None if a is None or a.dynamic else a.value


class ViewerSink(PrimSink):
    """Collects a scene's declarations; ``draw(frame_data)`` -> {name: DrawItem} per frame.

    Args:
        max_points: draw at most this many points of a points prim (evenly strided; a million-
            particle liquid stays interactive); None: all.
    """

    def __init__(self, max_points=None):
        super().__init__()
        self.max_points = max_points
        self.frame = 0
        self._topology = {}  # mesh name -> (counts, indices, triangles, version)

    def static_items(self):
        """{name: DrawItem} of the prims that never change (colliders, static meshes)."""
        out = {}
        for name, decl in self.prims.items():
            if decl.is_dynamic:
                continue
            if isinstance(decl, MeshDecl):
                pts = _static(decl, "points")
                tris = triangulate(_static(decl, "faceVertexCounts"), _static(decl, "faceVertexIndices"))
                out[name] = DrawItem(name, "mesh", np.asarray(pts, np.float32), decl_color(decl, "mesh"),
                                     triangles=tris, static=True, opacity=decl_opacity(decl))
            elif isinstance(decl, GeomDecl):
                attrs = {k: a.value for k, a in decl.attrs.items() if not a.dynamic}
                verts, tris = unit_mesh(decl.type_name, attrs)
                offset = np.asarray(attrs.get("xformOp:translate", (0.0, 0.0, 0.0)), np.float32)
                out[name] = DrawItem(name, "mesh", verts + offset, decl_color(decl, "mesh"), triangles=tris,
                                     static=True, opacity=decl_opacity(decl))
        return out

    def draw(self, data, frame=None):
        """{name: DrawItem} of the time-varying prims for one frame of ``{prim: {key: array}}``
        (ValueError, as the USD writer raises, for missing or malformed data)."""
        self._sealed = True
        frame = self.frame if frame is None else int(frame)
        self.frame = frame + 1
        out = {}
        for name, decl in self.prims.items():
            if not decl.is_dynamic:
                continue
            samples = decl.frame_samples(data.get(name), frame)
            # own copies: on the CPU, state arrays are views that the next step overwrites
            samples = {k: v.copy() if isinstance(v, np.ndarray) and v.base is not None else v
                       for k, v in samples.items()}
            out[name] = self._item(name, decl, samples)
        return out

    def _item(self, name, decl, s):
        if isinstance(decl, PointsDecl):
            pts = s["points"]
            radius = float(np.mean(s["widths"]) / 2) if "widths" in s and len(s["widths"]) else \
                float(np.mean(decl.pad)) if np.size(decl.pad) else 0.01
            shown = subsample(len(pts), self.max_points)
            return DrawItem(name, "points", pts if shown is None else pts[shown], decl_color(decl, "points"),
                            radius=radius, shown=shown)
        if isinstance(decl, MeshDecl):
            if decl.topology_changes:
                tris, version = self._mesh_topology(name, s["faceVertexCounts"], s["faceVertexIndices"])
            else:
                tris, version = self._mesh_topology(name, _static(decl, "faceVertexCounts"),
                                                    _static(decl, "faceVertexIndices"))
            return DrawItem(name, "mesh", s["points"], decl_color(decl, "mesh"), triangles=tris, topology=version)
        if isinstance(decl, CurvesDecl):
            segs = curve_segments(s["points"], _static(decl, "curveVertexCounts"))
            return DrawItem(name, "segments", segs, decl_color(decl, "segments"),
                            radius=float(np.mean(decl.pad)))  # per-vertex widths (hair): their mean
        if isinstance(decl, InstancerDecl):
            protos = [unit_mesh(child.type_name, {k: a.value for k, a in child.attrs.items()})
                      for _, child in decl.children]
            n = len(s["positions"])
            orient = xyzw_to_wxyz(s["orientations"]) if "orientations" in s else \
                np.tile(np.array([[1.0, 0, 0, 0]], np.float32), (n, 1))
            colors = [decl_color(child, "instances") for _, child in decl.children]
            return DrawItem(name, "instances", s["positions"], colors[0], orientations=orient,
                            proto=s["protoIndices"], prototypes=protos)
        raise ValueError(f"prim {name!r}: the viewer cannot draw a {type(decl).__name__}")

    def _mesh_topology(self, name, counts, indices):
        """Triangles of a mesh, re-triangulated only when its counts/indices change."""
        known = self._topology.get(name)
        if known is not None and np.array_equal(known[0], counts) and np.array_equal(known[1], indices):
            return known[2], known[3]
        tris = triangulate(counts, indices)
        version = 0 if known is None else known[3] + 1
        self._topology[name] = (np.array(counts, copy=True), np.array(indices, copy=True), tris, version)
        return tris, version
