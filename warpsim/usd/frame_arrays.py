"""A scene's frame data as a function of its particle arrays: one description, one world or all.

A scene that can (``Scene.frame_arrays()``) describes each time-varying prim's per-frame keys
as arrays derived from the simulator's particle arrays::

    {"teapot": {"points": Particles("positions", slice(0, n)),
                "velocities": Particles("velocities", slice(0, n))},
     "springs": {"points": Particles("positions", slice(None))},
     "obstacle": {"points": Shared(obstacle.corners)}}

- :class:`Particles`: the ``positions`` or ``velocities`` of the particles ``index`` picks (None:
  the array itself, a ``wp.array`` in a lone run; a slice or an int array: those rows);
- :class:`PerWorld`: ``fn(x, v)`` of one world's positions and velocities (P, 3) (a scalar such
  as a kinetic energy);
- :class:`Shared`: ``fn()``, the same for every world of a batch (geometry moved by a host clock).

:func:`frame_data_from` gives one world's ``{prim: {key: value}}`` (what ``scene.frame_data()``
returns: a lone run, the viewer, the renderer and the exporter read that) and
:func:`batch_frame_data` every world's at once from the batch's (N, P, 3) host copies, each key
an array with a leading world axis (a list for :class:`PerWorld` values); a batch layer turns
that into samples with a few vectorised operations (:func:`world_samples`: extents by min/max
over each world's points) instead of asking the scene once per world.
"""
from __future__ import annotations

import os

import numpy as np

from .prims import CurvesDecl, JoinedPointsDecl, MeshDecl, PointsDecl, as_numpy, coerce

__all__ = ["Particles", "PerWorld", "Shared", "batch_frame_data", "described", "frame_data_from", "world_bounds",
           "world_extents", "world_samples"]

SOURCES = ("positions", "velocities")


class Particles:
    """A frame-data key that is rows of one of the particle arrays: ``source`` ("positions" or
    "velocities"), ``index`` (None: the whole array as the simulator holds it; a slice or an
    int array of particle indices within a world)."""

    __slots__ = ("source", "index")

    def __init__(self, source="positions", index=None):
        if source not in SOURCES:
            raise ValueError(f"Particles source {source!r} must be one of {SOURCES}")
        self.source = source
        self.index = index if index is None or isinstance(index, slice) else np.asarray(index, np.int64)

    def one(self, arrays, host):
        a = arrays[self.source]
        if self.index is None:
            return a
        if self.source not in host:
            host[self.source] = as_numpy(a)
        return host[self.source][self.index]

    def many(self, arrays, n):
        a = arrays[self.source]
        return a if self.index is None else a[:, self.index]


class PerWorld:
    """A frame-data key computed from one world's positions and velocities: ``fn(x, v)`` with
    ``x``, ``v`` NumPy (P, 3) float32 arrays (called once per world in a batch)."""

    __slots__ = ("fn",)

    def __init__(self, fn):
        self.fn = fn

    def one(self, arrays, host):
        for s in SOURCES:
            if s not in host:
                host[s] = as_numpy(arrays[s])
        return self.fn(host["positions"], host["velocities"])

    def many(self, arrays, n):
        x, v = arrays["positions"], arrays["velocities"]
        return [self.fn(x[w], v[w]) for w in range(n)]


class Shared:
    """A frame-data key that is the same for every world of a batch: ``fn()`` (e.g. an obstacle
    moved by the scene's clock), evaluated once a frame."""

    __slots__ = ("fn",)

    def __init__(self, fn):
        self.fn = fn

    def one(self, arrays, host):
        return self.fn()

    def many(self, arrays, n):
        value = self.fn()
        if isinstance(value, (int, float, str, bool)):
            return [value] * n
        a = as_numpy(value)
        return np.broadcast_to(a, (n,) + a.shape)


