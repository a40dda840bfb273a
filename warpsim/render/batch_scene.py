"""A sweep's batch layer drawn world by world, reading what its worlds share once.

In a batch layer (:mod:`warpsim.sweeps.usd`) every world's prim ``/Worlds/world_G/NAME`` inherits
its declaration (topology, widths, colours, materials) from the class prim ``/WorldShared/NAME``;
only its clip-sampled attributes differ. A world's prim is *shared* when the layer authors nothing
on it but that inherit, nothing on its world prim but clips and custom data, and its clip
manifest samples at most ``points`` and ``extent`` of what is drawn (:func:`_undrawn`: beside
velocities, warpsim's records, other primvars).

For a shared prim, everything that follows from the declaration is made once per prim name and
frame from the first world that has it, by :class:`~warpsim.render.usd_scene.CacheScene`'s own
functions: whether and how it is drawn (transform, colour, opacity), its triangles, face
colours, widths or joined-points pairs (``_decl_KIND``), its bounding box and geometry when it
samples nothing. A world then reads only its points and draws them with that declaration
(``_draw_KIND``: corner normals, capsules). Any other prim (a world-level override, other
sampled attributes, a point count unlike the first world's) is read as
:meth:`CacheScene.geometry` reads it. The geometry and ground height are the same, bit for bit,
as :meth:`CacheScene.geometry` and :func:`warpsim.render.cache.ground_height` of the world's prims.
"""
from __future__ import annotations

import numpy as np

from .cache import ground_below, ground_scene
from .geometry import GeometryBuilder
from .usd_scene import CacheScene

__all__ = ["BatchScene"]

POINTS_KINDS = ("Mesh", "Points", "BasisCurves")
"""Prim types whose declaration and points are read apart (``_decl_KIND`` / ``_draw_KIND``)."""
_READ_RECORDS = ("warpsim:segments", "warpsim:cellSize")
_READ_PRIMVARS = ("displayColor", "displayOpacity", "density", "widths", "normals")


def _undrawn(name) -> bool:
    """Whether a sampled attribute changes no picture and no box: velocities, accelerations,
    warpsim's own records (not its joined-points segments or cell size) and primvars other than
    the display colour and opacity, density, widths and normals."""
    if name in ("velocities", "accelerations"):
        return True
    if name.startswith("warpsim:"):
        return name not in _READ_RECORDS
    return name.startswith("primvars:") and name.split(":")[1] not in _READ_PRIMVARS


_WORLD_INFO = frozenset({"specifier", "typeName", "clips", "customData"})
_PRIM_INFO = frozenset({"specifier", "typeName", "inheritPaths"})


