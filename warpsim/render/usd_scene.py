"""Gathering a USD cache's prims into renderer geometry, frame by frame (``pxr`` imported lazily).

Which prims are drawn, as USD tools do by default: imageable prims whose computed purpose is
``default`` or ``render`` (``guide`` prims only with ``guides=True``, translucent: their
``displayOpacity`` or ``GUIDE_OPACITY``; ``proxy`` never) and whose
computed visibility is not ``invisible``. ``primvars:displayColor`` (constant, uniform or
vertex) colours them and a constant ``primvars:displayOpacity`` < 1 makes them translucent.

- ``Mesh``: polygons, fan-triangulated; ``Cube`` and ``Cone`` are tessellated.
- ``Points``: spheres of diameter ``widths``; a ``Points`` prim carrying a ``density`` primvar
  and a ``warpsim:cellSize`` attribute [m] (cell-centre samples of a grid, as the smoke scene
  writes) becomes a density volume instead.
- ``BasisCurves``: every curve as a chain of capsules of its width (thin tubes).
- ``Sphere``, ``Capsule``, ``Cylinder`` (drawn as a capsule): exact shapes.
- ``PointInstancer``: each instance of a Sphere/Capsule prototype exactly, Cube/Cone/Mesh
  prototypes as transformed triangles; per-instance ``displayColor`` primvars are honoured.
"""
from __future__ import annotations

import numpy as np

from ..usd.prims import segment_pairs
from ..usd.validate import frame_codes, open_stage
from .geometry import GeometryBuilder, cone_mesh, cube_mesh, mesh_faces

DRAWN_PURPOSES = ("default", "render")
GUIDE_OPACITY = 0.25


_EYE = np.eye(4)
_EYE_TOL = 1e-8 + 1e-5 * _EYE  # np.allclose's atol + rtol |b|


def quat_rotate(q, v):
    """Rotate vectors v (n, 3) or (3,) by unit quaternions q (n, 4) stored (x, y, z, w)."""
    q = np.asarray(q, np.float64)
    xyz, w = q[:, :3], q[:, 3:4]
    t = 2.0 * np.cross(xyz, v)
    return v + w * t + np.cross(xyz, t)


def _np(value, dtype=np.float64):
    return np.zeros(0, dtype) if value is None else np.asarray(value, dtype)


