"""One frame of a USD cache as geometry files other tools read: ``.obj``, ``.ply``, ``.stl`` and
``.glb`` (through trimesh; line sets in ``.obj`` are written here, trimesh has no OBJ line writer).

    export_frame("usd_out/dam_break.usda", "splash.obj", frame=60, surface=True)

What becomes what (world space, metres; ``up``: the file's up axis, by default the format's
convention, ``UP_AXIS``: Z for ``.ply`` and ``.stl``, which Blender and most mesh tools read as
Z-up, Y for ``.obj`` and ``.glb``, whose readers turn Y-up into their own; warpsim's caches are
Y-up, so a Z-up file holds (x, -z, y), a proper rotation that keeps the winding):

- ``Mesh`` prims: triangle meshes (polygons fan-triangulated); ``Cube``, ``Cone``, ``Sphere``,
  ``Capsule`` and ``Cylinder`` (colliders) are tessellated; a ``PointInstancer`` becomes its
  instances' prototype meshes (spheres and capsules tessellated).
- ``Points`` prims: a point cloud, or with ``surface=True`` a closed marching-cubes surface of the
  particles (Zhu-Bridson field on a grid of about the particle spacing, Warp kernels). In ``.obj`` a
  point cloud is its ``v`` lines alone: Blender's OBJ importer reads a file without faces or lines
  as a point cloud and warns once per line at ``p`` elements, so points are never merged into an
  ``.obj`` with meshes or curves (refused: write them to their own file, ``.ply`` or ``.glb``).
- ``BasisCurves`` prims: line sets (one segment per pair of consecutive curve vertices). A format
  that holds no lines (``.stl``) leaves curves out with a note (``export_frame``'s ``notes``).

``prims`` chooses prims by name (default: every drawn prim).

Prims are read as USD tools draw them: purpose ``default`` or ``render`` (``guide`` prims only
with ``guides=True``), not invisible. Without ``merge`` each prim goes to its own file
``OUT-STEM_PRIM.SUFFIX``; with ``merge`` all go to ``OUT`` (``.glb`` and ``.obj`` hold every kind
together; ``.ply`` and ``.stl`` hold one kind: triangles, or for ``.ply`` one point cloud or one line
set). STL holds triangles only, so points need ``surface=True`` there.
Every mistake (a frame outside the cache, a cache with nothing to export, an unknown suffix or prim
name, a kind the format cannot hold) is a ``ValueError`` raised before any file is written.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from ..core.safe_files import open_temporary
from ..usd.prims import segment_pairs
from ..usd.validate import frame_codes, open_stage
from .geometry import cone_mesh, cube_mesh, triangulate

__all__ = ["FORMATS", "UP_AXIS", "ExportPart", "export_frame", "file_vertex_count", "read_frame",
           "surface_from_points", "write_parts"]

FORMATS = {
    ".obj": ("mesh", "points", "curves"),
    ".ply": ("mesh", "points", "curves"),
    ".stl": ("mesh",),
    ".glb": ("mesh", "points", "curves"),
}
"""Suffix -> the kinds of geometry it holds."""

UP_AXIS = {".obj": "y", ".ply": "z", ".stl": "z", ".glb": "y"}
"""Suffix -> the up axis its readers assume (Blender: PLY and STL are read as they are, Z-up; its
OBJ and glTF importers turn Y-up files Z-up)."""

EXPORTED_PURPOSES = ("default", "render")


@dataclass
class ExportPart:
    """One prim's geometry at one frame, in world space.

    Attributes:
        name: the prim's name (its path with ``_`` for ``/`` where two prims share a name).
        kind: ``"mesh"``, ``"points"`` or ``"curves"``.
        vertices: positions [m], shape (V, 3), float64.
        faces: triangles (mesh), shape (F, 3), int64 indices into ``vertices``.
        segments: line segments (curves), shape (S, 2), int64 indices into ``vertices``.
        color: display colour in [0, 1]: None, (3,) or per vertex (V, 3).
        widths: point diameters [m] (points), shape (V,) or (1,), or None.
        opacity: constant opacity in [0, 1] (the prim's ``primvars:displayOpacity``; 1: opaque).
    """

    name: str
    kind: str
    vertices: np.ndarray
    faces: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.int64))
    segments: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.int64))
    color: Optional[np.ndarray] = None
    widths: Optional[np.ndarray] = None
    opacity: float = 1.0


# ---------------------------------------------------------------------------------------- reading
def _np(value, dtype=np.float64):
    return np.zeros(0, dtype) if value is None else np.asarray(value, dtype)


def _apply(m, p):
    """Row-vector USD transform ``m`` (4, 4) applied to points (n, 3)."""
    return p @ m[:3, :3] + m[3, :3]


def _quat_rotate(q, v):
    """Rotate vectors v (n, 3) by unit quaternions q (n, 4) stored (x, y, z, w)."""
    xyz, w = q[:, :3], q[:, 3:4]
    t = 2.0 * np.cross(xyz, v)
    return v + w * t + np.cross(xyz, t)


def up_rotation(source: str, target: str) -> np.ndarray:
    """Rotation (3, 3), row-vector convention (``p @ R``), from a ``source``-up to a ``target``-up
    frame ("y" or "z"): Y-up to Z-up takes (x, y, z) to (x, -z, y), +90 degrees about +X."""
    source, target = source.lower(), target.lower()
    if source == target:
        return np.eye(3)
    y_to_z = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
    return y_to_z if (source, target) == ("y", "z") else y_to_z.T


def _axis_rotation(axis: str) -> np.ndarray:
    """Rotation (3, 3), row-vector convention, taking +Z to the USD ``axis`` ("X", "Y" or "Z")."""
    perm = {"X": [2, 0, 1], "Y": [1, 2, 0], "Z": [0, 1, 2]}[axis]
    return np.eye(3)[:, perm]


def _shape_mesh(prim, t):
    """(points (V, 3), triangles (F, 3)) of a Mesh/Cube/Cone/Sphere/Capsule/Cylinder prim in its
    own space, or None for other types."""
    import trimesh
    from pxr import UsdGeom

    kind = prim.GetTypeName()
    get = prim.GetAttribute
    if kind == "Mesh":
        mesh = UsdGeom.Mesh(prim)
        pts = _np(mesh.GetPointsAttr().Get(t))
        counts = _np(mesh.GetFaceVertexCountsAttr().Get(t), np.int64)
        idx = _np(mesh.GetFaceVertexIndicesAttr().Get(t), np.int64)
        tris = triangulate(counts, idx)[0]
        if mesh.GetOrientationAttr().Get() == UsdGeom.Tokens.leftHanded:
            tris = tris[:, ::-1]
        return pts, tris.astype(np.int64)
    if kind == "Cube":
        pts, counts, idx = cube_mesh(get("size").Get(t) or 2.0)
        return np.asarray(pts, np.float64), triangulate(counts, idx)[0]
    if kind == "Cone":
        pts, counts, idx = cone_mesh(get("radius").Get(t) or 1.0, get("height").Get(t) or 2.0,
                                     str(get("axis").Get(t) or "Z"))
        return np.asarray(pts, np.float64), np.asarray(idx, np.int64).reshape(-1, 3)
    if kind == "Sphere":
        s = trimesh.creation.icosphere(subdivisions=3, radius=float(get("radius").Get(t) or 1.0))
        return np.asarray(s.vertices), np.asarray(s.faces, np.int64)
    if kind in ("Capsule", "Cylinder"):
        r = float(get("radius").Get(t) or (0.5 if kind == "Capsule" else 1.0))
        h = float(get("height").Get(t) or (1.0 if kind == "Capsule" else 2.0))
        s = (trimesh.creation.capsule(height=h, radius=r, count=[16, 16]) if kind == "Capsule"
             else trimesh.creation.cylinder(radius=r, height=h, sections=24))
        return np.asarray(s.vertices) @ _axis_rotation(str(get("axis").Get(t) or "Z")), np.asarray(s.faces, np.int64)
    return None


def _color(prim, t, count):
    """Constant (3,) or per-vertex (count, 3) displayColor, else None."""
    from pxr import UsdGeom

    pv = UsdGeom.PrimvarsAPI(prim).GetPrimvar("displayColor")
    if not (pv and pv.HasValue()):
        return None
    value = pv.ComputeFlattened(t)
    if value is None or not len(value):
        return None
    c = np.clip(np.asarray(value, np.float64).reshape(-1, 3), 0.0, 1.0)
    return c[0] if len(c) == 1 else (c if len(c) == count else None)


def _opacity(prim, t) -> float:
    """The constant ``displayOpacity`` of ``prim`` in [0, 1] (e.g. the walls' 0.2), else 1."""
    from pxr import UsdGeom

    pv = UsdGeom.PrimvarsAPI(prim).GetPrimvar("displayOpacity")
    value = pv.Get(t) if pv and pv.HasValue() and pv.GetInterpolation() == UsdGeom.Tokens.constant else None
    return float(np.clip(value[0], 0.0, 1.0)) if value is not None and len(value) == 1 else 1.0


def _instancer_mesh(prim, t):
    """Every instance of a PointInstancer as its prototype's triangles, world-independent
    (instancer space); (points, triangles) or None when it has no mesh-like prototype."""
    from pxr import UsdGeom

    inst = UsdGeom.PointInstancer(prim)
    pos = _np(inst.GetPositionsAttr().Get(t)).reshape(-1, 3)
    n = len(pos)
    if n == 0:
        return None
    q = _np(inst.GetOrientationsAttr().Get(t)).reshape(-1, 4) if inst.GetOrientationsAttr().HasValue() else None
    q = q if q is not None and len(q) == n else np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))
    scales = _np(inst.GetScalesAttr().Get(t)).reshape(-1, 3) if inst.GetScalesAttr().HasValue() else None
    scale = scales if scales is not None and len(scales) == n else np.ones((n, 3))
    proto = _np(inst.GetProtoIndicesAttr().Get(t), np.int64)
    proto = proto if len(proto) == n else np.zeros(n, np.int64)
    stage = prim.GetStage()
    points, tris, offset = [], [], 0
    for k, target in enumerate(inst.GetPrototypesRel().GetTargets()):
        sel = np.flatnonzero(proto == k)
        shape = _shape_mesh(stage.GetPrimAtPath(target), t) if len(sel) else None
        if shape is None:
            continue
        lp, lt = shape
        v = len(lp)
        world = (_quat_rotate(np.repeat(q[sel], v, 0), np.tile(lp, (len(sel), 1)) * np.repeat(scale[sel], v, 0))
                 + np.repeat(pos[sel], v, 0))
        points.append(world)
        tris.append((lt[None, :, :] + (offset + v * np.arange(len(sel)))[:, None, None]).reshape(-1, 3))
        offset += len(world)
    if not points:
        return None
    return np.concatenate(points), np.concatenate(tris)


