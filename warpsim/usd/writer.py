"""Crash-safe streaming USD caches.

:class:`UsdCacheWriter` streams time samples to disk while a simulation runs. Layout beside the
file a user opens (``cache.usda`` here; ``.usd`` and ``.usdc`` work the same)::

    cache.usda                root layer: stage metadata, prim declarations, static geometry and
                              value clips (``clips["default"]``) pointing at the chunk files
    cache.manifest.usda       clip manifest: the time-varying attributes and their types
    cache.chunk000000.usdc    frames 0 .. K-1 (one chunk of ``chunk_size`` frames)
    cache.chunk000024.usdc    frames K .. 2K-1, ...
    cache.chunks.jsonl        chunk index: per chunk its frames, size, CRC-32, element counts and
                              bounds (``warpsim.usd.chunk_index``; ``warpsim info`` reads only this
                              and the root layer, ``--resume`` checks the chunks it keeps with it)

Crash safety: a chunk is written under a temporary name (saved incrementally, so memory holds
about one frame, not the chunk), synced and then ``os.replace``-d into place; only then is the
small root layer rewritten (temporary name + ``os.replace``) to list it. A process killed at any
moment (SIGKILL included) therefore leaves a root layer that opens and holds every completed
chunk. ``flatten=True`` turns the result into one self-contained ``.usdc`` at :meth:`close`.

Conventions: the frame index is the time code; ``timeCodesPerSecond = framesPerSecond = fps``;
``startTimeCode``/``endTimeCode`` track the completed frames; ``upAxis = Y``; ``metersPerUnit = 1``;
``defaultPrim`` is the root prim (``/World``); ``extent`` is authored at every sample.

``pxr`` (usd-core) is imported lazily, so ``import warpsim`` works without it.

Example::

    with UsdCacheWriter("usd_out/drop.usda", fps=60) as w:
        w.add_points("particles", radius=0.01, color=(0.2, 0.5, 1.0))
        w.add_plane("floor")
        for frame in range(120):
            sim.step(1 / 60)
            w.write_frame(frame, {"particles": {"points": sim.state.positions,
                                                "velocities": sim.state.velocities}})
"""
from __future__ import annotations

import collections
import functools
import glob
import operator
import os
import secrets

import numpy as np

from ..core import checks
from ..core.safe_files import clear_temporary, disk_full, disk_reason
from . import chunk_index
from .lock import OutputLock
from ..core.names import close_matches
from .chunk_author import copy_specs, specs_source
from .chunk_pool import WorkerChunks
from .value_types import pxr_modules as _pxr, to_vt, vt_maker
from .sink import PrimSink, state_frame_data

__all__ = ["ROOT_EXTENSIONS", "CacheWriteError", "UsdCacheWriter", "declare_prim", "settings_run_id"]

ROOT_EXTENSIONS = (".usd", ".usda", ".usdc")


def settings_run_id(settings) -> str:
    """A run id from a run's settings (a JSON-able dict): two runs of the same settings get the same
    id (their files stay byte-identical; their frames are too, so a mix of them is harmless) and
    runs that differ get different ones (``warpsim info`` tells their chunks apart)."""
    import hashlib
    import json

    text = json.dumps(settings, sort_keys=True, default=lambda v: list(v) if isinstance(v, tuple) else str(v))
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def _fsync(path):
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _tmp_name(path):
    """Temporary sibling of ``path`` with the same extension (USD picks the format from it)."""
    stem, ext = os.path.splitext(path)
    return f"{stem}.tmp-{os.getpid()}{ext}"


class CacheWriteError(OSError):
    """The disk took no more (full, read-only, over quota) while a cache was written: the message
    is one line naming the file and the frames kept (readable); the temporaries were removed."""


def _disk_guard(method):
    """Run a writing method; a full, read-only or over-quota disk (an ``OSError`` or a ``pxr``
    error saying so) removes this process's temporary files and becomes :class:`CacheWriteError`."""

    @functools.wraps(method)
    def guarded(self, *args, **kwargs):
        try:
            return method(self, *args, **kwargs)
        except CacheWriteError:
            raise
        except Exception as exc:  # noqa: BLE001  (pxr's Tf.ErrorException is no OSError)
            code = disk_full(exc)
            if code is None:
                raise
            self._drop_temporaries()
            raise CacheWriteError(code, f"cannot write {os.path.relpath(self._target or self.path)}: "
                                        f"{disk_reason(code)}; {self._kept_text()}") from None

    return guarded