class CacheScene:
    """A USD cache opened for rendering.

    Args:
        path: the cache (``.usd``/``.usda``/``.usdc``); ValueError when it does not open.
        guides: also draw ``guide`` prims (with their ``displayOpacity``).
        only: names (or paths) of the prims to draw; None draws every drawn prim.
    Attributes: ``frames`` (the integer time codes, empty for a static file), ``fps``.
    """

    def __init__(self, path, guides=False, only=None):
        from pxr import Usd, UsdGeom

        if only is not None and (isinstance(only, (str, bytes)) or not all(isinstance(n, str) for n in only)):
            raise TypeError(f"only must be a list of prim names or paths, got {only!r}; e.g. only=['particles']")
        self.stage = open_stage(path)
        self.path = str(path)
        self.frames = frame_codes(self.stage)
        self.fps = float(self.stage.GetTimeCodesPerSecond())
        self.purposes = DRAWN_PURPOSES + (("guide",) if guides else ())
        skip = set()
        for prim in self.stage.Traverse():
            if prim.IsA(UsdGeom.PointInstancer):
                skip.update(str(t) for t in UsdGeom.PointInstancer(prim).GetPrototypesRel().GetTargets())
        self.prims = []
        it = iter(Usd.PrimRange(self.stage.GetPseudoRoot()))
        for prim in it:
            if str(prim.GetPath()) in skip:
                it.PruneChildren()
                continue
            wanted = only is None or prim.GetName() in only or str(prim.GetPath()) in only
            if wanted and (prim.IsA(UsdGeom.Gprim) or prim.IsA(UsdGeom.PointInstancer)):
                self.prims.append(prim)
        if only is not None:
            found = {p.GetName() for p in self.prims} | {str(p.GetPath()) for p in self.prims}
            missing = [n for n in only if n not in found]
            if missing or not only:
                names = sorted({p.GetName() for p in self.stage.Traverse()
                                if p.IsA(UsdGeom.Gprim) or p.IsA(UsdGeom.PointInstancer)})
                raise ValueError(f"only={list(only)!r}: {'no prim named ' + repr(missing[0]) if missing else 'no names'}"
                                 f" in {self.path}; drawn prims: {', '.join(names) or 'none'}")

    # ------------------------------------------------------------------ framing
    def time(self, frame):
        from pxr import Usd

        return Usd.TimeCode.Default() if frame is None else Usd.TimeCode(float(frame))

    def bounds(self, frames=None, samples=5):
        """World bounds [[lo], [hi]] [m] of the drawn prims over up to ``samples`` of ``frames``
        (all of the cache's by default); None when nothing is drawn."""
        from pxr import UsdGeom

        frames = list(self.frames if frames is None else frames) or [None]
        picks = sorted({frames[round(k)] for k in np.linspace(0, len(frames) - 1, min(samples, len(frames)))},
                       key=lambda f: -1 if f is None else f)
        lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
        for f in picks:
            cache = self.bbox_cache(f)
            for prim in self.prims:
                box = self.prim_box(cache, prim) if self._drawn(prim, f) else None
                if box is not None:
                    lo, hi = np.minimum(lo, box[0]), np.maximum(hi, box[1])
        return np.array([lo, hi]) if np.isfinite(lo).all() else None

    def bbox_cache(self, frame):
        """A ``UsdGeom.BBoxCache`` of ``frame`` over this scene's purposes (no extentsHint)."""
        from pxr import UsdGeom

        return UsdGeom.BBoxCache(self.time(frame), list(self.purposes), useExtentsHint=False)

    @staticmethod
    def prim_box(cache, prim):
        """World bounds ((3,) lo, (3,) hi) [m] of ``prim`` from ``cache`` (:meth:`bbox_cache`), None when empty."""
        box = cache.ComputeWorldBound(prim).ComputeAlignedRange()
        return None if box.IsEmpty() else (np.asarray(box.GetMin()), np.asarray(box.GetMax()))

    def subject_bounds(self, frames=None, samples=7, quantile=0.01):
        """Robust world bounds [[lo], [hi]] [m] of the scene's subject: the time-varying prims
        (points, meshes, curves, instancers; not colliders, containers or floors) over up to
        ``samples`` of ``frames``, cut at the ``quantile`` and ``1 - quantile`` of their points
        per axis (a few outliers, such as debris flung far away, do not shrink the subject to a
        speck), widened by point radii and 5 % of the extent. None when nothing moves."""
        from pxr import UsdGeom

        frames = list(self.frames if frames is None else frames)
        if not frames or frames == [None]:
            return None
        picks = sorted({frames[round(k)] for k in np.linspace(0, len(frames) - 1, min(samples, len(frames)))})
        moving = []
        for prim in self.prims:
            attr = prim.GetAttribute("positions" if prim.IsA(UsdGeom.PointInstancer) else "points")
            if attr and attr.ValueMightBeTimeVarying():
                moving.append((prim, attr))
        if not moving:
            return None
        clouds, pad = [], 0.0
        for f in picks:
            t = self.time(f)
            xf = UsdGeom.XformCache(t)
            for prim, attr in moving:
                if not self._drawn(prim, f):
                    continue
                pts = _np(attr.Get(t)).reshape(-1, 3)
                if len(pts) == 0:
                    continue
                clouds.append(self._apply(np.asarray(xf.GetLocalToWorldTransform(prim), np.float64), pts))
                widths = prim.GetAttribute("widths")
                w = _np(widths.Get(t)) if widths else np.zeros(0)
                pad = max(pad, 0.5 * float(np.max(w)) if len(w) else 0.0)
        if not clouds:
            return None
        pts = np.concatenate(clouds)
        lo, hi = np.quantile(pts, quantile, axis=0), np.quantile(pts, 1.0 - quantile, axis=0)
        grow = 0.05 * (hi - lo) + pad
        return np.array([lo - grow, hi + grow])

    def _drawn(self, prim, frame):
        from pxr import UsdGeom

        img = UsdGeom.Imageable(prim)
        if img.ComputePurpose() not in self.purposes:
            return False
        return img.ComputeVisibility(self.time(frame)) != UsdGeom.Tokens.invisible

    # ------------------------------------------------------------------ geometry
    def geometry(self, frame=None):
        """:class:`~warpsim.render.geometry.FrameGeometry` of ``frame`` (None: default time)."""
        from pxr import UsdGeom

        t = self.time(frame)
        xf = UsdGeom.XformCache(t)
        g = GeometryBuilder()
        for prim in self.prims:
            look = self.look(prim, frame, xf)
            if look is not None:
                self.add_prim(g, prim, t, look)
        return g.build()

    def look(self, prim, frame, xf):
        """How ``prim`` is drawn at ``frame``: (transform (4, 4) [m], colour, opacity), or None when
        it is not drawn; ``xf``: a ``UsdGeom.XformCache`` of the frame."""
        from pxr import UsdGeom

        if not self._drawn(prim, frame):
            return None
        m = np.asarray(xf.GetLocalToWorldTransform(prim), np.float64)  # row-vector convention: p' = [p 1] m
        color, opacity = self._display(prim, self.time(frame))
        if opacity >= 1.0 and UsdGeom.Imageable(prim).ComputePurpose() == "guide":
            opacity = GUIDE_OPACITY  # guides without a displayOpacity are drawn see-through
        return m, color, opacity

    def add_prim(self, g, prim, t, look):
        """Add ``prim`` at time ``t`` drawn with ``look`` (:meth:`look`) to the GeometryBuilder ``g``."""
        handler = getattr(self, f"_add_{prim.GetTypeName()}", None)
        if handler is not None:
            handler(g, prim, t, *look)

    @staticmethod
    def _display(prim, t):
        """(colour: None, (3,) or (n, 3); constant opacity) from the display primvars."""
        from pxr import UsdGeom

        api = UsdGeom.PrimvarsAPI(prim)
        color = None
        pv = api.GetPrimvar("displayColor")
        if pv and pv.HasValue():
            value = pv.ComputeFlattened(t)
            if value is not None and len(value):
                color = np.asarray(value, np.float32)
        opacity = 1.0
        pv = api.GetPrimvar("displayOpacity")
        if pv and pv.HasValue():
            value = pv.ComputeFlattened(t)
            if value is not None and len(value):
                opacity = float(np.asarray(value, np.float64).mean())
        return color, opacity

    @staticmethod
    def _apply(m, p):
        if (np.abs(m - _EYE) <= _EYE_TOL).all():  # np.allclose(m, np.eye(4)), without its generality
            return p
        return p @ m[:3, :3] + m[3, :3]

    @staticmethod
    def _scale(m):
        return float(np.cbrt(abs(np.linalg.det(m[:3, :3])))) or 1.0

    # A Mesh, Points or BasisCurves prim is read in two parts: its declaration (_decl_KIND: topology,
    # widths, colours; what a batch layer's worlds share) and its points (the sampled part), which
    # _draw_KIND turns into geometry with the declaration.
    @staticmethod
    def _points(prim, t):
        """The prim's ``points`` at ``t``, (n, 3) float32 (local) [m]."""
        return _np(prim.GetAttribute("points").Get(t), np.float32)

    def _add_Mesh(self, g, prim, t, m, color, opacity):
        pts = self._points(prim, t)
        if len(pts) == 0:
            return
        self._draw_Mesh(g, self._decl_Mesh(prim, t, color, len(pts)), pts, m, opacity)

    @staticmethod
    def _decl_Mesh(prim, t, color, count):
        """:class:`~warpsim.render.geometry.MeshFaces` of the mesh over ``count`` points (or None)."""
        from pxr import UsdGeom

        mesh = UsdGeom.Mesh(prim)
        counts = _np(mesh.GetFaceVertexCountsAttr().Get(t), np.int64)
        indices = _np(mesh.GetFaceVertexIndicesAttr().Get(t), np.int64)
        return mesh_faces(counts, indices, color, count)

    def _draw_Mesh(self, g, decl, pts, m, opacity):
        g.add_faces(self._apply(m, pts), decl, opacity)

    def _add_Cube(self, g, prim, t, m, color, opacity):
        pts, counts, idx = cube_mesh(prim.GetAttribute("size").Get(t) or 2.0)
        g.add_mesh(self._apply(m, pts), counts, idx, color, opacity)

    def _add_Cone(self, g, prim, t, m, color, opacity):
        pts, counts, idx = cone_mesh(prim.GetAttribute("radius").Get(t) or 1.0, prim.GetAttribute("height").Get(t) or 2.0,
                                     str(prim.GetAttribute("axis").Get(t) or "Z"))
        g.add_mesh(self._apply(m, pts), counts, idx, color, opacity)

    def _add_Sphere(self, g, prim, t, m, color, opacity):
        r = float(prim.GetAttribute("radius").Get(t) or 1.0) * self._scale(m)
        g.add_spheres(m[3:4, :3], r, color)

    def _capsule_axis(self, prim, t):
        r = float(prim.GetAttribute("radius").Get(t) or 0.5)
        h = float(prim.GetAttribute("height").Get(t) or 1.0)
        axis = np.zeros(3)
        axis["XYZ".index(str(prim.GetAttribute("axis").Get(t) or "Z"))] = 0.5 * h
        return r, axis

    def _add_Capsule(self, g, prim, t, m, color, opacity):
        r, axis = self._capsule_axis(prim, t)
        ends = self._apply(m, np.stack([-axis, axis]))
        g.add_capsules(ends[:1], ends[1:], r * self._scale(m), color)

    _add_Cylinder = _add_Capsule

    def _add_Points(self, g, prim, t, m, color, opacity):
        pts = self._points(prim, t)
        if len(pts) == 0:
            return
        decl = self._decl_Points(prim, t, color, len(pts))
        if not (decl["volume"] and self._add_volume(g, prim, t, self._apply(m, pts), m, color)):
            self._draw_Points(g, decl, pts, m, opacity)

    @staticmethod
    def _decl_Points(prim, t, color, count):
        """{"volume": a density grid's samples?, "widths", "pairs" (joined points) or None, "color"}."""
        from pxr import UsdGeom

        density = UsdGeom.PrimvarsAPI(prim).GetPrimvar("density")
        cell = prim.GetAttribute("warpsim:cellSize")
        return {"volume": bool(density and density.HasValue() and cell and cell.HasValue()), "color": color,
                "widths": _np(UsdGeom.Points(prim).GetWidthsAttr().Get(t), np.float32),
                "pairs": segment_pairs(prim)}  # a sweep's springs: curves between its points, drawn as curves are

    def _draw_Points(self, g, decl, pts, m, opacity):
        pts, widths, pairs, color = self._apply(m, pts), decl["widths"], decl["pairs"], decl["color"]
        if pairs is not None and len(widths) == 1 and (not len(pairs) or pairs.max() < len(pts)):
            g.add_capsules(pts[pairs[:, 0]], pts[pairs[:, 1]], 0.5 * float(widths[0]) * self._scale(m),
                           color if color is None or len(color) == 1 else None)
            return
        r = 0.5 * (widths if len(widths) == len(pts) else (widths[:1] if len(widths) else np.float32(0.01)))
        g.add_spheres(pts, r * self._scale(m), color if color is None or len(color) in (1, len(pts)) else None)

    def _add_volume(self, g, prim, t, pts, m, color):
        """The Points prim as a density volume (its ``density`` at its world points ``pts``);
        False when the densities do not match the points."""
        from pxr import UsdGeom

        rho = _np(UsdGeom.PrimvarsAPI(prim).GetPrimvar("density").ComputeFlattened(t), np.float32)
        if len(rho) != len(pts):
            return False
        dx = float(prim.GetAttribute("warpsim:cellSize").Get()) * self._scale(m)
        lo = pts.min(0)
        ijk = np.rint((pts - lo) / dx).astype(np.int64)
        grid = np.zeros(ijk.max(0) + 1, np.float32)
        grid[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = rho
        c = (0.8, 0.8, 0.85) if color is None else np.asarray(color, np.float32).reshape(-1, 3)[0]
        g.set_volume(grid, lo - 0.5 * dx, dx, c)
        return True

    def _add_BasisCurves(self, g, prim, t, m, color, opacity):
        pts = self._points(prim, t)
        if len(pts) == 0:
            return
        self._draw_BasisCurves(g, self._decl_BasisCurves(prim, t, color, len(pts)), pts, m, opacity)

    @staticmethod
    def _decl_BasisCurves(prim, t, color, count):
        """The segments of curves over ``count`` points: {"starts": (S,) first point of each,
        "radius": [m] (scalar or (S,)), "color"}, or None when the counts do not add up to ``count``."""
        from pxr import UsdGeom

        curves = UsdGeom.BasisCurves(prim)
        counts = _np(curves.GetCurveVertexCountsAttr().Get(t), np.int64)
        if len(counts) == 0 or counts.sum() != count:
            return None
        widths = _np(curves.GetWidthsAttr().Get(t), np.float32)
        seg_start = np.ones(count, bool)
        seg_start[np.cumsum(counts) - 1] = False  # the last vertex of a curve starts no segment
        i = np.flatnonzero(seg_start)
        r = 0.5 * (widths[i] if len(widths) == count else (widths[0] if len(widths) else 0.005))
        c = color if color is None or len(color) == 1 else (color[i] if len(color) == count else None)
        return {"starts": i, "radius": r, "color": c}

    def _draw_BasisCurves(self, g, decl, pts, m, opacity):
        if decl is not None:
            i, pts = decl["starts"], self._apply(m, pts)
            g.add_capsules(pts[i], pts[i + 1], decl["radius"] * self._scale(m), decl["color"])

    def _add_PointInstancer(self, g, prim, t, m, color, opacity):
        from pxr import UsdGeom

        inst = UsdGeom.PointInstancer(prim)
        pos = _np(inst.GetPositionsAttr().Get(t))
        if len(pos) == 0:
            return
        n = len(pos)
        pos = self._apply(m, pos)  # (the instancer's own rotation is not applied to the instances)
        q = _np(inst.GetOrientationsAttr().Get(t))
        q = q if len(q) == n else np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))
        scales = _np(inst.GetScalesAttr().Get(t))
        scale = scales if len(scales) == n else np.ones((n, 3))
        proto = _np(inst.GetProtoIndicesAttr().Get(t), np.int64)
        proto = proto if len(proto) == n else np.zeros(n, np.int64)
        per = color if color is not None and len(color) == n else None
        stage = prim.GetStage()
        for k, target in enumerate(inst.GetPrototypesRel().GetTargets()):
            sel = np.flatnonzero(proto == k)
            if len(sel) == 0:
                continue
            p = stage.GetPrimAtPath(target)
            pc, _ = self._display(p, t)
            c = per[sel] if per is not None else pc
            kind = p.GetTypeName()
            s = np.cbrt(np.prod(scale[sel], axis=1))
            if kind == "Sphere":
                g.add_spheres(pos[sel], float(p.GetAttribute("radius").Get(t) or 1.0) * s, c)
            elif kind in ("Capsule", "Cylinder"):
                r, axis = self._capsule_axis(p, t)
                a = quat_rotate(q[sel], np.broadcast_to(axis, (len(sel), 3)) * scale[sel])
                g.add_capsules(pos[sel] - a, pos[sel] + a, r * s, c)
            else:
                if kind == "Cube":
                    lp, counts, idx = cube_mesh(p.GetAttribute("size").Get(t) or 2.0)
                elif kind == "Cone":
                    lp, counts, idx = cone_mesh(p.GetAttribute("radius").Get(t) or 1.0,
                                                p.GetAttribute("height").Get(t) or 2.0,
                                                str(p.GetAttribute("axis").Get(t) or "Z"))
                elif kind == "Mesh":
                    mesh = UsdGeom.Mesh(p)
                    lp = _np(mesh.GetPointsAttr().Get(t))
                    counts = _np(mesh.GetFaceVertexCountsAttr().Get(t), np.int64)
                    idx = _np(mesh.GetFaceVertexIndicesAttr().Get(t), np.int64)
                else:
                    continue
                lp = np.asarray(lp, np.float64)
                v = len(lp)
                world = (quat_rotate(np.repeat(q[sel], v, 0), np.tile(lp, (len(sel), 1)) * np.repeat(scale[sel], v, 0))
                         + np.repeat(pos[sel], v, 0))
                counts = np.asarray(counts).reshape(-1)
                all_idx = (np.asarray(idx).reshape(1, -1) + v * np.arange(len(sel))[:, None]).reshape(-1)
                cc = c
                if c is not None and len(c) == len(sel) and len(sel) > 1:
                    cc = np.repeat(c, len(counts), 0)  # one colour per polygon of each instance
                g.add_mesh(world, np.tile(counts, len(sel)), all_idx, cc, 1.0)
