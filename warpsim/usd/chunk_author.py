"""One chunk file of a batch layer authored in a worker process (:mod:`warpsim.process_pool`).

The stepping process gathers a chunk's samples (every world, every frame of the chunk) into
shared memory and sends a :func:`chunk_job`; :func:`author_chunk` writes them with usd-core's Sdf
API into the chunk's temporary crate file, in the order and with the incremental saves the
writing process itself uses (:class:`warpsim.sweeps.usd.BatchLayerWriter`), so the file's bytes
are the same; the writing process then renames it, appends its chunk index record and rewrites
the root, keeping the cache's crash-safety rules (a chunk is listed only once complete).

Imports no Warp and no solver (a worker starts fast): NumPy, ``pxr`` and
:mod:`warpsim.usd.value_types`.
"""
from __future__ import annotations

import collections
import itertools
import os

import numpy as np

__all__ = ["author_chunk", "chunk_job", "copy_specs", "prepare_specs", "set_frame_samples", "specs_source"]


def chunk_job(tmp_path, specs, fields, times, blocks, save_bytes, durable) -> dict:
    """A picklable chunk job.

    ``tmp_path``: the temporary file to write; ``specs``: the chunk's prim and attribute specs as
    ``.usda`` text (copied spec by spec into the crate layer); ``fields``: one
    ``(paths, type_name, on_change)`` per attribute, ``paths`` the attribute's path in every
    world (N strings), in the order the writer authors them; ``times``: the chunk's time codes
    (F,); ``blocks``: per field, ``("shm", ref)`` (a :meth:`warpsim.process_pool.SharedBlock.ref`
    of an (F, N, ...) array) or ``("list", values)`` (``values[f][w]``, arrays of any length);
    ``save_bytes``: bytes of samples after which the layer is saved (as the writer does);
    ``durable``: fsync the file before answering."""
    return {"tmp_path": tmp_path, "specs": specs, "fields": fields, "times": list(times), "blocks": blocks,
            "save_bytes": int(save_bytes), "durable": bool(durable)}


_PARSED: dict = {}  # the last specs text this process parsed -> its layer (specs_source)


def specs_source(text, cache=None):
    """A layer holding the specs of ``text`` (``.usda`` text), parsed once per ``cache`` (a dict;
    None: this process's): the chunks of one writer share their specs, which take seconds to parse
    with many worlds."""
    from pxr import Sdf

    cache = _PARSED if cache is None else cache
    source = cache.get(text)
    if source is None:
        source = Sdf.Layer.CreateAnonymous(".usda")
        if not source.ImportFromString(text):
            raise ValueError("the chunk's specs did not parse")
        cache.clear()  # (one writer's at a time: a worker serves one writer)
        cache[text] = source
    return source


def prepare_specs(text) -> None:
    """A worker's job: parse ``text`` now (:func:`specs_source`), before the first chunk needs it."""
    specs_source(text)


def copy_specs(text, layer):
    """Copy the specs of ``text`` (a layer as ``.usda`` text, or a layer made by :func:`specs_source`)
    into ``layer``, prim by prim."""
    from pxr import Sdf

    source = specs_source(text) if isinstance(text, str) else text
    for prim in source.rootPrims:
        Sdf.CreatePrimInLayer(layer, prim.path)
        if not Sdf.CopySpec(source, prim.path, layer, prim.path):
            raise ValueError(f"could not copy the spec {prim.path}")


def author_chunk(job) -> tuple:
    """Write ``job`` (:func:`chunk_job`) into its temporary crate file; returns the file's (size
    in bytes, CRC-32) (:func:`warpsim.usd.chunk_index.file_digest`, read here so that the writer's
    process does not read every chunk back to index it)."""
    from pxr import Sdf

    from ..process_pool import attach

    tmp = job["tmp_path"]
    if os.path.lexists(tmp):
        os.remove(tmp)  # a leftover (or a planted link): removed, never followed
    layer = Sdf.Layer.CreateNew(tmp)
    if layer is None:
        raise OSError(f"could not create {tmp}")
    handles = []
    try:
        copy_specs(job["specs"], layer)
        values = []
        for kind, data in job["blocks"]:
            if kind == "shm":
                view, handle = attach(data)
                handles.append(handle)
                values.append(view)
            else:
                values.append(data)
        _author_samples(layer, job, values)
        del values
        if not layer.Save():
            raise OSError(f"could not save {tmp}")
    finally:
        for handle in handles:
            handle.close()
    del layer
    if job["durable"]:
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
    from .chunk_index import file_digest

    return file_digest(tmp)


def set_frame_samples(layer, paths, time, make, values) -> None:
    """``layer.SetTimeSample(paths[w], time, make(values[w]))`` for every world ``w`` in one ``map``
    (no Python statement a world); a crate file's bytes do not depend on the order samples were set
    in within a save (tests/test_sweep_store.py, tests/test_chunk_workers.py)."""
    collections.deque(map(layer.SetTimeSample, paths, itertools.repeat(float(time)), map(make, values)), maxlen=0)


def _author_samples(layer, job, values) -> int:
    """Author every sample of ``job`` from ``values`` (per field: (F, N, ...) or ``[f][w]``):
    frame by frame (the incremental saves fall where the writer's own do), each field's samples
    of all worlds at once (:func:`set_frame_samples`)."""
    from pxr import Sdf

    from .value_types import vt_maker

    fields, times = job["fields"], job["times"]
    makers = [vt_maker(type_name) for _, type_name, _ in fields]
    paths = [[Sdf.Path(p) for p in field_paths] for field_paths, _, _ in fields]
    changes = [bool(on_change) for _, _, on_change in fields]
    n = len(paths[0]) if paths else 0
    last: list = [[None] * n for _ in fields]
    pending = total = 0
    save_bytes = job["save_bytes"]
    for f, t in enumerate(times):
        t = float(t)
        for k in range(len(fields)):
            frame_values = values[k][f]
            if not changes[k]:
                set_frame_samples(layer, paths[k], t, makers[k], frame_values)
                size = frame_values.nbytes if isinstance(frame_values, np.ndarray) else \
                    sum(getattr(value, "nbytes", 8) for value in frame_values)
                pending += size
                total += size
                continue
            for w in range(n):
                value = frame_values[w]
                prev = last[k][w]
                if prev is not None and np.array_equal(prev, value):
                    continue
                last[k][w] = np.array(value, copy=True)
                layer.SetTimeSample(paths[k][w], t, makers[k](value))
                size = getattr(value, "nbytes", 8)
                pending += size
                total += size
        if pending >= save_bytes:  # crate saves append: as the writer saves a chunk it authors itself
            layer.Save()
            pending = 0
    return total