class BatchScene:
    """The worlds of the batch layer ``path``: :meth:`geometry` and :meth:`ground` of one world at a
    frame. ``worlds``: ``{"world_GGGGGG": [its drawn prims]}``; ``frames``: the layer's frames."""

    def __init__(self, path):
        self.scene = CacheScene(path)
        self.frames = self.scene.frames
        self.worlds: dict = {}
        for prim in self.scene.prims:  # /Worlds/world_GGGGGG/...
            parts = str(prim.GetPath()).split("/")
            if len(parts) > 3 and parts[2].startswith("world_"):
                self.worlds.setdefault(parts[2], []).append(prim)
        self._full = ground_scene(self.scene)
        self._shared = _SharedPrims(self.scene.stage)
        self._templates: dict = {}  # (prim name, frame) -> _Template
        self._frame_caches: dict = {}  # frame -> (XformCache, BBoxCache of the ground's purposes)

    def _caches(self, frame):
        from pxr import UsdGeom

        if frame not in self._frame_caches:
            self._frame_caches = {frame: (UsdGeom.XformCache(self.scene.time(frame)), self._full.bbox_cache(frame))}
        return self._frame_caches[frame]

    def _template(self, world, prim, frame):
        """The shared declaration of ``prim`` (of ``world``) at ``frame``, or None: read it alone."""
        kind = self._shared.of(world).get(prim.GetName())
        if kind is None:
            return None
        key = (prim.GetName(), frame)
        if key not in self._templates:
            self._templates[key] = _Template(self, prim, frame, kind)
        tpl = self._templates[key]
        return tpl if tpl.kind == kind else None

    def geometry(self, world, frame):
        """:class:`~warpsim.render.geometry.FrameGeometry` of ``world``'s prims at ``frame``."""
        scene, t = self.scene, self.scene.time(frame)
        g = GeometryBuilder()
        for prim in self.worlds.get(world, []):
            tpl = self._template(world, prim, frame)
            if tpl is None:
                look = scene.look(prim, frame, self._caches(frame)[0])
                if look is not None:
                    scene.add_prim(g, prim, t, look)
            elif tpl.look is None:
                continue
            elif tpl.kind == "static":
                g.extend(tpl.geometry)
            else:
                pts = scene._points(prim, t)
                if tpl.decl is None or len(pts) != tpl.count:
                    scene.add_prim(g, prim, t, tpl.look)  # (a count unlike the template's: read alone)
                elif len(pts):
                    m, _, opacity = tpl.look
                    getattr(scene, "_draw_" + prim.GetTypeName())(g, tpl.decl, pts, m, opacity)
        return g.build()

    def ground(self, world, frame):
        """Ground height [m] under ``world`` at ``frame`` (False: nothing), as
        :func:`warpsim.render.cache.ground_height` of its prims at ``[frame]``."""
        full, t = self._full, self.scene.time(frame)
        cache = self._caches(frame)[1]
        lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
        for prim in self.worlds.get(world, []):
            tpl = self._template(world, prim, frame)
            if tpl is None:
                box = full.prim_box(cache, prim) if full._drawn(prim, frame) else None
            elif not tpl.ground_drawn:
                continue
            elif tpl.kind == "static":
                box = tpl.box
            else:
                box = (_extent_box(prim, t) if tpl.extent_box else None) or full.prim_box(cache, prim)
            if box is not None:
                lo, hi = np.minimum(lo, box[0]), np.maximum(hi, box[1])
        return ground_below(np.array([lo, hi]) if np.isfinite(lo).all() else None)


class _Template:
    """What a shared prim's declaration makes at one frame, read from one world's prim.
    ``kind``: "static" (samples nothing drawn), "points" or None (read each world's prim alone)."""

    def __init__(self, batch, prim, frame, kind):
        scene, full = batch.scene, batch._full
        xf, cache = batch._caches(frame)
        t = scene.time(frame)
        self.kind, self.look, self.decl, self.count, self.geometry, self.box = kind, None, None, 0, None, None
        self.look = scene.look(prim, frame, xf)
        self.ground_drawn = full._drawn(prim, frame)
        # a sampled prim's box is its extent sample where the BBoxCache reads just that (untransformed,
        # nothing below it): seen here to be its box, bit for bit; a world's empty or non-finite extent
        # is boxed by the BBoxCache
        self.extent_box = (kind == "points" and self.ground_drawn and not prim.GetAllChildren()
                           and np.array_equal(np.asarray(xf.GetLocalToWorldTransform(prim), np.float64), np.eye(4))
                           and _same_box(_extent_box(prim, t), full.prim_box(cache, prim)))
        if kind == "static":
            self.geometry = GeometryBuilder()
            if self.look is not None:
                scene.add_prim(self.geometry, prim, t, self.look)
            self.box = full.prim_box(cache, prim) if self.ground_drawn else None
        elif self.look is not None:
            pts = scene._points(prim, t)
            self.count = len(pts)
            if self.count:
                self.decl = getattr(scene, "_decl_" + prim.GetTypeName())(prim, t, self.look[1], self.count)
                if prim.GetTypeName() == "Points" and self.decl["volume"]:
                    self.kind = None  # a density grid: its densities are read with its points


