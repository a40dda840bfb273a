"""Reading triangle meshes from files: OBJ, STL, PLY, GLB/GLTF, OFF through trimesh, and USD
``Mesh`` prims through pxr (imported inside the loader only). Colliders (``TriangleMesh.from_file``)
and soft bodies both read meshes here, so neither imports the other for it."""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from . import meshtools
from ..core import checks

MESH_EXTENSIONS = (".obj", ".stl", ".ply", ".glb", ".gltf", ".off")
USD_EXTENSIONS = (".usd", ".usda", ".usdc")


def load_mesh(path, *, weld_tolerance: float = 1.0e-7) -> tuple[np.ndarray, np.ndarray]:
    """Read a triangle mesh: OBJ, STL, PLY, GLB/GLTF, OFF (trimesh; scenes are concatenated) or
    USD (first Mesh prim, see load_usd_mesh). Polygons are triangulated and vertices welded by
    position. Returns (points (V, 3) float64 [file units], faces (F, 3) int64)."""
    path = checks.existing_file(path, "mesh file")
    ext = os.path.splitext(path)[1].lower()
    weld_tolerance = checks.positive(weld_tolerance, "load_mesh weld_tolerance", fix="a fraction of the mesh size, "
                                     "e.g. 1e-7")
    if ext in USD_EXTENSIONS:
        points, faces = load_usd_mesh(path)
    elif ext in MESH_EXTENSIONS:
        import trimesh

        if os.path.getsize(path) == 0:
            raise ValueError(f"mesh file {path!r} is empty (0 bytes); export the mesh again")
        try:
            mesh: Any = trimesh.load(path, force="mesh", process=False)  # a Trimesh (force="mesh")
            points, faces = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)
        except (ImportError, MemoryError):
            raise
        except Exception as exc:  # noqa: BLE001  (trimesh raises anything from struct.error to KeyError)
            raise ValueError(f"mesh file {path!r} could not be read as {ext[1:].upper()} ({type(exc).__name__}: "
                             f"{str(exc)[:200]}); check that it is a valid, complete {ext[1:].upper()} file") from None
        if points.ndim != 2 or (points.size and points.shape[1] != 3) or faces.ndim != 2 or \
                (faces.size and faces.shape[1] != 3):
            raise ValueError(f"mesh file {path!r} holds no triangle mesh (vertices {points.shape}, faces "
                             f"{faces.shape}); export it as triangles or polygons")
    else:
        raise ValueError(f"mesh file {path!r}: unknown extension {ext!r}; supported: "
                         f"{', '.join(MESH_EXTENSIONS + USD_EXTENSIONS)}")
    if len(faces) == 0:
        raise ValueError(f"mesh file {path!r} holds no triangles; check that it is a complete, valid mesh file")
    points = checks.mesh_vertices(points, f"mesh file {path!r}")
    if faces.min() < 0 or faces.max() >= len(points):
        bad = int(faces.max() if faces.max() >= len(points) else faces.min())
        raise ValueError(f"mesh file {path!r}: a face uses vertex {bad} but the file has {len(points)} vertices; "
                         "repair the file")
    size = float(np.ptp(points, axis=0).max()) if len(points) else 1.0
    points, faces, _ = meshtools.weld(points, faces, tolerance=weld_tolerance * max(size, 1e-30))
    return points, faces


def triangulate(counts, indices) -> np.ndarray:
    """Fan-triangulate polygons given USD-style face vertex counts and indices, shape (F, 3)."""
    counts = np.asarray(counts, dtype=np.int64)
    indices = np.asarray(indices, dtype=np.int64)
    if np.any(counts < 3):
        bad = int(np.flatnonzero(counts < 3)[0])
        raise ValueError(f"polygon {bad} has {counts[bad]} vertices; faces need >= 3")
    if counts.sum() != len(indices):
        raise ValueError(f"face vertex counts sum to {counts.sum()} but there are {len(indices)} indices")
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    tris = [np.stack([np.full(c - 2, indices[s]), indices[s + 1:s + c - 1], indices[s + 2:s + c]], axis=1)
            for s, c in zip(starts, counts)]
    return np.concatenate(tris) if tris else np.zeros((0, 3), dtype=np.int64)


def load_usd_mesh(path, prim_path=None, time=None):
    """Points (in world space, at ``time``; default: the stage's default time) and triangles of
    a ``UsdGeom.Mesh``: ``prim_path`` or the first Mesh prim found. Left-handed meshes are
    re-wound to right-handed. ``pxr`` is imported here only."""
    try:
        from pxr import Usd, UsdGeom
    except ImportError as exc:  # pragma: no cover - usd-core is a dependency
        raise ImportError("loading USD meshes needs usd-core: pip install usd-core") from exc
    path = checks.existing_file(path, "USD file")
    try:
        stage = Usd.Stage.Open(path)
    except Exception as exc:  # noqa: BLE001  (pxr raises Tf.ErrorException)
        raise ValueError(f"USD file {path!r} does not open ({str(exc).strip().splitlines()[-1][:200]}); check that "
                         "it is a valid, complete USD file") from None
    if stage is None:
        raise ValueError(f"cannot open USD stage {path!r}; check that it is a valid, complete USD file")
    if prim_path is not None:
        prim = stage.GetPrimAtPath(prim_path)
        if not prim or not prim.IsA(UsdGeom.Mesh):
            raise ValueError(f"{path!r} has no Mesh prim at {prim_path!r}")
    else:
        prim = next((p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)), None)
        if prim is None:
            raise ValueError(f"{path!r} holds no UsdGeom.Mesh prim")
    t = Usd.TimeCode.Default() if time is None else Usd.TimeCode(time)
    mesh = UsdGeom.Mesh(prim)
    points = np.asarray(mesh.GetPointsAttr().Get(t), dtype=np.float64).reshape(-1, 3)
    counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get(t), dtype=np.int64)
    indices = np.asarray(mesh.GetFaceVertexIndicesAttr().Get(t), dtype=np.int64)
    faces = triangulate(counts, indices)
    if mesh.GetOrientationAttr().Get() == UsdGeom.Tokens.leftHanded:
        faces = faces[:, ::-1]
    xf = np.asarray(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(t), dtype=np.float64)
    points = points @ xf[:3, :3] + xf[3, :3]  # USD matrices act on row vectors
    return points, faces
