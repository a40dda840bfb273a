"""USD output of many worlds: the batch layers (the root over them: :mod:`warpsim.browse.roots`).

Batch layer (one per batch, ``.usdc``): every world of the batch under
``/Worlds/world_GGGGGG`` (G: the world's global index), holding the scene's own prims (declared
once by ``scene.declare`` on a :class:`warpsim.usd.writer.UsdCacheWriter`, never described twice)
with a time sample per frame. ``customLayerData["warpsim"]`` records ``firstWorld``,
``worldCount``, ``scene``, ``span`` (the largest extent of a world [m], for galleries) and ``lo`` /
``hi`` (the corners of the worlds' extent [m]: a root over several layers spans their union).

Written once, not per world or frame: every prim's declaration (topology, widths, colours,
materials) lives in the class prim ``/WorldShared/NAME``, which each world's ``NAME`` inherits;
curves between particles (``add_curves(name, indices)``, e.g. springs) are written as a ``Points``
prim of the particles' positions with the index pairs once (:class:`warpsim.usd.prims.JoinedPointsDecl`;
the viewer, gallery, renderer and exporter draw the curves from the points, and a world re-run
alone writes them as curves). A 16-teapot x 60-frame sweep writes 18 MB instead of 133 MB.
:func:`estimate_sweep_bytes` says how much a sweep will write before it starts.

``pxr`` is imported lazily.
"""
from __future__ import annotations

import operator
import os

import numpy as np

from ..browse.roots import world_prim_name
from ..usd.frame_arrays import world_bounds
from ..usd.prims import joined_form
from ..usd.writer import UsdCacheWriter

__all__ = ["BatchLayerWriter", "auto_chunk_frames", "chunk_writers", "estimate_sweep_bytes", "stored_frames",
           "world_frame_bytes"]

SHARED = "/WorldShared"
"""Class prim of a batch layer holding the declarations every world's prims inherit."""
SAMPLE_OVERHEAD = 24
"""Bytes a time sample costs in a chunk besides its values (its time and value record; measured:
about 23 B a sample in a teapot sweep's chunks)."""
WORLD_SPEC_BYTES = 1024
"""Bytes a world costs in the layer besides its samples: its prim specs, parameters and clip list."""


def stored_frames(frames, store_every=1) -> int:
    """How many of ``frames`` frames (frame 0 included) a sweep's layers hold with ``store_every``
    (``run_batch``: 1 every frame, k > 1 every k-th and the last, 0 none kept)."""
    frames, k = int(frames), int(store_every)
    if frames <= 0 or k == 0:
        return 0
    return len(range(0, frames, k)) + (1 if (frames - 1) % k else 0)


def estimate_sweep_bytes(scene, layer_path, worlds, frames, fps=60.0, store_every=1) -> dict:
    """Bytes a sweep of ``worlds`` worlds like ``scene`` (world 0, built) writes over ``frames``
    frames (frame 0 included) into its batch layers: ``{"bytes", "frame_bytes", "frames"}`` (the
    whole sweep, one world's frame, the frames kept), from the prims the layer writes and world 0's
    first frame (counts that change later, as fluids', make it an estimate of the first frame's
    rate). ``store_every``: as ``run_batch`` takes it (``--store``: 1 all, k preview, 0 none: no
    layer is kept)."""
    writer = BatchLayerWriter(layer_path, scene, 0, int(worlds), fps)  # declares only: nothing is written
    per = writer.frame_bytes(scene.frame_data())
    kept = stored_frames(frames, store_every)
    static = writer.static_bytes() if int(store_every) else 0
    return {"bytes": int(worlds) * kept * per + static, "frame_bytes": per, "frames": kept}


POOL_CHUNK_BYTES = 8 << 20
"""A sweep whose chunk files hold at least this many bytes [bytes] has worker processes author
them (:func:`chunk_writers`); smaller ones are written faster than a worker starts."""
AUTO_CHUNK_BYTES = 128 << 20
"""The most bytes [bytes] an automatic chunk holds (:func:`auto_chunk_frames`): many worlds'
frames are cut into several chunks, which worker processes author side by side."""
MAX_CHUNK_FRAMES = 24
"""Frames an automatic chunk holds at most (a lone run's default ``chunk_size``)."""