class _Chunk:
    """The chunk being written: a crate layer under a temporary name."""

    def __init__(self, start, final_path):
        self.start = start
        self.end = start
        self.final_path = final_path
        self.tmp_path = _tmp_name(final_path)
        self.layer = None
        self.pending_bytes = 0
        self.last = {}  # attribute path -> last value written (on-change attributes)
        self.stats = chunk_index.ChunkStats()  # counts and bounds for the chunk index
        self.stage = None  # warpsim.usd.chunk_stage.ChunkStage when a worker writes the chunk
        self.digest = None  # (size, CRC-32) of the file, as that worker read it


def declare_prim(layer, path, decl, manifest=False) -> None:
    """Author declaration ``decl`` (:mod:`warpsim.usd.prims`) as a prim spec at ``path`` of the
    Sdf ``layer``: its type, applied schemas, attributes (static values, metadata, connections),
    relationships and child prims; ``manifest``: only the time-varying attributes (a clip manifest
    or chunk). The one way a declaration becomes USD: caches, sweeps and picked worlds."""
    Sdf, _, _ = _pxr()
    spec = Sdf.CreatePrimInLayer(layer, path)
    spec.specifier = Sdf.SpecifierDef
    spec.typeName = decl.type_name
    schemas = getattr(decl, "api_schemas", None)
    if schemas and not manifest:
        spec.SetInfo("apiSchemas", Sdf.TokenListOp.Create(prependedItems=list(schemas)))
    for attr in decl.attrs.values():
        if manifest and not attr.dynamic:
            continue
        variability = Sdf.VariabilityUniform if attr.uniform else Sdf.VariabilityVarying
        a = Sdf.AttributeSpec(spec, attr.name, Sdf.ValueTypeNames.Find(attr.type_name), variability,
                              attr.custom)
        for key, value in attr.metadata.items():
            a.SetInfo(key, value)
        if not attr.dynamic and attr.value is not None:
            a.default = to_vt(attr.type_name, attr.value)
        if getattr(attr, "connection", None):
            a.connectionPathList.explicitItems.append(path.AppendPath(Sdf.Path(attr.connection)))
    if manifest:
        return
    for rel_name, targets in decl.relationships.items():
        rel = Sdf.RelationshipSpec(spec, rel_name, custom=False)
        for t in targets:
            rel.targetPathList.explicitItems.append(path.AppendPath(Sdf.Path(t)))
    for rel_path, child in decl.children:
        parent = path
        for part in rel_path.split("/")[:-1]:  # intermediate scopes
            parent = parent.AppendChild(part)
            if not layer.GetPrimAtPath(parent):
                s = Sdf.CreatePrimInLayer(layer, parent)
                s.specifier = Sdf.SpecifierDef
                s.typeName = "Scope"
        declare_prim(layer, path.AppendPath(Sdf.Path(rel_path)), child, manifest)


