"""The declaration side of every output of a scene (pure NumPy; no ``pxr`` import).

A scene describes itself once, in ``declare(sink)``, with :class:`PrimSink`'s methods
(``add_points``, ``add_mesh``, ``add_curves``, ``add_instancer``, static ``add_plane`` /
``add_box`` / ``add_sphere`` / ``add_static_mesh``, ``add_primvar`` / ``add_attribute``), and
hands ``{prim name: {key: array}}`` frames to whatever listens. Each sink subclasses
:class:`PrimSink`: :class:`warpsim.usd.writer.UsdCacheWriter` writes the frames to a USD cache,
``warpsim.viewer.sink.ViewerSink`` draws them in a browser. ``sink.prims`` holds the
:mod:`warpsim.usd.prims` declarations ({name: PrimDecl}, in declaration order); a declaration's
``frame_samples(data, frame)`` validates one frame and returns its attribute samples.
"""
from __future__ import annotations

import re

import numpy as np

from ..core.names import close_matches
from .prims import CurvesDecl, GeomDecl, InstancerDecl, MeshDecl, PointsDecl, bind_preview_material

__all__ = ["PrimSink", "state_frame_data"]

_IDENTIFIER = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


def state_frame_data(prims, state):
    """``{name: {"points", "velocities"}}`` for the points prims declared ``from_state=True``."""
    return {d.name: {"points": state.positions, **({"velocities": state.velocities} if d.has_velocities else {})}
            for d in prims.values() if d.from_state}


PURPOSES = ("default", "render", "proxy", "guide")


def display_hints(decl, opacity=None, purpose=None):
    """Author a constant ``primvars:displayOpacity`` and the ``purpose`` on a declaration; with an
    opacity, also a bound ``UsdPreviewSurface`` material of that opacity and the prim's colour (what
    Blender's importer and usdview read as see-through; ``displayOpacity`` alone they do not)."""
    if opacity is not None:
        if not 0.0 <= float(opacity) <= 1.0:
            raise ValueError(f"prim {decl.name!r}: opacity must lie in [0, 1], got {opacity!r}")
        decl.add_primvar("displayOpacity", "float[]", "constant", [float(opacity)])
        color = decl.attrs.get("primvars:displayColor")
        rgb = np.asarray(color.value, np.float64).reshape(-1, 3)[0] if color is not None and color.value is not None \
            else (0.6, 0.6, 0.6)
        bind_preview_material(decl, rgb, float(opacity))
    if purpose is not None:
        if purpose not in PURPOSES:
            raise ValueError(f"prim {decl.name!r}: purpose {purpose!r} is not one of {PURPOSES}."
                             f"{close_matches(purpose, PURPOSES)}")
        decl.static("purpose", "token", purpose, uniform=True)