def _extent_box(prim, t):
    """((3,) lo, (3,) hi) [m] of ``prim``'s ``extent`` at ``t`` as float64, None unless finite and not empty."""
    e = prim.GetAttribute("extent").Get(t)
    if e is None or len(e) != 2:
        return None
    e = np.asarray(e, np.float64)
    return (e[0], e[1]) if np.isfinite(e).all() and (e[0] <= e[1]).all() else None


def _same_box(a, b) -> bool:
    return a is not None and b is not None and all(x.tobytes() == y.tobytes() for x, y in zip(a, b))


class _SharedPrims:
    """Which prims of a world of the batch layer open as ``stage`` add nothing to their
    ``/WorldShared`` declaration (see the module docstring), read world by world when first asked
    (a worker reads only its worlds): ``of(world name)`` -> ``{prim name: "static" | "points"}``;
    none when the layer has sublayers or the stage a session layer with opinions."""

    def __init__(self, stage):
        self.layer = stage.GetRootLayer()
        shared = self.layer.GetPrimAtPath("/WorldShared")
        others = self.layer.subLayerPaths or len(stage.GetSessionLayer().rootPrims)
        # the declarations: {prim name: (type name, class prim path)}
        self.decls = {} if shared is None or others else {c.name: (c.typeName, str(c.path)) for c in shared.nameChildren}
        self.known: dict = {}
        self.manifests: dict = {}

    def of(self, world) -> dict:
        if world not in self.known:
            spec = self.layer.GetPrimAtPath("/Worlds/" + world) if self.decls else None
            self.known[world] = self._read(spec) if spec is not None else {}
        return self.known[world]

    def _read(self, world):
        from pxr import Sdf

        if set(world.ListInfoKeys()) - _WORLD_INFO or world.properties:
            return {}
        sampled = _clip_sampled(self.layer, world, self.manifests, Sdf)
        if sampled is None:
            return {}
        prims = {}
        for spec in world.nameChildren:
            decl = self.decls.get(spec.name)
            if decl is None or not _only_inherits(spec, *decl):
                continue
            drawn = {name for name in sampled.get(spec.name, ()) if not _undrawn(name)}
            if not drawn:
                prims[spec.name] = "static"
            elif drawn - {"extent"} == {"points"} and spec.typeName in POINTS_KINDS:
                prims[spec.name] = "points"  # (its box, from its extent, is read per world)
        return prims


def _only_inherits(spec, type_name, decl_path) -> bool:
    """Whether the prim spec ``spec`` authors nothing but one inherit of the class prim at ``decl_path``
    (a string) of type ``type_name``."""
    if set(spec.ListInfoKeys()) - _PRIM_INFO or spec.properties or spec.nameChildren or spec.typeName != type_name:
        return False
    paths = spec.GetInfo("inheritPaths")  # (an Sdf.PathListOp: its items read fast, unlike the spec's list editor's)
    items = paths.explicitItems if paths.isExplicit else paths.prependedItems + paths.appendedItems + paths.addedItems
    return [str(p) for p in items] == [decl_path] and not paths.deletedItems and not paths.orderedItems


def _clip_sampled(layer, world, manifests, Sdf):
    """``{prim name: attribute names}`` the clips of the world prim spec ``world`` sample (from
    their manifests), or None when that is not known or the world prim itself is sampled."""
    clips = world.GetInfo("clips") if world.HasInfo("clips") else {}
    out: dict = {}
    for clip_set in clips.values():
        asset = clip_set.get("manifestAssetPath")
        if asset is None or not asset.path:
            return None
        if asset.path not in manifests:
            manifests[asset.path] = Sdf.Layer.FindOrOpenRelativeToLayer(layer, asset.path)
        manifest = manifests[asset.path]
        spec = manifest.GetPrimAtPath(clip_set.get("primPath", str(world.path))) if manifest is not None else None
        if spec is None or spec.properties:
            return None
        for child in spec.nameChildren:
            if child.nameChildren:
                return None
            out.setdefault(child.name, set()).update(child.properties.keys())
    return out