def frame_data_from(description, positions, velocities) -> dict:
    """One world's frame data ``{prim: {key: value}}`` from its ``description`` and its particle
    arrays (``wp.array`` or NumPy (P, 3)); the host copy of each array is made once."""
    arrays, host = {"positions": positions, "velocities": velocities}, {}
    return {prim: {key: spec.one(arrays, host) for key, spec in keys.items()} for prim, keys in description.items()}


def batch_frame_data(description, x, v) -> dict:
    """Every world's frame data at once: ``{prim: {key: (N, ...) array or list of N values}}``
    from the batch's host copies ``x``, ``v`` (N, P, 3)."""
    arrays, n = {"positions": x, "velocities": v}, len(x)
    return {prim: {key: spec.many(arrays, n) for key, spec in keys.items()} for prim, keys in description.items()}


def _definer(cls, name):
    return next((k for k in cls.__mro__ if name in vars(k)), None)


def described(scene):
    """``scene.frame_arrays()`` when its frame data is that description (None: its frame data is
    not a function of the particle arrays, or a subclass overrides ``frame_data`` without
    describing it: such a scene's worlds are asked one at a time)."""
    fn = getattr(scene, "frame_arrays", None)
    if fn is None:
        return None
    cls = type(scene)
    data_cls, arrays_cls = _definer(cls, "frame_data"), _definer(cls, "frame_arrays")
    if data_cls is None or arrays_cls is None or not issubclass(arrays_cls, data_cls):
        return None
    return fn()


# ---------------------------------------------------------------------- samples of every world
PARALLEL_BOUNDS = 1 << 20
"""Coordinates (N k 3) from which :func:`world_bounds` reduces blocks of worlds in threads."""
_BOUNDS_POOL: list = []


def _bounds_block(points, lo, hi, start, stop):
    for c in range(3):  # (NumPy's reductions release the GIL: blocks run side by side)
        points[start:stop, :, c].min(axis=1, out=lo[start:stop, c])
        points[start:stop, :, c].max(axis=1, out=hi[start:stop, c])


def world_bounds(points):
    """(lo, hi), each (N, 3) float32: the smallest and largest coordinates of each world's points
    (N, k, 3), k >= 1 (NaN where a world's points hold one). One component at a time: a
    reduction over the points' axis of the (N, k, 3) layout runs about 14x slower in NumPy.
    From :data:`PARALLEL_BOUNDS` coordinates on, blocks of worlds are reduced in threads (a
    minimum is exact: the same values whatever the blocks)."""
    n = points.shape[0]
    lo = np.empty((n, 3), points.dtype)
    hi = np.empty((n, 3), points.dtype)
    threads = min(8, os.cpu_count() or 1, n)
    if points.size < PARALLEL_BOUNDS or threads < 2:
        _bounds_block(points, lo, hi, 0, n)
        return lo, hi
    if not _BOUNDS_POOL:
        from concurrent.futures import ThreadPoolExecutor

        _BOUNDS_POOL.append(ThreadPoolExecutor(threads, thread_name_prefix="warpsim-bounds"))
    edges = np.linspace(0, n, threads + 1).astype(int)
    jobs = [_BOUNDS_POOL[0].submit(_bounds_block, points, lo, hi, a, b) for a, b in zip(edges[:-1], edges[1:]) if b > a]
    for job in jobs:
        job.result()
    return lo, hi


def world_extents(points, pad, bounds_out=None):
    """Bounds (N, 2, 3) float32 of each world's points (N, k, 3) float32 grown by ``pad`` (scalar
    or one per point): :func:`warpsim.usd.prims._extent` of every world, bit for bit.
    ``bounds_out``: a list that receives the points' own :func:`world_bounds` ``(lo, hi)`` where
    they were reduced on the way (a scalar pad), so a caller needing them reduces nothing twice."""
    n, k = points.shape[0], points.shape[1]
    out = np.zeros((n, 2, 3), np.float32)
    if k == 0:
        return out
    pad = np.asarray(pad, np.float32)
    if pad.ndim == 1:
        for c in range(3):
            out[:, 0, c] = (points[..., c] - pad[None, :]).min(axis=1)
            out[:, 1, c] = (points[..., c] + pad[None, :]).max(axis=1)
    else:
        lo, hi = world_bounds(points)
        out[:, 0] = lo - pad
        out[:, 1] = hi + pad
        if bounds_out is not None:
            bounds_out.append((lo, hi))
    return out