def frame_range_text(frames) -> str:
    return f"frames {frames[0]}..{frames[-1]}" if frames else "no time samples (a static file)"


def read_frame(cache, frame=None, guides=False, up=None) -> tuple:
    """(frame, [ExportPart, ...]) of ``cache`` at ``frame`` (None: the last frame), turned to ``up``
    ("y" or "z"; None: the cache's own up axis). ValueError when the frame is outside the cache or
    nothing is there to export."""
    from pxr import Usd, UsdGeom

    stage = open_stage(cache)
    frames = frame_codes(stage)
    if frame is None:
        frame = frames[-1] if frames else None
    elif not frames or not (frames[0] <= int(frame) <= frames[-1]) or int(frame) != frame:
        raise ValueError(f"--frame {frame}: cache {str(cache)!r} has {frame_range_text(frames)}; "
                         f"pick a frame in that range")
    t = Usd.TimeCode.Default() if frame is None else Usd.TimeCode(float(frame))
    purposes = EXPORTED_PURPOSES + (("guide",) if guides else ())
    xf = UsdGeom.XformCache(t)
    turn = up_rotation(str(UsdGeom.GetStageUpAxis(stage)), up) if up else np.eye(3)
    skip, parts, names = set(), [], {}
    for prim in stage.Traverse():
        if prim.IsA(UsdGeom.PointInstancer):
            skip.update(str(p) for p in UsdGeom.PointInstancer(prim).GetPrototypesRel().GetTargets())
    it = iter(Usd.PrimRange(stage.GetPseudoRoot()))
    for prim in it:
        if str(prim.GetPath()) in skip:
            it.PruneChildren()
            continue
        if not (prim.IsA(UsdGeom.Gprim) or prim.IsA(UsdGeom.PointInstancer)):
            continue
        img = UsdGeom.Imageable(prim)
        if img.ComputePurpose() not in purposes or img.ComputeVisibility(t) == UsdGeom.Tokens.invisible:
            continue
        m = np.asarray(xf.GetLocalToWorldTransform(prim), np.float64)
        m = np.hstack([m[:, :3] @ turn, m[:, 3:]])  # world space turned to the file's up axis
        kind = prim.GetTypeName()
        part = None
        pairs = segment_pairs(prim)  # a sweep's springs: curves between its points (line segments)
        if kind == "Points" and pairs is not None:
            pts = _np(UsdGeom.Points(prim).GetPointsAttr().Get(t)).reshape(-1, 3)
            if len(pts) and len(pairs) and pairs.max() < len(pts):
                part = ExportPart(prim.GetName(), "curves", _apply(m, pts), segments=pairs,
                                  color=_color(prim, t, len(pts)))
        elif kind == "Points":
            pts = _np(UsdGeom.Points(prim).GetPointsAttr().Get(t)).reshape(-1, 3)
            if len(pts):
                widths = _np(UsdGeom.Points(prim).GetWidthsAttr().Get(t))
                part = ExportPart(prim.GetName(), "points", _apply(m, pts), color=_color(prim, t, len(pts)),
                                  widths=widths * (float(np.cbrt(abs(np.linalg.det(m[:3, :3])))) or 1.0))
        elif kind == "BasisCurves":
            curves = UsdGeom.BasisCurves(prim)
            pts = _np(curves.GetPointsAttr().Get(t)).reshape(-1, 3)
            counts = _np(curves.GetCurveVertexCountsAttr().Get(t), np.int64)
            if len(pts) and len(counts) and counts.sum() == len(pts):
                starts = np.ones(len(pts), bool)
                starts[np.cumsum(counts) - 1] = False  # a curve's last vertex starts no segment
                i = np.flatnonzero(starts)
                part = ExportPart(prim.GetName(), "curves", _apply(m, pts), segments=np.stack([i, i + 1], 1),
                                  color=_color(prim, t, len(pts)))
        else:
            shape = _instancer_mesh(prim, t) if kind == "PointInstancer" else _shape_mesh(prim, t)
            if shape is not None and len(shape[0]) and len(shape[1]):
                part = ExportPart(prim.GetName(), "mesh", _apply(m, shape[0]), faces=shape[1],
                                  color=_color(prim, t, len(shape[0])) if kind != "PointInstancer" else None)
        if part is not None:
            part.opacity = _opacity(prim, t)
            if part.name in names:  # two prims of one name (e.g. under different parents): use the path
                part.name = str(prim.GetPath()).strip("/").replace("/", "_")
            names[part.name] = part
            parts.append(part)
    if not parts:
        raise ValueError(f"cache {str(cache)!r} holds nothing to export at frame {frame} (no drawn mesh, points or "
                         "curves" + ("" if guides else "; guide prims are skipped without --guides") + ")")
    return frame, parts