def world_frame_bytes(writer, batch) -> int:
    """Bytes one frame of every world of ``batch`` adds to ``writer``'s chunks [bytes] (from world 0's
    frame data now: counts that change later, as fluids', make it the first frame's rate)."""
    x, v = batch.world_slices()
    return writer.frame_bytes(batch.world_frame_data(x[0], v[0], 0)) * batch.world_count


def auto_chunk_frames(frame_bytes) -> int:
    """Frames per chunk for frames of ``frame_bytes`` bytes: :data:`MAX_CHUNK_FRAMES`, fewer when
    that would hold more than :data:`AUTO_CHUNK_BYTES` (at least one)."""
    return int(max(1, min(MAX_CHUNK_FRAMES, AUTO_CHUNK_BYTES // max(int(frame_bytes), 1))))


def chunk_writers(writer, frame_bytes, frames, store_every=1) -> int:
    """Worker processes for ``writer``'s chunk files (:mod:`warpsim.usd.chunk_author`), frames of
    ``frame_bytes`` bytes (:func:`world_frame_bytes`): none when a chunk would hold less than
    :data:`POOL_CHUNK_BYTES` or nothing is kept, else one per core left beside this process
    (:func:`warpsim.process_pool.default_workers`), at most one per chunk. The environment
    variable ``WARPSIM_WRITE_WORKERS=N`` sets the count (0: never)."""
    from ..process_pool import default_workers, forced_workers

    forced = forced_workers()
    if forced is not None:
        return forced
    kept = stored_frames(int(frames) + 1, store_every)
    if not kept:
        return 0
    frames_a_chunk = min(writer.chunk_size, kept)
    if frame_bytes * frames_a_chunk < POOL_CHUNK_BYTES:
        return 0
    return default_workers(jobs=-(-kept // frames_a_chunk))


class BatchLayerWriter(UsdCacheWriter):
    """Streams the frames of ``world_count`` worlds (global indices ``first_world ..``) into one
    crash-safe chunked layer (:class:`warpsim.usd.writer.UsdCacheWriter` with root prim
    ``/Worlds``): frames go to chunk files of ``chunk_size`` frames beside ``path``, each world
    prim lists them as value clips (clips do not reach through a reference to a prim below the
    one that carries them), and a process killed at any moment leaves a layer holding every
    completed chunk. ``resume_frame``: keep the completed chunks before that frame and go on.
    ``workers``: processes authoring the chunk files while the worlds step on
    (:class:`warpsim.usd.writer.UsdCacheWriter`; the same bytes; 0: this process)."""

    def __init__(self, path, scene, first_world, world_count, fps, save_bytes=64 << 20, *, chunk_size=24,
                 resume_frame=None, durable=True, workers=0):
        path = os.path.abspath(os.fspath(path))
        if os.path.splitext(path)[1] not in (".usd", ".usdc", ".usda"):
            raise ValueError(f"batch layer {path!r} must end in .usd, .usdc or .usda")
        super().__init__(path, fps=fps, chunk_size=chunk_size, resume_frame=resume_frame, root_prim="Worlds",
                         durable=durable, save_bytes=save_bytes, workers=workers)
        scene.declare(self)
        self.prims = {name: joined_form(decl) for name, decl in self.prims.items()}  # curves: from the points
        self.first_world, self.world_count = int(first_world), int(world_count)
        self.scene_name = ""
        self.world_params = {}
        self._root = None  # the root layer as last written (updated in place: _write_root); None: author it anew
        self.dynamic = {name: d for name, d in self.prims.items() if d.is_dynamic}
        self.lo = np.full(3, np.inf)
        self.hi = np.full(3, -np.inf)
        for decl in self.prims.values():  # static geometry counts in a world's extent
            pts = getattr(decl.attrs.get("points"), "value", None)
            if pts is not None and not decl.is_dynamic:
                self._grow_bounds(pts)

    def frame_bytes(self, data) -> int:
        """Bytes one world's frame adds to the chunks [bytes]: the samples of ``data`` (one world's
        ``scene.frame_data()``) as this layer writes them, plus USD's per-sample overhead."""
        samples = [decl.frame_samples(data.get(name), 0) for name, decl in self.dynamic.items()]
        return sum(int(getattr(v, "nbytes", 8)) + SAMPLE_OVERHEAD for s in samples for v in s.values())

    def static_bytes(self) -> int:
        """Bytes of the layer's declarations [bytes]: the shared prims' values (once) and each
        world's prim specs (``WORLD_SPEC_BYTES``)."""
        values = [a.value for d in self.prims.values() for a in d.attrs.values() if a.value is not None]
        return sum(int(getattr(v, "nbytes", 8)) for v in values) + self.world_count * WORLD_SPEC_BYTES

    def set_world_params(self, local, params):
        """Author world ``local``'s parameters on its prim: ``customData["warpsim"]`` holds
        ``world`` (the global index) and ``params`` {name: value}, so a root or a picked file that
        references the prim carries them (not only the CSV)."""
        self.world_params[int(local)] = dict(params)
        self._root = None  # the root's declarations carry them: authored again

    def _world_path(self, local):
        return self._world_paths()[local]

    def _world_paths(self):
        """The prim path of every world (``/Worlds/world_GGGGGG``), made once."""
        paths = self.__dict__.get("_paths_text")
        if paths is None:
            paths = self._paths_text = [f"/Worlds/{world_prim_name(self.first_world + k)}"
                                        for k in range(self.world_count)]
        return paths

    def observe(self, datas):
        """Widen the worlds' extent by one frame's data without writing it (frames a resumed
        run re-simulates before its first new chunk)."""
        for data in datas:
            for name in self.dynamic:
                value = (data.get(name) or {}).get("points")
                if value is None:
                    continue
                self._grow_bounds(getattr(value, "numpy", lambda: value)())

    def write_worlds(self, frame, datas):
        """One frame of every world: ``datas[local]`` is world ``local``'s frame data
        (``{prim name: {key: array}}``, as ``scene.frame_data()`` gives it)."""
        if self._closed:
            raise ValueError("the writer is closed")
        frame = operator.index(frame)
        if len(datas) != self.world_count:
            raise ValueError(f"frame {frame}: data for {len(datas)} worlds, the layer holds {self.world_count}")
        if not self._sealed:
            self._seal()
        if self.last_frame is not None and frame <= self.last_frame:
            raise ValueError(f"frames must increase: got frame {frame} after {self.last_frame}")
        samples = [{name: decl.frame_samples(data.get(name), frame) for name, decl in self.dynamic.items()}
                   for data in datas]
        if self._chunk is not None and frame // self.chunk_size != self._chunk.start // self.chunk_size:
            self._finish_chunk()
        if self._chunk is None:
            self._open_chunk(frame)
        self._write_samples(frame, samples)
        self.last_frame = frame

    def observe_batch(self, batched):
        """:meth:`observe` for every world at once (``batched``: as :meth:`write_batch` takes it)."""
        for name in self.dynamic:
            value = (batched.get(name) or {}).get("points")
            if value is None:
                continue
            if isinstance(value, np.ndarray) and value.ndim == 3:
                self._grow_worlds(value)
            else:
                for v in value:
                    self._grow_bounds(getattr(v, "numpy", lambda: v)())

    def write_batch(self, frame, batched):
        """One frame of every world from arrays with a leading world axis: ``batched[prim][key]``
        (N, ...) (``WorldBatch.batch_frame_data``, from the scene's ``frame_arrays()``). The same
        samples, chunks and bytes as :meth:`write_worlds` given each world's ``frame_data()``,
        made with vectorised operations (:func:`warpsim.usd.frame_arrays.world_samples`) and
        authored in one Sdf change block with Vt arrays made from NumPy buffers."""
        from ..usd.frame_arrays import world_samples

        if self._closed:
            raise ValueError("the writer is closed")
        frame = operator.index(frame)
        if not self._sealed:
            self._seal()
        if self.last_frame is not None and frame <= self.last_frame:
            raise ValueError(f"frames must increase: got frame {frame} after {self.last_frame}")
        n = self.world_count
        samples, bounds = {}, {}
        for name, decl in self.dynamic.items():
            reduced: list = []
            samples[name] = world_samples(decl, batched.get(name), frame, n, reduced)
            if reduced:
                bounds[name] = reduced[0]  # (each world's points reduced once: for the extent and the layer's bounds)
        if self._chunk is not None and frame // self.chunk_size != self._chunk.start // self.chunk_size:
            self._finish_chunk()
        if self._chunk is None:
            self._open_chunk(frame)
        self._write_batch_samples(frame, samples, bounds)
        self.last_frame = frame

    def _batch_paths(self, name, attr_name):
        """The path strings of attribute ``name.attr_name`` of every world (made once)."""
        cache = self.__dict__.setdefault("_paths", {})
        key = (name, attr_name)
        if key not in cache:
            cache[key] = [f"{world}/{name}.{attr_name}" for world in self._world_paths()]
        return cache[key]

    def _sdf_paths(self, text):
        """``text`` (a :meth:`_batch_paths` list) as Sdf paths, made once (only this process's
        authoring needs them: a worker makes its own)."""
        cache = self.__dict__.setdefault("_sdf", {})
        if id(text) not in cache:
            from pxr import Sdf

            cache[id(text)] = [Sdf.Path(t) for t in text]
        return cache[id(text)]

    def _write_batch_samples(self, frame, samples, bounds=None):
        """Author (or stage for the chunk's worker) one frame of every world's ``samples`` and
        grow the layer's bounds; ``bounds``: ``{prim: (lo, hi)}`` per-world bounds (N, 3) of its
        sampled points already reduced (:func:`warpsim.usd.frame_arrays.world_samples`)."""
        from ..usd.writer import vt_maker

        chunk, n, t = self._chunk, self.world_count, float(frame)
        plan = []
        for name, attrs in samples.items():
            decl = self.prims[name]
            for attr_name, values in attrs.items():
                attr = decl.attrs[attr_name]
                text = self._batch_paths(name, attr_name)
                plan.append((attr, values, text, vt_maker(attr.type_name), name))
        if chunk.stage is not None:  # a worker authors the chunk (the same order, values and saves)
            self._stage_batch(t, [entry[:4] for entry in plan])
        else:
            self._author_batch(t, [entry[:4] for entry in plan])
        for attr, values, text, make, name in plan:  # the worlds' extent, grown once a frame
            if attr.name == "points" and not attr.on_change:
                if isinstance(values, np.ndarray) and values.shape[1] and name in (bounds or {}):
                    self._grow_reduced(*bounds[name])
                elif isinstance(values, np.ndarray):
                    self._grow_worlds(values, finite=True)  # (world_samples refused non-finite points)
                else:
                    for v in values:
                        self._grow_bounds(v)
        for name, attrs in samples.items():  # the chunk index's counts and bounds
            pts = attrs["points"] if "points" in attrs else attrs.get("positions")
            extent = attrs.get("extent")
            if isinstance(pts, np.ndarray) and (extent is None or isinstance(extent, np.ndarray)):
                union = None if extent is None else np.stack([extent[:, 0].min(0), extent[:, 1].max(0)])
                chunk.stats.add(name, pts.shape[1], union)
            else:
                for w in range(n):
                    chunk.stats.add(name, None if pts is None else len(pts[w]), None if extent is None else extent[w])
        self._end_frame_samples(frame)

    def _author_batch(self, t, plan):
        """Author one frame of every world in the open chunk's layer (in one Sdf change block),
        attribute by attribute: what changes every frame for all worlds at once
        (:func:`warpsim.usd.chunk_author.set_frame_samples`)."""
        from pxr import Sdf

        from ..usd.chunk_author import set_frame_samples

        chunk = self._chunk
        layer, last, pending = chunk.layer, chunk.last, 0
        with Sdf.ChangeBlock():
            for attr, values, text, make in plan:
                paths = self._sdf_paths(text)
                if not attr.on_change and isinstance(values, np.ndarray):
                    set_frame_samples(layer, paths, t, make, values)
                    pending += values.nbytes
                    continue
                for w in range(self.world_count):
                    value = values[w]
                    if attr.on_change:
                        prev = last.get(text[w])
                        if prev is not None and np.array_equal(prev, value):
                            continue
                        last[text[w]] = np.array(value, copy=True)
                        self._authored(attr.name, value)
                    layer.SetTimeSample(paths[w], t, make(value))
                    pending += getattr(value, "nbytes", 8)
        chunk.pending_bytes += pending

    def _stage_batch(self, t, plan):
        """One frame of every world staged for the chunk's worker (:class:`warpsim.usd.chunk_stage.ChunkStage`)."""
        for attr, values, text, make in plan:
            if attr.on_change and attr.name == "points":  # (an unchanged value adds nothing new to the bounds)
                for value in values:
                    self._authored(attr.name, value)
            self._chunk.stage.add(t, text[0], text, attr.type_name, attr.on_change, values)

    def _grow_worlds(self, points, finite=False):
        """:meth:`_grow_bounds` of each world's points (N, k, 3), vectorised (non-finite worlds
        skipped; ``finite``: the caller has checked they are all finite)."""
        pts = np.asarray(points)
        if pts.shape[1] == 0:
            return
        keep = None if finite else np.isfinite(pts).all(axis=(1, 2))
        if keep is not None and not keep.all():
            pts = pts[keep]
            if not len(pts):
                return
        self._grow_reduced(*world_bounds(pts))

    def _grow_reduced(self, lo, hi):
        """Widen ``lo``/``hi`` [m] by every world's bounds ``lo``, ``hi`` (N, 3), all finite."""
        lo, hi = lo.min(axis=0).astype(np.float64), hi.max(axis=0).astype(np.float64)
        self.lo, self.hi = np.minimum(self.lo, lo), np.maximum(self.hi, hi)

    def _write_samples(self, frame, samples):
        for local, world in enumerate(samples):
            self._set_prim_samples(frame, self._world_path(local), world)
            self._chunk.stats.add_frame(world)
        self._end_frame_samples(frame)

    def _authored(self, attr_name, value):
        if attr_name == "points":  # the bounds of every world's points, for the root's extent
            self._grow_bounds(value)

    def _grow_bounds(self, points):
        """Widen ``lo``/``hi`` [m] by these points (N, 3) when they are all finite."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if len(pts) and np.isfinite(pts).all():
            self.lo, self.hi = np.minimum(self.lo, pts.min(0)), np.maximum(self.hi, pts.max(0))

    def _dynamic_paths(self):
        return [f"{self._world_path(k)}/{name}.{a.name}" for k in range(self.world_count)
                for name, d in self.dynamic.items() for a in d.dynamic_attrs()]

    def _load_for_resume(self, resume_frame):
        """Adopt the kept chunks (``UsdCacheWriter``), refusing a layer written before the worlds
        inherited ``/WorldShared`` (its chunks hold curves' segment ends where this layer writes
        particles' points: the frames would not match)."""
        from pxr import Sdf

        if resume_frame and os.path.exists(self.path):
            old = Sdf.Layer.OpenAsAnonymous(self.path)
            if old is not None and old.GetPrimAtPath("/Worlds") and not old.GetPrimAtPath(SHARED):
                raise ValueError(f"cannot resume at frame {resume_frame}: {os.path.basename(self.path)} was written "
                                 "by an earlier warpsim (each world's prims declared in full, curves stored as "
                                 "segment ends); run the sweep again without --resume")
        super()._load_for_resume(resume_frame)

    def _clip_prim(self, layer):
        return layer.GetPrimAtPath(self._world_path(0))

    def _declare_specs(self, layer, manifest):
        """The root layer (authored once, then updated in place: :meth:`_write_root`): every prim
        declared once in the class ``/WorldShared`` (static attributes, topology, materials) and
        inherited by each world's prim of that name, which holds nothing itself (its samples come
        from the chunks); a chunk (``manifest``): each world's time-varying attributes (world 0's
        declared, the others' copied: :meth:`_declare_world_prims`)."""
        from pxr import Sdf

        if not manifest:
            shared = Sdf.CreatePrimInLayer(layer, SHARED)
            shared.specifier = Sdf.SpecifierClass
            for name, decl in self.prims.items():
                self._declare_prim(layer, shared.path.AppendChild(name), decl, manifest)
        root = Sdf.CreatePrimInLayer(layer, "/Worlds")
        root.specifier = Sdf.SpecifierDef
        root.typeName = "Scope"
        names = [(name, decl) for name, decl in self.prims.items() if not manifest or decl.is_dynamic]
        inherits = [Sdf.PathListOp.Create(prependedItems=[Sdf.Path(f"{SHARED}/{name}")]) for name, _ in names]
        first = None  # world 0's prims in a chunk, copied into every other world
        with Sdf.ChangeBlock():
            for k, path in enumerate(self._world_paths()):  # (PrimSpec: specifier and type in one call)
                spec = Sdf.PrimSpec(root, path[len("/Worlds/"):], Sdf.SpecifierDef, "Xform")
                if manifest:
                    first = self._declare_world_prims(layer, spec, names, first)
                    continue
                if k in self.world_params:
                    spec.customData = {"warpsim": {"world": self.first_world + k, "params": {
                        str(key): v if type(v) in _PLAIN else _custom_value(v)
                        for key, v in self.world_params[k].items()}}}
                for (name, decl), inherit in zip(names, inherits):  # each inherits /WorldShared/NAME
                    prim = Sdf.PrimSpec(spec, name, Sdf.SpecifierDef, decl.type_name)
                    prim.SetInfo("inheritPaths", inherit)
        return root

    def _declare_world_prims(self, layer, spec, names, first):
        """A chunk's prims ``names`` of the world prim ``spec``: declared in the first world
        (``first`` None), copied from ``first`` (their paths there) in the others (``Sdf.CopySpec``,
        C++, spec by spec; the chunks copy them from the manifest's text, so their bytes stay the
        same); returns the first world's paths."""
        from pxr import Sdf

        if first is None:
            first = [spec.path.AppendChild(name) for name, _ in names]
            for path, (_, decl) in zip(first, names):
                self._declare_prim(layer, path, decl, True)
            return first
        for (name, _), source in zip(names, first):
            child = spec.path.AppendChild(name)
            Sdf.CreatePrimInLayer(layer, child)
            if not Sdf.CopySpec(layer, source, layer, child):
                raise ValueError(f"could not copy the spec {source} to {child}")
        return first

    def _set_clips(self, layer, world, clips):
        """The clips on every world prim instead of ``/Worlds``, each with its own ``primPath``."""
        for path in self._world_paths():
            layer.GetPrimAtPath(path).SetInfo("clips", {"default": {**clips, "primPath": path}})

    def _set_root_info(self, layer, world):
        from pxr import Vt

        super()._set_root_info(layer, world)
        finite = np.isfinite(self.hi - self.lo).all()
        span = float(np.max(self.hi - self.lo)) if finite else 1.0
        data = dict(layer.customLayerData.get("warpsim", {}))
        data.update(firstWorld=self.first_world, worldCount=self.world_count, scene=self.scene_name, span=span,
                    center=Vt.DoubleArray(list(0.5 * (self.lo + self.hi)) if finite else [0.0, 0.0, 0.0]))
        if finite:
            data.update(lo=Vt.DoubleArray(list(self.lo)), hi=Vt.DoubleArray(list(self.hi)))
        layer.customLayerData = {"warpsim": data}

    def _write_root(self):
        """Rewrite the root layer: authored once (the first time, or again once no chunk is
        listed), then only its metadata and clips updated in place (with many worlds, authoring
        its specs again cost seconds a chunk); the same fields in the same order, so the same bytes."""
        layer = self._root
        if layer is None or not self.chunks:
            layer = self._build_layer(manifest=False)
        else:
            self._set_root_info(layer, layer.GetPrimAtPath("/Worlds"))
        self._root = layer
        self._export_atomic(layer, self.path)

    def close(self, scene_name=""):
        """Complete the last chunk and rewrite the layer; returns its path."""
        self.scene_name = scene_name or self.scene_name
        if self._closed:
            return self.path
        if not self._sealed:
            self._seal()
        chunks = len(self.chunks)
        self.flush()
        if len(self.chunks) == chunks:  # (a chunk just completed wrote the root with the final extent)
            self._write_root()  # the final extent (span) even when the last chunk came before it
        self._stop_pool()
        self._closed = True
        self._release_lock()  # the layer's lock file (warpsim.usd.lock) goes with the writer
        return self.path


_PLAIN = (bool, int, float, str)
"""Types USD customData holds as they are (:func:`_custom_value`)."""


def _custom_value(value):
    """A parameter value as USD customData holds it (vectors as double arrays)."""
    from pxr import Vt

    if isinstance(value, _PLAIN):
        return value
    if isinstance(value, (tuple, list, np.ndarray)):
        return Vt.DoubleArray([float(v) for v in value])
    return str(value)