def _vector_form(decl):
    """(point keys, pad) when ``decl``'s samples can be made for all worlds at once, else None."""
    kind = type(decl)
    if kind in (PointsDecl, JoinedPointsDecl):
        if decl.count_changes or decl.dynamic_widths:
            return None
        return decl.pad
    if kind is MeshDecl:
        if decl.topology_changes or "points" not in decl.attrs or not decl.attrs["points"].dynamic:
            return None
        return 0.0
    if kind is CurvesDecl:
        return decl.pad
    return None


def _per_world(decl, values, frame, n):
    per = [decl.frame_samples({k: v[w] for k, v in values.items()}, frame) for w in range(n)]
    return {attr: [p[attr] for p in per] for attr in per[0]} if per else {}


def world_samples(decl, values, frame, n, bounds_out=None) -> dict:
    """The samples of prim ``decl`` for every world of a frame: ``{attribute: (N, ...) array or
    list}`` in the order :meth:`PrimDecl.frame_samples` gives them, equal to it world by world
    (``values``: this prim's entry of :func:`batch_frame_data`). Points, meshes with fixed
    topology and curves are made with vectorised operations; any other prim world by world.
    ``bounds_out``: a list that receives each world's bounds ``(lo, hi)`` (N, 3) of the sampled
    points when the extents were made from them (:func:`world_extents`)."""
    where = f"prim {decl.name!r} at frame {frame}"
    if values is None:
        raise ValueError(f"{where}: no data given; every time-varying prim needs data every frame")
    pad = _vector_form(decl)
    names = {decl.aliases.get(k, k): k for k in values}
    dynamic = [a for a in decl.dynamic_attrs() if not a.derived]
    if pad is None or set(names) != {a.name for a in dynamic} or len(names) != len(values):
        return _per_world(decl, values, frame, n)
    out: dict = {}
    for attr in dynamic:
        value = values[names[attr.name]]
        if attr.type_name in ("point3f[]", "vector3f[]"):
            a = value if isinstance(value, np.ndarray) else np.asarray(value)
            if a.ndim != 3 or a.shape[0] != n or a.shape[2] != 3:
                return _per_world(decl, values, frame, n)
            out[attr.name] = np.ascontiguousarray(a, dtype=np.float32)
        else:
            out[attr.name] = [coerce(attr.type_name, value[w], f"{where}, {attr.name!r}") for w in range(n)]
    points = out["points"]
    if isinstance(decl, CurvesDecl):
        if decl.gather is not None:
            if len(decl.gather) and decl.gather.max() >= points.shape[1]:
                return _per_world(decl, values, frame, n)  # its error names the indices
            for key in ("points", "velocities"):
                if key in out:
                    out[key] = out[key][:, decl.gather]
            points = out["points"]
        for key in ("points", "velocities"):
            if key in out and out[key].shape[1] != decl.vertex_count:
                return _per_world(decl, values, frame, n)
    k = points.shape[1]
    if "velocities" in out and out["velocities"].shape[1] != k:
        return _per_world(decl, values, frame, n)
    if isinstance(decl, (PointsDecl, MeshDecl)):
        decl._check_count(k, where, "points", True)
    if isinstance(decl, MeshDecl) and decl.index_max >= k:
        return _per_world(decl, values, frame, n)
    if isinstance(decl, JoinedPointsDecl) and decl.index_max >= k:
        return _per_world(decl, values, frame, n)
    extent = world_extents(points, pad, bounds_out)
    if not np.isfinite(extent).all():
        raise ValueError(f"{where}: points contain NaN or infinite values")
    out["extent"] = extent
    return out