# ---------------------------------------------------------------------------------------- surfaces
def _spacing(points, widths) -> float:
    """Particle spacing [m]: the median width when the cache has one per point (or one for all),
    else the median nearest-neighbour distance of up to 2,000 points."""
    if widths is not None and len(widths) and np.median(widths) > 0.0:
        return float(np.median(widths))
    sample = points[:: max(1, len(points) // 2000)]
    if len(sample) < 2:
        return 0.01
    d = np.linalg.norm(sample[:, None, :] - sample[None, :, :], axis=2)
    np.fill_diagonal(d, np.inf)
    return float(np.median(d.min(1)))


def surface_from_points(points, spacing=None, device=None, widths=None) -> tuple:
    """A closed surface around particles: (vertices (V, 3), triangles (F, 3)). The Zhu-Bridson field
    of :class:`warpsim.particle_fluids.surface.FluidSurface` on a grid of ``spacing`` [m] (default:
    from the particles' widths or their nearest-neighbour distance) over the particles' bounds
    padded by 3 spacings, meshed by warpsim's marching cubes."""
    import types

    import warp as wp

    from ..particle_fluids.surface import FluidSurface

    points = np.asarray(points, np.float64).reshape(-1, 3)
    s = _spacing(points, widths) if spacing is None else float(spacing)
    if not (np.isfinite(s) and s > 0.0):
        raise ValueError(f"surface spacing must be > 0 [m], got {s}")
    lo, hi = points.min(0) - 3.0 * s, points.max(0) + 3.0 * s
    cells = np.prod(np.ceil((hi - lo) / s) + 1)
    if cells > 256 ** 3:
        raise ValueError(f"a surface grid of spacing {s:g} m over the particles' bounds {np.round(hi - lo, 3)} m "
                         f"needs {cells:.3g} nodes (at most {256 ** 3:.3g}); give a coarser --spacing (e.g. "
                         f"--spacing {s * (cells / 256 ** 3) ** (1 / 3) * 1.05:.3g}) or export without --surface")
    dev = wp.get_device(device)
    fluid = types.SimpleNamespace(spacing=s, domain=(lo, hi), device=dev,
                                  positions=wp.array(points.astype(np.float32), dtype=wp.vec3, device=dev))
    vertices, faces, _ = FluidSurface(fluid).mesh().numpy()
    return np.asarray(vertices, np.float64), np.asarray(faces, np.int64).reshape(-1, 3)


# ---------------------------------------------------------------------------------------- writing
def _rgba(color, count, opacity=1.0):
    if color is None:
        return None
    c = np.asarray(color, np.float64).reshape(-1, 3)
    c = np.repeat(c, count, 0) if len(c) == 1 else c
    return np.hstack([np.round(c * 255), np.full((len(c), 1), np.round(opacity * 255))]).astype(np.uint8)


def _trimesh_geometry(part):
    import trimesh

    colors = _rgba(part.color, len(part.vertices), part.opacity)
    if part.kind == "mesh":
        return trimesh.Trimesh(part.vertices, part.faces, vertex_colors=colors, process=False)
    if part.kind == "points":
        return trimesh.PointCloud(part.vertices, colors=colors)
    entities = [trimesh.path.entities.Line(seg) for seg in part.segments]
    return trimesh.path.Path3D(entities=entities, vertices=part.vertices, process=False)


def _blended(part, colors):
    """glTF look of a see-through mesh part (opacity < 1): a material of its colour with alpha =
    opacity, ``alphaMode`` BLEND and double-sided: Blender's glTF importer makes it a blended
    material whose viewport colour (Solid view) carries the alpha, and glTF viewers draw it
    see-through (vertex alpha alone they ignore). Per-vertex colours, if any, stay ``COLOR_0``
    (Blender's Solid view then shows them opaque: a constant colour is written as the material's)."""
    from trimesh.visual import TextureVisuals
    from trimesh.visual.material import PBRMaterial

    c = np.asarray(part.color, np.float64).reshape(-1) if part.color is not None else np.ones(3)
    rgb = c if c.shape == (3,) else np.ones(3)  # per-vertex colours: white, COLOR_0 carries them
    material = PBRMaterial(name=f"{part.name}_material", baseColorFactor=[*rgb, part.opacity], alphaMode="BLEND",
                           doubleSided=True, metallicFactor=0.0, roughnessFactor=0.6)
    visual = TextureVisuals(material=material)
    if colors is not None and c.shape != (3,):
        visual.vertex_attributes["color"] = colors
    return visual


def file_vertex_count(part, suffix) -> int:
    """How many vertices the file ``suffix`` holds for ``part``: trimesh writes a line set to
    ``.ply`` and ``.glb`` as the two ends of every segment; ``.obj`` and every other kind hold
    the part's vertices."""
    if part.kind == "curves" and suffix in (".ply", ".glb"):
        return 2 * len(part.segments)
    return len(part.vertices)


def _obj_text(parts) -> str:
    """Wavefront OBJ with one object per part: ``f`` for triangles, ``l`` for line segments (1-based
    indices); a point cloud is its ``v`` lines alone (what Blender's importer reads as points)."""
    lines, base = ["# warpsim export"], 1
    for part in parts:
        lines.append(f"o {part.name}")
        lines.extend(f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in part.vertices)
        if part.kind == "mesh":
            lines.extend(f"f {a + base} {b + base} {c + base}" for a, b, c in part.faces)
        elif part.kind == "curves":
            lines.extend(f"l {a + base} {b + base}" for a, b in part.segments)
        base += len(part.vertices)
    return "\n".join(lines) + "\n"


def _merge_same_kind(parts, name):
    """One part of the parts' common kind (vertices concatenated, indices offset)."""
    offsets = np.cumsum([0] + [len(p.vertices) for p in parts[:-1]])
    colors = [p.color for p in parts]
    color = None
    if all(c is not None for c in colors):
        color = np.concatenate([np.broadcast_to(np.asarray(c).reshape(-1, 3), (len(p.vertices), 3))
                                for p, c in zip(parts, colors)])
    return ExportPart(name, parts[0].kind, np.concatenate([p.vertices for p in parts]),
                      faces=np.concatenate([p.faces + o for p, o in zip(parts, offsets)]),
                      segments=np.concatenate([p.segments + o for p, o in zip(parts, offsets)]), color=color)


def _write_one(parts, path, suffix):
    """Write ``parts`` (one, or several for a merged .obj/.glb) to ``path``."""
    import trimesh

    tmp = f"{path}.tmp-{os.getpid()}{suffix}"
    try:
        if suffix == ".obj":
            with open_temporary(tmp) as f:
                f.write(_obj_text(parts))
        elif suffix == ".glb":
            scene = trimesh.Scene()
            for part in parts:
                geometry = _trimesh_geometry(part)
                if part.kind == "mesh" and part.opacity < 1.0:
                    geometry.visual = _blended(part, _rgba(part.color, len(part.vertices), part.opacity))
                scene.add_geometry(geometry, node_name=part.name, geom_name=part.name)
            with open_temporary(tmp, "wb") as f:
                f.write(scene.export(file_type="glb"))
        else:
            (part,) = parts
            data = _trimesh_geometry(part).export(file_type=suffix[1:])
            with open_temporary(tmp, "wb" if isinstance(data, bytes) else "w") as f:
                f.write(data)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


def _plan(parts, out, merge):
    """[(path, [parts])] to write; ValueError for what the format cannot hold."""
    suffix = os.path.splitext(out)[1].lower()
    if suffix not in FORMATS:
        raise ValueError(f"--out {out!r}: unknown suffix {suffix or '(none)'!r}; write one of "
                         f"{', '.join(FORMATS)}")
    held = FORMATS[suffix]
    for part in parts:
        if part.kind not in held:
            fix = "pass --surface to mesh the particles, or " if part.kind == "points" else ""
            raise ValueError(f"prim {part.name!r} is {part.kind} and {suffix} holds triangles only; "
                             f"{fix}write .obj, .ply or .glb")
    if not merge:
        stem = os.path.splitext(out)[0]
        if len(parts) == 1:
            return [(out, parts)]
        return [(f"{stem}_{part.name}{suffix}", [part]) for part in parts]
    kinds = sorted({p.kind for p in parts})
    if suffix == ".obj" and "points" in kinds and len(kinds) > 1:
        points = [p.name for p in parts if p.kind == "points"]
        others = " and ".join(k for k in kinds if k != "points")
        raise ValueError(f"--merge into .obj: points {', '.join(map(repr, points))} with {others}: "
                         "an OBJ reader (Blender's) takes the points of a file without faces or lines only; leave out "
                         "--merge (one file per prim), pass --surface, or merge into .glb")
    if suffix in (".obj", ".glb"):
        return [(out, parts)]
    if len(kinds) > 1:
        raise ValueError(f"--merge into {suffix}: the frame holds {' and '.join(kinds)} and a {suffix} file one kind; "
                         "choose prims of one kind with --prims, merge into .obj or .glb, or leave out --merge (one "
                         "file per prim)")
    return [(out, [_merge_same_kind(parts, os.path.splitext(os.path.basename(out))[0])])]


def write_parts(parts, out, merge=False) -> list:
    """Write ``parts`` to ``out`` (one file per part unless ``merge``); returns the paths written.
    Every check runs before the first file is written."""
    plan = _plan(parts, out, merge)
    folder = os.path.dirname(os.path.abspath(out))
    os.makedirs(folder, exist_ok=True)
    suffix = os.path.splitext(out)[1].lower()
    for path, group in plan:
        _write_one(group, path, suffix)
    return [path for path, _ in plan]


def export_frame(cache, out, frame=None, *, surface=False, merge=False, guides=False, spacing=None,
                 device=None, allow_damaged=False, up=None, prims=None) -> dict:
    """Export frame ``frame`` (None: the last) of ``cache`` to ``out`` (see the module docstring):
    ``up`` "y" or "z" (None: ``UP_AXIS`` of the suffix), ``prims`` prim names (None: every drawn
    prim). Returns {"frame", "paths", "parts": [(name, kind, vertex count as the file holds them
    (:func:`file_vertex_count`), face or segment count)],
    "notes": [one line per thing left out]}."""
    if frame is not None and (isinstance(frame, bool) or not hasattr(frame, "__index__")):
        raise TypeError(f"frame {frame!r} is not a whole frame number; give e.g. frame=10 (None: the last)")
    if not isinstance(out, (str, os.PathLike)):
        raise TypeError(f"out {out!r} is not a path; give e.g. 'frame.obj'")
    suffix = os.path.splitext(str(out))[1].lower()
    if suffix not in FORMATS:  # before the cache is read
        raise ValueError(f"--out {str(out)!r}: unknown suffix {suffix or '(none)'!r}; write one of "
                         f"{', '.join(FORMATS)}")
    if up is not None and str(up).lower() not in ("y", "z"):
        raise ValueError(f"--up {up!r}: give y or z (default for {suffix}: {UP_AXIS[suffix]})")
    if prims is not None and (isinstance(prims, str) or not all(isinstance(n, str) and n for n in prims)):
        raise ValueError(f"prims {prims!r}: give a list of prim names, e.g. ['teapot']")
    up = str(up or UP_AXIS[suffix]).lower()
    from ..usd.family import check_output
    from ..usd.lock import OutputLock
    from ..usd.validate import check_damage

    check_output(out, [cache], "--out")
    if isinstance(cache, (str, os.PathLike)) and os.path.isfile(cache):
        bad = check_damage(cache, allow_damaged, what="export")  # like render: a lost chunk is said, not skipped
        if bad and frame is None:
            frame = max(f for f in _readable_frames(cache) if f not in bad)
        elif frame is not None and int(frame) in bad:
            raise ValueError(f"--frame {frame} lies in a damaged chunk file of {os.fspath(cache)!r}; export a readable "
                             "frame, or restore the file")
    with OutputLock(out, "--out"):
        return _export(cache, out, frame, surface, merge, guides, spacing, device, up, prims)


def _readable_frames(cache):
    return frame_codes(open_stage(cache))


def _chosen(parts, prims, frame):
    """``parts`` of the names in ``prims`` (None: all); ValueError naming an unknown one."""
    if prims is None:
        return parts
    have = {p.name: p for p in parts}
    unknown = [n for n in prims if n not in have]
    if unknown:
        raise ValueError(f"--prims {','.join(unknown)}: frame {frame} has no drawn prim of that name; its prims: "
                         f"{', '.join(have)}")
    return [have[n] for n in dict.fromkeys(prims)]


def _without_curves(parts, suffix):
    """(parts, notes): curves left out of a format that holds no lines, with a one-line note."""
    if "curves" in FORMATS[suffix]:
        return parts, []
    curves = [p.name for p in parts if p.kind == "curves"]
    if not curves or len(curves) == len(parts):  # nothing but curves: _plan says why it cannot write them
        return parts, []
    return ([p for p in parts if p.kind != "curves"],
            [f"note: left out curves {', '.join(curves)} ({suffix} holds triangles only; write .obj, .ply or .glb "
             "for them)"])


def _export(cache, out, frame, surface, merge, guides, spacing, device, up="y", prims=None) -> dict:
    frame, parts = read_frame(cache, frame, guides, up)
    if prims is not None and not guides and any(n not in {p.name for p in parts} for n in prims):
        _, every = read_frame(cache, frame, True, up)  # a guide prim named without --guides: say so
        guide = [n for n in prims if n in {p.name for p in every} - {p.name for p in parts}]
        if guide:
            raise ValueError(f"--prims {','.join(guide)}: {'it is a guide prim' if len(guide) == 1 else 'they are guide prims'}"
                             f" (a helper, left out by default); add --guides to export it")
    parts, notes = _without_curves(_chosen(parts, prims, frame), os.path.splitext(str(out))[1].lower())
    if surface:
        meshed = []
        for part in parts:
            if part.kind == "points":
                v, f = surface_from_points(part.vertices, spacing, device, part.widths)
                if len(f) == 0:
                    raise ValueError(f"prim {part.name!r}: the particle surface at frame {frame} is empty")
                c = part.color if part.color is None or np.asarray(part.color).ndim == 1 else None
                part = ExportPart(part.name, "mesh", v, faces=f, color=c)
            meshed.append(part)
        parts = meshed
    paths = write_parts(parts, str(out), merge)
    suffix = os.path.splitext(str(out))[1].lower()
    summary = [(p.name, p.kind, file_vertex_count(p, suffix), len(p.faces) if p.kind == "mesh" else
                len(p.segments) if p.kind == "curves" else 0) for p in parts]
    return {"frame": frame, "paths": paths, "parts": summary, "notes": notes}