class PrimSink:
    """Collects a scene's prim declarations (see the module docstring). Declarations are frozen
    once a sink is sealed (``self._sealed``: the first frame was written or drawn)."""

    def __init__(self):
        self.prims = {}  # name -> PrimDecl, in declaration order
        self._sealed = False

    # ------------------------------------------------------------------ declarations
    def _valid_name(self, name):
        """Whether ``name`` is a valid USD prim identifier (letters, digits, '_', no leading digit)."""
        return _IDENTIFIER.fullmatch(name) is not None

    def _declare(self, decl):
        if self._sealed:
            raise ValueError(f"declare prim {decl.name!r} before the first frame is written")
        if not self._valid_name(decl.name):
            raise ValueError(f"prim name {decl.name!r} is not a valid USD identifier (letters, digits, '_', "
                             "not starting with a digit)")
        if decl.name in self.prims:
            raise ValueError(f"prim {decl.name!r} is declared twice")
        self.prims[decl.name] = decl
        return decl

    def add_points(self, name, *, count_changes=False, radius=0.01, dynamic_widths=False, color=None,
                   velocities=True, from_state=False):
        """Declare ``UsdGeom.Points``. Per frame: ``points`` (n, 3) [m], ``velocities`` (n, 3) [m/s]
        (unless ``velocities=False``), ``ids`` (n,) when ``count_changes``, ``widths`` (n,) [m]
        diameters when ``dynamic_widths``. ``radius`` [m] is a scalar or per-point array (fixed
        counts); widths are authored as diameters. ``from_state``: :meth:`write` fills it."""
        return self._declare(PointsDecl(name, count_changes=count_changes, radius=radius,
                                        dynamic_widths=dynamic_widths, color=color, velocities=velocities,
                                        from_state=from_state))

    def add_mesh(self, name, face_vertex_counts=None, face_vertex_indices=None, *, topology_changes=False,
                 velocities=True, color=None, double_sided=False):
        """Declare a deforming ``UsdGeom.Mesh`` (``subdivisionScheme = none``). Fixed topology is
        written once; with ``topology_changes=True`` pass ``faceVertexCounts``/``faceVertexIndices``
        every frame and they are sampled only when they change. Per frame: ``points`` (v, 3) [m],
        ``velocities`` (v, 3) [m/s] unless ``velocities=False``."""
        return self._declare(MeshDecl(name, face_vertex_counts, face_vertex_indices,
                                      topology_changes=topology_changes, velocities=velocities, color=color,
                                      double_sided=double_sided))

    def add_curves(self, name, indices=None, *, curve_vertex_counts=None, width=0.005, color=None,
                   velocities=False):
        """Declare linear ``UsdGeom.BasisCurves``. With ``indices`` (pairs of particle indices, e.g.
        ``model.spring_indices``) each frame's ``points`` are the particle positions (n, 3) and one
        two-vertex segment is drawn per pair; otherwise ``points`` are the curve vertices for
        ``curve_vertex_counts``. ``width`` [m] is the curve diameter: one number, or one per curve
        vertex (e.g. hair tapering from root to tip)."""
        return self._declare(CurvesDecl(name, indices, curve_vertex_counts=curve_vertex_counts, width=width,
                                        color=color, velocities=velocities))

    def add_instancer(self, name, prototypes, *, count_changes=True, orientations=True, velocities=True,
                      primvars=None):
        """Declare a ``UsdGeom.PointInstancer`` (agents). ``prototypes``: list of ``(kind, params)``
        with kind in sphere/cube/cone/capsule/mesh, e.g. ``("cone", {"radius": 0.05, "height":
        0.2, "axis": "Z", "color": (1, 0, 0)})``. Per frame: ``positions`` (n, 3) [m],
        ``orientations`` (n, 4) quaternions (x, y, z, w), ``protoIndices`` (n,) (optional with one
        prototype), ``ids`` (n,) (optional when counts are fixed), ``velocities`` (n, 3) [m/s], and
        each primvar in ``primvars`` ({name: type name}, per-agent e.g. ``{"state": "int[]"}``)."""
        decl = InstancerDecl(name, prototypes, count_changes=count_changes, orientations=orientations,
                             velocities=velocities)
        for pv_name, type_name in (primvars or {}).items():
            decl.add_primvar(pv_name, type_name, "vertex")
        return self._declare(decl)

    def add_static_mesh(self, name, points, face_vertex_counts, face_vertex_indices, *, color=None,
                        double_sided=True, opacity=None, purpose=None):
        """Declare fixed geometry (a collider) as a ``UsdGeom.Mesh``: points (v, 3) [m].
        ``opacity`` in [0, 1] authors a constant ``primvars:displayOpacity`` and ``purpose``
        (default/render/proxy/guide) the prim's purpose: a container written with e.g.
        ``opacity=0.15, purpose="guide"`` does not hide what it holds in other USD tools."""
        decl = MeshDecl(name, face_vertex_counts, face_vertex_indices, points=points, color=color,
                        double_sided=double_sided)
        display_hints(decl, opacity, purpose)
        return self._declare(decl)

    def add_plane(self, name, normal=(0.0, 1.0, 0.0), offset=0.0, *, size=4.0, color=(0.5, 0.5, 0.5)):
        """Declare a plane collider ``dot(n, x) = offset`` as a square quad mesh of side ``size`` [m]."""
        n = np.asarray(normal, np.float64)
        if n.shape != (3,) or not np.isfinite(n).all() or np.linalg.norm(n) == 0:
            raise ValueError(f"plane {name!r}: normal must be a non-zero 3-vector, got {normal!r}")
        n = n / np.linalg.norm(n)
        helper = np.array([1.0, 0, 0]) if abs(n[0]) < 0.9 else np.array([0, 0, 1.0])
        u = np.cross(n, helper)
        u /= np.linalg.norm(u)
        v = np.cross(n, u)  # (u, v, n) right-handed: the quad faces +n
        c = n * float(offset)
        h = 0.5 * float(size)
        pts = [c - h * u - h * v, c + h * u - h * v, c + h * u + h * v, c - h * u + h * v]
        return self.add_static_mesh(name, np.array(pts), [4], [0, 1, 2, 3], color=color)

    def add_box(self, name, lower, upper, *, color=(0.6, 0.6, 0.6), opacity=None, purpose=None):
        """Declare an axis-aligned box collider [lower, upper] [m] as a six-quad mesh (normals outward);
        ``opacity`` and ``purpose`` as in :meth:`add_static_mesh`."""
        lo = np.asarray(lower, np.float64)
        hi = np.asarray(upper, np.float64)
        if lo.shape != (3,) or hi.shape != (3,) or not (hi > lo).all():
            raise ValueError(f"box {name!r}: need lower < upper component-wise, got {lower!r}, {upper!r}")
        corners = np.array([[(hi if (i >> k) & 1 else lo)[k] for k in range(3)] for i in range(8)])
        faces = [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]]
        return self.add_static_mesh(name, corners, [4] * 6, np.array(faces).reshape(-1), color=color,
                                    double_sided=False, opacity=opacity, purpose=purpose)

    def add_sphere(self, name, center=(0.0, 0.0, 0.0), radius=1.0, *, color=(0.6, 0.6, 0.6)):
        """Declare a sphere collider as a ``UsdGeom.Sphere`` at ``center`` [m] of ``radius`` [m]."""
        r = float(radius)
        if not np.isfinite(r) or r <= 0:
            raise ValueError(f"sphere {name!r}: radius must be > 0, got {radius!r}")
        return self._declare(GeomDecl(name, "Sphere", {"radius": ("double", r),
                                                       "extent": ("float3[]", [[-r] * 3, [r] * 3])},
                                      color=color, translate=center))

    def add_primvar(self, prim, name, type_name, interpolation="vertex", value=None):
        """Add primvar ``name`` to declared ``prim``: static when ``value`` is given, else sampled per
        frame under key ``name`` (or ``primvars:name``)."""
        self._prim(prim).add_primvar(name, type_name, interpolation, value)

    def add_attribute(self, prim, name, type_name, value=None, *, unit=None):
        """Add custom attribute ``name`` (e.g. ``"warpsim:energy"``, ``"double"``) to ``prim``:
        static when ``value`` is given, else sampled per frame under key ``name``. ``unit`` (e.g.
        ``"rad"``) goes to the attribute's ``customData["unit"]``, which ``warpsim plot`` puts on
        its axis."""
        if self._sealed:
            raise ValueError(f"add attribute {name!r} before the first frame is written")
        self._prim(prim).add_attribute(name, type_name, value, unit=unit)

    def _prim(self, name):
        if self._sealed:
            raise ValueError("declare prims and attributes before the first frame is written")
        if name not in self.prims:
            raise ValueError(f"no prim named {name!r}; declared: {sorted(self.prims)}.{close_matches(name, self.prims)}")
        return self.prims[name]