class UsdCacheWriter(WorkerChunks, PrimSink):
    """Streams simulation frames into a crash-safe chunked USD cache (see module docstring).

    Args:
        path: the file a user opens (``.usd``, ``.usda`` or ``.usdc``); chunk files live beside it.
        fps: frames per second (also ``timeCodesPerSecond``); the frame index is the time code.
        chunk_size: frames per chunk file (K); a chunk holds frames ``[c K, (c + 1) K)``.
        flatten: at :meth:`close`, write one self-contained ``.usdc`` (the root's name with a
            ``.usdc`` extension, or the root itself if it is ``.usd``/``.usdc``) and remove the chunks.
        resume_frame: keep the existing cache's frames ``< resume_frame`` and continue from there
            (``None``: start a new cache, removing any previous chunks of this name).
        root_prim: name of the default prim holding every declared prim.
        durable: ``fsync`` files before renaming them (survives power loss, not only process kills).
        save_bytes: bytes of samples held in memory before the chunk file is saved incrementally.
        run_id: names this run in the root layer and every chunk index line (letters and digits;
            None: a random one; :func:`settings_run_id` gives one from the run's settings, so two
            runs of the same settings write byte-identical files). A resumed cache keeps its own.
        workers: worker processes that author the chunk files (:mod:`warpsim.usd.chunk_author`)
            while this process goes on stepping (0: this process authors them). The files'
            bytes, the chunk index and the crash-safety rules are the same either way: a chunk is
            renamed into place, indexed and listed by the root here, in order, once its worker
            has saved and synced it.

    Declare prims (``add_points``, ``add_mesh``, ``add_curves``, ``add_instancer``, static
    ``add_plane``/``add_sphere``/``add_box``/``add_static_mesh``, extra ``add_primvar``/
    ``add_attribute``) before the first frame, then call :meth:`write_frame` once per frame with a
    ``{prim name: {key: array}}`` mapping (NumPy arrays or ``wp.array``), or :meth:`write` with a
    warpsim ``State``. Every time-varying prim needs data in every frame.
    """

    def __init__(self, path, fps=60.0, chunk_size=24, flatten=False, *, resume_frame=None, root_prim="World",
                 durable=True, save_bytes=64 << 20, run_id=None, workers=0):
        path = os.path.abspath(os.fspath(path))
        self.dirname, base = os.path.split(path)
        self.stem, ext = os.path.splitext(base)
        if ext not in ROOT_EXTENSIONS:
            raise ValueError(f"USD cache path {path!r} must end in one of {ROOT_EXTENSIONS}, e.g. 'usd_out/run.usda'")
        fps = float(fps)
        if not np.isfinite(fps) or fps <= 0:
            raise ValueError(f"fps must be > 0, got {fps}")
        if int(chunk_size) != chunk_size or chunk_size < 1:
            raise ValueError(f"chunk_size must be an integer >= 1, got {chunk_size!r}")
        Sdf, _, _ = _pxr()
        if not Sdf.Path.IsValidIdentifier(root_prim):
            raise ValueError(f"root_prim {root_prim!r} is not a valid USD prim name (letters, digits, '_')")
        if resume_frame is not None and (int(resume_frame) != resume_frame or resume_frame < 0):
            raise ValueError(f"resume_frame must be an integer >= 0, got {resume_frame!r}")
        self.path = path
        self.fps = fps
        self.chunk_size = int(chunk_size)
        self.flatten = checks.flag(flatten, "UsdCacheWriter flatten")
        self.resume_frame = None if resume_frame is None else int(resume_frame)
        self.root_prim = root_prim
        self.durable = checks.flag(durable, "UsdCacheWriter durable")
        self.save_bytes = int(save_bytes)
        self.prims = {}  # name -> PrimDecl, in declaration order
        self.chunks = []  # completed chunks: [start frame, end frame, file name]
        self.last_frame = None
        self.output_path = path  # the file to open once closed (the flat file with flatten=True)
        self._chunk = None
        self._sealed = False
        self._closed = False
        self._lock = None  # the output's lock (warpsim.usd.lock), held from begin() to close()
        self._target = None  # the file being written now (named when the disk takes no more)
        if run_id is not None and not (isinstance(run_id, str) and run_id.isalnum()):
            raise ValueError(f"run_id {run_id!r} must be letters and digits, e.g. settings_run_id(settings)")
        self.run_id = run_id or secrets.token_hex(6)  # names this run in the root layer and every index line
        self.workers = checks.integer(workers, "UsdCacheWriter workers", lo=0, hi=64,
                                      fix="0 (author chunks here) or a few processes, e.g. default_workers()")
        self._pool = None  # warpsim.process_pool.ProcessPool of the chunk authors (workers > 0)
        self._blocks = None  # warpsim.process_pool.BlockPool of their shared memory
        self._inflight = collections.deque()  # chunks handed to workers: (chunk, future), oldest first
        self._specs_text = None  # a chunk's specs as .usda text (the workers copy them)
        self._parsed = {}  # the specs text parsed once for this process's chunks (chunk_author.specs_source)
        self._unlisted = []  # chunks from workers renamed into place, not yet indexed and in the root
        self._root_due = 0.0  # time.monotonic() after which the root is rewritten again

    # ------------------------------------------------------------------ declarations
    # add_points, add_mesh, add_curves, add_instancer, add_static_mesh, add_plane, add_box,
    # add_sphere, add_primvar and add_attribute come from PrimSink (warpsim.usd.sink).
    def _valid_name(self, name):
        Sdf, _, _ = _pxr()
        return Sdf.Path.IsValidIdentifier(name)

    # ------------------------------------------------------------------ frames
    @_disk_guard
    def begin(self):
        """Freeze the declarations and write the manifest and root layer now (adopting the
        existing chunks when resuming); otherwise the first frame does it. ValueError when a
        resume is impossible."""
        if not self._sealed:
            self._seal()
        return self

    @_disk_guard
    def write_frame(self, frame, data):
        """Write one frame. ``data``: ``{prim name: {key: array}}`` for every time-varying prim."""
        if self._closed:
            raise ValueError("the writer is closed")
        frame = operator.index(frame)
        if frame < 0:
            raise ValueError(f"frame must be >= 0, got {frame}")
        if self.last_frame is not None and frame <= self.last_frame:
            raise ValueError(f"frames must increase: got frame {frame} after {self.last_frame}")
        if not self._sealed:
            self._seal()
            if self.last_frame is not None and frame <= self.last_frame:
                raise ValueError(f"frames must increase: got frame {frame} after {self.last_frame}")
        data = dict(data)
        for name in data:
            if name not in self.prims or not self.prims[name].is_dynamic:
                dyn = [n for n, p in self.prims.items() if p.is_dynamic]
                raise ValueError(f"frame {frame}: {name!r} is not a declared time-varying prim; declared: {dyn}."
                                 f"{close_matches(name, dyn)}")
        samples = {name: decl.frame_samples(data.get(name), frame)
                   for name, decl in self.prims.items() if decl.is_dynamic}
        if self._chunk is not None and frame // self.chunk_size != self._chunk.start // self.chunk_size:
            self._finish_chunk()
        if self._chunk is None:
            self._open_chunk(frame)
        self._write_samples(frame, samples)
        self.last_frame = frame

    def write(self, frame, state, **extra):
        """Simulator hook: write ``state.positions``/``state.velocities`` into every points prim
        declared with ``from_state=True`` (declaring ``particles`` if no prim exists yet).
        ``extra``: further ``{prim name: {key: array}}`` entries for this frame."""
        if not self.prims and not self._sealed:
            self.add_points("particles", from_state=True)
        data = state_frame_data(self.prims, state)
        data.update(extra)
        self.write_frame(frame, data)

    __call__ = write

    @_disk_guard
    def flush(self):
        """Complete the current chunk now (e.g. before saving a checkpoint): every frame written so
        far is then in the root layer. Returns the last completed frame (None if none)."""
        if self._chunk is not None:
            self._finish_chunk()
        if self._inflight:
            self._reap(wait_all=True)
        return self.chunks[-1][1] if self.chunks else None

    @_disk_guard
    def close(self):
        """Complete the last (partial) chunk, flatten if asked; returns the path to open."""
        if self._closed:
            return self.output_path
        try:
            if not self._sealed:
                self._seal()
            self.flush()
            self._closed = True
            if self.flatten:
                self.output_path = self._flatten()
        finally:
            self._stop_pool(wait=self._closed)
            if self._closed:
                self._release_lock()
        return self.output_path

    @property
    def closed(self) -> bool:
        """Whether :meth:`close` has completed the cache."""
        return self._closed

    def _kept_text(self) -> str:
        """What a failed write kept: the completed chunks the root layer lists (readable)."""
        if not self.chunks or not os.path.exists(self.path):
            return "no frames were kept"
        return (f"kept frames {self.chunks[0][0]}..{self.chunks[-1][1]} in {os.path.relpath(self.path)} "
                "(readable)")

    def _drop_temporaries(self) -> None:
        """After a failed write: forget the open chunk and remove this process's temporary files
        (``<name>.tmp-PID.*`` and usd-core's own ``<name>.tmp-PID.usdc.XXXXXX``)."""
        chunk, self._chunk = self._chunk, None
        if chunk is not None:
            chunk.layer = None  # release the layer (and its file) before removing it
        for c in [chunk, *(c for c, _ in self._inflight)]:
            if c is not None and getattr(c, "stage", None) is not None:
                c.stage.release()
        self._inflight.clear()
        self._stop_pool(wait=False)  # (the workers' temporaries carry this process's id too)
        for tmp in glob.glob(self._abs(glob.escape(self.stem) + f".*tmp-{os.getpid()}*")):
            try:
                os.remove(tmp)
            except OSError:
                pass

    def _release_lock(self) -> None:
        """Give the output's lock back (once the writer is closed; subclasses' ``close`` call it)."""
        if self._lock is not None:
            self._lock.release()
            self._lock = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()  # also on errors: every frame written so far stays readable
        return False

    # ------------------------------------------------------------------ layout
    def _file(self, kind, start=None):
        if kind == "manifest":
            return f"{self.stem}.manifest.usda"
        return f"{self.stem}.chunk{start:06d}.usdc"

    def _abs(self, name):
        return os.path.join(self.dirname, name)

    @property
    def _index_file(self):
        return chunk_index.index_path(self.dirname, self.stem)

    def _replace(self, tmp, final, synced=False, sync_folder=True):
        """Rename ``tmp`` to ``final``; with ``durable``, the file synced first (unless ``synced``)
        and the folder after (unless ``sync_folder`` is False: the caller syncs it once for several)."""
        if self.durable and not synced:
            _fsync(tmp)
        os.replace(tmp, final)
        if self.durable and sync_folder:
            self._sync_folder()

    def _sync_folder(self):
        try:
            fd = os.open(self.dirname, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
        except OSError:  # pragma: no cover - directories cannot be opened on some platforms
            pass

    def _export_atomic(self, layer, final):
        tmp = _tmp_name(final)
        self._target = final
        clear_temporary(tmp)  # never through a link planted at the temporary name
        if not layer.Export(tmp):
            raise OSError(f"could not write {tmp}")
        self._replace(tmp, final)

    def _seal(self):
        """Freeze declarations; write the manifest and the first root layer."""
        os.makedirs(self.dirname, exist_ok=True)
        if self._lock is None:  # one writer per cache: another process writing it is refused here
            self._lock = OutputLock(self.path).acquire()
        if self.workers and self._pool is None:  # started now: they are ready by the first chunk
            self._start_pool()
        try:
            # Leftovers of a killed run: our "<name>.tmp-PID.usdc" files and the temporaries usd-core
            # itself writes while saving one ("<name>.tmp-PID.XXXXXX", no .usd suffix).
            for tmp in glob.glob(self._abs(glob.escape(self.stem) + ".*tmp-*")):
                os.remove(tmp)
            self._sealed = True
            manifest = self._abs(self._file("manifest"))
            self._export_atomic(self._build_layer(manifest=True), manifest)
            with open(manifest, encoding="utf-8", newline="") as f:  # a chunk's specs: the manifest's,
                self._specs_text = f.read()  # authored once (its .usda text; WorkerChunks._chunk_specs)
            if self.resume_frame is not None:
                self._load_for_resume(self.resume_frame)
            else:
                chunk_index.write_index(self._index_file, [], self.durable)
            self._write_root()
            self._remove_unlisted_chunks()
            if self._pool is not None:
                self._warm_workers()
        except BaseException:
            self._lock.release()  # nothing of this run was written: the cache stays free for another writer
            self._lock = None
            raise

    def _remove_unlisted_chunks(self):
        keep = {c[2] for c in self.chunks}
        for f in glob.glob(self._abs(glob.escape(self.stem) + ".chunk[0-9]*.usdc")):
            if os.path.basename(f) not in keep:
                os.remove(f)

    def _open_chunk(self, frame):
        Sdf, _, _ = _pxr()
        chunk = _Chunk(frame, self._abs(self._file("chunk", frame)))
        self._target = chunk.final_path
        if self._pool is not None:  # staged for a worker (warpsim.usd.chunk_stage): no layer here
            from .chunk_stage import ChunkStage

            chunk.stage = ChunkStage(self.chunk_size, self._blocks)
            self._chunk = chunk
            return
        clear_temporary(chunk.tmp_path)  # a leftover, or a planted link: removed, never followed
        layer = Sdf.Layer.CreateNew(chunk.tmp_path)
        if layer is None:
            raise OSError(f"could not create {chunk.tmp_path}")
        # as a worker does (the same bytes whoever writes the chunk); the text parsed once for all chunks
        copy_specs(specs_source(self._chunk_specs(), self._parsed), layer)
        chunk.layer = layer
        self._chunk = chunk

    def _set_prim_samples(self, frame, base, samples) -> None:
        """Author one frame of ``samples`` ({prim: {attribute: value}}) under the prim path
        ``base`` in the open chunk, skipping on-change attributes whose value did not change;
        each authored value also goes to :meth:`_authored`."""
        chunk = self._chunk
        if chunk.stage is not None:
            for name, values in samples.items():
                for attr_name, value in values.items():
                    attr = self.prims[name].attrs[attr_name]
                    self._authored(attr_name, value)  # (an unchanged on-change value adds nothing new)
                    chunk.stage.add(float(frame), (base, name, attr_name), [f"{base}/{name}.{attr_name}"],
                                    attr.type_name, attr.on_change, [value])
            return
        for name, values in samples.items():
            decl = self.prims[name]
            for attr_name, value in values.items():
                attr = decl.attrs[attr_name]
                path = f"{base}/{name}.{attr_name}"
                if attr.on_change:
                    prev = chunk.last.get(path)
                    if prev is not None and np.array_equal(prev, value):
                        continue
                    chunk.last[path] = np.array(value, copy=True)
                self._authored(attr_name, value)
                chunk.layer.SetTimeSample(path, float(frame), to_vt(attr.type_name, value))
                chunk.pending_bytes += getattr(value, "nbytes", 8)

    def _authored(self, attr_name, value) -> None:
        """Called with every value :meth:`_set_prim_samples` authors (a hook for subclasses)."""

    def _end_frame_samples(self, frame) -> None:
        """The frame's samples are authored: note its end; save the chunk once enough is pending."""
        chunk = self._chunk
        chunk.end = frame
        self._target = chunk.final_path
        if chunk.stage is not None:  # the worker saves as this process would
            return
        if chunk.pending_bytes >= self.save_bytes:
            chunk.layer.Save()  # crate saves append: memory holds only the unsaved samples
            chunk.pending_bytes = 0

    def _write_samples(self, frame, samples):
        self._set_prim_samples(frame, "/" + self.root_prim, samples)
        self._chunk.stats.add_frame(samples)
        self._end_frame_samples(frame)

    def _finish_chunk(self):
        chunk = self._chunk
        self._chunk = None
        self._target = chunk.final_path
        if chunk.stage is not None:
            self._submit(chunk)
            return
        if not chunk.layer.Save():
            raise OSError(f"could not save {chunk.tmp_path}")
        chunk.layer = None  # release the layer (and its file mapping) before renaming
        self._replace(chunk.tmp_path, chunk.final_path)
        self._target = self._index_file
        chunk_index.append_record(self._index_file, chunk_index.record(chunk.final_path, chunk.start, chunk.end,
                                                                        chunk.stats, self.run_id), self.durable)
        self.chunks.append([chunk.start, chunk.end, os.path.basename(chunk.final_path)])
        try:
            self._write_root()
        except BaseException:
            self.chunks.pop()  # the root on disk still lists the chunks before this one
            raise

    # ------------------------------------------------------------------ layers
    def _declare_specs(self, layer, manifest):
        """Author the prim hierarchy: all declarations (root) or only time-varying attributes."""
        Sdf, _, _ = _pxr()
        world = Sdf.CreatePrimInLayer(layer, "/" + self.root_prim)
        world.specifier = Sdf.SpecifierDef
        world.typeName = "Xform"
        for name, decl in self.prims.items():
            if manifest and not decl.is_dynamic:
                continue
            self._declare_prim(layer, world.path.AppendChild(name), decl, manifest)
        return world

    def _declare_prim(self, layer, path, decl, manifest):
        declare_prim(layer, path, decl, manifest)

    def _build_layer(self, manifest):
        Sdf, _, _ = _pxr()
        layer = Sdf.Layer.CreateAnonymous(".usda")
        world = self._declare_specs(layer, manifest)
        if not manifest:
            self._set_root_info(layer, world)
        return layer

    def _set_root_info(self, layer, world):
        """Author the root layer's metadata and its clips (on ``world``, the root prim's spec) listing
        the completed chunks; again on the same layer, the same fields in the same order."""
        Sdf, Vt, _ = _pxr()
        layer.defaultPrim = self.root_prim
        layer.timeCodesPerSecond = self.fps
        layer.framesPerSecond = self.fps
        layer.pseudoRoot.SetInfo("upAxis", "Y")
        layer.pseudoRoot.SetInfo("metersPerUnit", 1.0)
        layer.customLayerData = {"warpsim": {"chunkSize": self.chunk_size, "run": self.run_id,
                                             "chunkIndex": os.path.basename(self._index_file),
                                             "chunkEnds": Vt.IntArray([c[1] for c in self.chunks])}}
        if self.chunks:
            layer.startTimeCode = float(self.chunks[0][0])
            layer.endTimeCode = float(self.chunks[-1][1])
            self._set_clips(layer, world, {
                "assetPaths": Sdf.AssetPathArray(["./" + c[2] for c in self.chunks]),
                "active": Vt.Vec2dArray([(float(c[0]), float(i)) for i, c in enumerate(self.chunks)]),
                "times": Vt.Vec2dArray([(float(self.chunks[0][0]),) * 2, (float(self.chunks[-1][1]),) * 2]),
                "manifestAssetPath": Sdf.AssetPath("./" + self._file("manifest")),
                "primPath": "/" + self.root_prim,
            })

    def _set_clips(self, layer, world, clips):
        """Author ``clips`` (the chunks' value clips) as ``clips["default"]`` of the root prim ``world``."""
        world.SetInfo("clips", {"default": clips})

    def _clip_prim(self, layer):
        """The prim spec of ``layer`` whose ``clips`` list the chunks (the root prim here)."""
        return layer.GetPrimAtPath("/" + self.root_prim)

    def _write_root(self):
        self._export_atomic(self._build_layer(manifest=False), self.path)

    # ------------------------------------------------------------------ resume / flatten
    def _load_for_resume(self, resume_frame):
        """Adopt the existing cache's chunks with frames < resume_frame (truncating the last one)."""
        Sdf, _, _ = _pxr()
        if resume_frame == 0:
            return
        if not os.path.exists(self.path):
            raise ValueError(f"cannot resume at frame {resume_frame}: {self.path} does not exist")
        old = Sdf.Layer.OpenAsAnonymous(self.path)
        data = dict(old.customLayerData.get("warpsim", {}))
        if isinstance(data.get("run"), str) and data["run"].isalnum():
            self.run_id = data["run"]  # a resumed run continues the cache's run
        world = self._clip_prim(old)
        clips = dict(world.GetInfo("clips")).get("default") if world and world.HasInfo("clips") else None
        if not clips or "chunkEnds" not in data:
            raise ValueError(f"cannot resume at frame {resume_frame}: {self.path} holds no chunked warpsim "
                             "frames (was it flattened?)")
        starts = [int(a[0]) for a in clips["active"]]
        files = [os.path.basename(p.path) for p in clips["assetPaths"]]
        ends = list(data["chunkEnds"])
        chunks = [[s, e, f] for s, e, f in zip(starts, ends, files) if s < resume_frame]
        last = chunks[-1][1] if chunks else None
        if last is None or last < resume_frame - 1:
            raise ValueError(f"cannot resume at frame {resume_frame}: {self.path} holds frames up to {last}; "
                             "resume from an earlier checkpoint")
        records = chunk_index.read_index(self._index_file) or {}
        for s, e, f in chunks:  # never resume over a hole: every frame before the checkpoint must be intact
            why = chunk_index.chunk_problem(self.dirname, f, records.get(f))
            if why:
                raise ValueError(f"cannot resume at frame {resume_frame}: chunk file {f} (frames {s}..{min(e, last)}) "
                                 f"is {why}, so frames before the checkpoint are lost; run again without --resume "
                                 "(or restore the file)")
        if last >= resume_frame:  # truncate the chunk that runs past the resume point
            chunks[-1][1] = resume_frame - 1
            stats = self._copy_chunk(chunks[-1], self._abs(chunks[-1][2]), resume_frame - 1)
            records[chunks[-1][2]] = chunk_index.record(self._abs(chunks[-1][2]), *chunks[-1][:2], stats, self.run_id)
        for s, e, f in chunks:  # caches written before the index existed get one now
            if f not in records:
                records[f] = chunk_index.record(self._abs(f), s, e, self._copy_chunk([s, e, f], None, e), self.run_id)
        chunk_index.write_index(self._index_file, [records[f] for s, e, f in chunks], self.durable)
        self.chunks = chunks
        self.last_frame = resume_frame - 1

    def _copy_chunk(self, chunk, dest, last_frame):
        """Rewrite chunk file ``dest`` keeping frames <= last_frame (atomic; ``dest=None``: only
        read it); returns the :class:`chunk_index.ChunkStats` of the frames kept."""
        Sdf, _, _ = _pxr()
        src = Sdf.Layer.OpenAsAnonymous(self._abs(chunk[2]))
        tmp = _tmp_name(dest)
        if dest is not None:
            self._target = dest
            clear_temporary(tmp)
        out = None if dest is None else Sdf.Layer.CreateNew(tmp)
        if out is not None:
            self._declare_specs(out, manifest=True)
        frames = {}
        for path in self._dynamic_paths():
            for t in src.ListTimeSamplesForPath(path):
                if chunk[0] <= t <= last_frame:
                    value = src.QueryTimeSample(path, t)
                    if out is not None:
                        out.SetTimeSample(path, t, value)
                    prim, attr = path.rsplit("/", 1)[1].split(".", 1)
                    frames.setdefault(t, {}).setdefault(prim, {})[attr] = value
        if out is not None:
            out.Save()
            del out
            self._replace(tmp, dest)
        del src
        stats = chunk_index.ChunkStats()
        for t in sorted(frames):
            stats.add_frame(frames[t])
        return stats

    def _dynamic_paths(self):
        return [f"/{self.root_prim}/{name}.{a.name}" for name, d in self.prims.items() for a in d.dynamic_attrs()]

    def _flatten(self):
        """Stream every chunk into one self-contained crate file; returns its path."""
        Sdf, _, _ = _pxr()
        ext = os.path.splitext(self.path)[1]
        final = self.path if ext in (".usd", ".usdc") else self._abs(self.stem + ".usdc")
        tmp = f"{os.path.splitext(final)[0]}.tmp-{os.getpid()}.usdc"
        self._target = final
        clear_temporary(tmp)
        out = Sdf.Layer.CreateNew(tmp)
        chunks, self.chunks = self.chunks, []
        out.TransferContent(self._build_layer(manifest=False))  # declarations, metadata, no clips
        self.chunks = chunks
        if chunks:
            out.startTimeCode = float(chunks[0][0])
            out.endTimeCode = float(chunks[-1][1])
        on_change = {f"/{self.root_prim}/{n}.{a.name}" for n, d in self.prims.items() for a in d.dynamic_attrs()
                     if a.on_change}
        last = {}
        for start, end, fname in chunks:
            src = Sdf.Layer.OpenAsAnonymous(self._abs(fname))
            for path in self._dynamic_paths():
                for t in src.ListTimeSamplesForPath(path):
                    if start <= t <= end:
                        value = src.QueryTimeSample(path, t)
                        if path in on_change:
                            if path in last and np.array_equal(last[path], value):
                                continue
                            last[path] = np.array(value)
                        out.SetTimeSample(path, t, value)
            out.Save()  # incremental: only the current chunk's samples are held in memory
            del src
        del out
        self._replace(tmp, final)  # a .usd name may hold crate contents
        if final != self.path:
            os.remove(self.path)
        for c in chunks:
            os.remove(self._abs(c[2]))
        os.remove(self._abs(self._file("manifest")))
        if os.path.exists(self._index_file):
            os.remove(self._index_file)
        self.chunks = []
        return final
