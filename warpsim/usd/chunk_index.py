"""The chunk index of a chunked cache: ``<stem>.chunks.jsonl`` beside the root layer.

One JSON line per completed chunk, appended (and synced) by :class:`UsdCacheWriter` right after
the chunk file is renamed into place and before the root layer lists it::

    {"file": "run.chunk000024.usdc", "start": 24, "end": 47, "bytes": 10342, "crc32": 2838219181,
     "prims": {"ball": {"count": [1, 1], "bounds": [[x, y, z], [x, y, z]]}}}

``bytes`` and ``crc32`` let a reader tell an intact chunk from a deleted, truncated or
overwritten one without opening it in USD; ``prims`` holds each time-varying prim's element
count range and the union of its per-frame extents [m] over the chunk's frames. ``warpsim info``
summarises a 50,000-frame cache from this file and the root layer alone, and ``--resume``
refuses to continue a cache whose frames before the checkpoint are not all intact.

A torn last line (a process killed while appending) is ignored: the root layer, rewritten only
after the line is synced, never lists that chunk.
"""

from __future__ import annotations

import json
import os
import zlib

import numpy as np

from ..core.safe_files import open_for_write, open_temporary

__all__ = [
    "ChunkStats",
    "chunk_problem",
    "file_digest",
    "index_path",
    "read_index",
    "readable_ranges",
    "write_index",
]

SUFFIX = ".chunks.jsonl"


def index_path(dirname, stem):
    """Path of the index beside the root layer ``<dirname>/<stem>.usd*``."""
    return os.path.join(dirname, stem + SUFFIX)


def file_digest(path, block=1 << 22):
    """(size in bytes, CRC-32) of a file, read in 4 MiB blocks."""
    crc = 0
    size = 0
    with open(path, "rb") as f:
        while True:
            data = f.read(block)
            if not data:
                break
            crc = zlib.crc32(data, crc)
            size += len(data)
    return size, crc


class ChunkStats:
    """Per-prim element-count range and extent union over a chunk's frames."""

    def __init__(self):
        self.prims = {}  # name -> [count min, count max, lo (3,), hi (3,)]

    def add(self, name, count, extent):
        """One frame of prim ``name``: ``count`` elements (or None), ``extent`` (2, 3) (or None)."""
        entry = self.prims.setdefault(name, [None, None, None, None])
        if count is not None:
            entry[0] = count if entry[0] is None else min(entry[0], count)
            entry[1] = count if entry[1] is None else max(entry[1], count)
        if extent is not None:
            e = np.asarray(extent, np.float64).reshape(2, 3)
            entry[2] = e[0] if entry[2] is None else np.minimum(entry[2], e[0])
            entry[3] = e[1] if entry[3] is None else np.maximum(entry[3], e[1])

    def add_frame(self, samples, point_keys=("points", "positions")):
        """Add one frame of ``{prim name: {attribute: value}}`` (the writer's samples)."""
        for name, values in samples.items():
            pts = next((values[k] for k in point_keys if k in values), None)
            self.add(name, None if pts is None else len(pts), values.get("extent"))

    def to_json(self):
        out = {}
        for name, (cmin, cmax, lo, hi) in self.prims.items():
            entry = {}
            if cmin is not None:
                entry["count"] = [int(cmin), int(cmax)]
            if lo is not None:
                entry["bounds"] = [[float(v) for v in lo], [float(v) for v in hi]]
            out[name] = entry
        return out


def record(path, start, end, stats, run=None, digest=None):
    """The index line of the chunk file at ``path`` holding frames ``start..end``, written by the
    run named ``run`` (the writer's run id, also in the root layer; None: not recorded);
    ``digest``: the file's (size, CRC-32) when its writer already read them (None: read here)."""
    size, crc = file_digest(path) if digest is None else digest
    rec = {
        "file": os.path.basename(path),
        "start": int(start),
        "end": int(end),
        "bytes": size,
        "crc32": crc,
        "prims": stats.to_json(),
    }
    if run is not None:
        rec["run"] = str(run)
    return rec


def _whole(value, low=0):
    return isinstance(value, int) and not isinstance(value, bool) and value >= low


def record_problem(rec) -> str | None:
    """What is wrong with the fields of one index line (None when every field is well formed)."""
    for key in ("start", "end", "bytes", "crc32"):
        if key not in rec:
            return f"field {key!r} is missing"
        if not _whole(rec[key]):
            return f"field {key!r} is {rec[key]!r}, not a whole number >= 0"
    if rec["end"] < rec["start"]:
        return f"field 'end' {rec['end']} is before 'start' {rec['start']}"
    if rec["crc32"] >= 1 << 32:
        return f"field 'crc32' {rec['crc32']} is not a CRC-32"
    if not isinstance(rec.get("prims", {}), dict):
        return f"field 'prims' is {type(rec['prims']).__name__}, not an object"
    if "run" in rec and not (isinstance(rec["run"], str) and rec["run"].isalnum()):
        return f"field 'run' is {rec['run']!r}, not a run id"
    return None


def append_record(index_file, rec, durable=True):
    """Append one line to the index (flushed and, with ``durable``, synced)."""
    with open_for_write(index_file, "a", what="chunk index") as f:
        f.write(json.dumps(rec, separators=(",", ":")) + "\n")
        f.flush()
        if durable:
            os.fsync(f.fileno())


def write_index(index_file, records, durable=True):
    """Replace the index with ``records`` (atomic: temporary file + rename)."""
    tmp = f"{index_file}.tmp-{os.getpid()}"
    with open_temporary(tmp) as f:
        for rec in records:
            f.write(json.dumps(rec, separators=(",", ":")) + "\n")
        f.flush()
        if durable:
            os.fsync(f.fileno())
    os.replace(tmp, index_file)


def read_index(index_file):
    """{chunk file name: record} from an index (None if there is no index); unreadable lines
    (a torn last line) are skipped. A line naming its file whose other fields are malformed (a
    tampered index) is kept as ``{"file": ..., "damaged": why}``, which :func:`chunk_problem`
    reports."""
    if os.path.exists(index_file) and not os.path.isfile(index_file):  # a FIFO would block for ever
        from .pxr_errors import DamagedFileError

        raise DamagedFileError(f"chunk index {index_file} is not a regular file (a pipe, socket or folder); restore "
                               "it or write the cache again")
    try:
        with open(index_file, encoding="utf-8", errors="replace") as f:
            lines = f.read().splitlines()
    except FileNotFoundError:
        return None
    out = {}
    for line in lines:
        try:
            rec = json.loads(line)
            name = rec["file"]
        except (ValueError, KeyError, TypeError):
            continue
        if not isinstance(name, str):
            continue
        why = record_problem(rec)
        out[name] = rec if why is None else {"file": name, "damaged": why, "index": os.path.basename(index_file)}
    return out


def chunk_problem(dirname, fname, rec, verify=True):
    """Why chunk file ``fname`` cannot be trusted ("missing", "truncated: ...", ...) or None
    when it is intact. With an index record, the size (and with ``verify`` the CRC-32) must
    match; without one (a cache written before the index existed), it must open in USD."""
    path = os.path.join(dirname, fname)
    try:
        size = os.path.getsize(path)
    except FileNotFoundError:
        return "missing"
    except OSError as exc:
        return f"unreadable ({exc.strerror})"
    if rec is not None and "damaged" in rec:  # the index line is at fault: name it, and say whether the chunk opens
        index = rec.get("index") or "the chunk index"
        opens = chunk_problem(dirname, fname, None, verify) is None
        return (f"listed by a damaged chunk index line ({rec['damaged']}) in {index}; "
                + ("the chunk itself opens in USD, so the index is at fault: restore " + index
                   + " or write the cache again" if opens else "the chunk does not open in USD either"))
    if rec is None:
        from pxr import Sdf

        try:
            layer = Sdf.Layer.OpenAsAnonymous(path)
        except Exception as exc:  # noqa: BLE001  (Tf.ErrorException)
            from .pxr_errors import pxr_reason

            return f"damaged (does not open in USD: {pxr_reason(exc, 120)})"
        return None if layer is not None else "damaged (does not open in USD)"
    if size != rec["bytes"]:
        return f"damaged ({size} bytes, written as {rec['bytes']})"
    if verify:
        try:
            crc = file_digest(path)[1]
        except OSError as exc:
            return f"unreadable ({exc.strerror})"
        if crc != rec["crc32"]:
            return "damaged (its contents changed since it was written: CRC-32 mismatch)"
    return None


def readable_ranges(chunks, bad):
    """Merged frame ranges [(start, end), ...] of the chunks [(start, end, file), ...] whose
    file is not in ``bad``."""
    out = []
    for start, end, fname in chunks:
        if fname in bad:
            continue
        if out and start == out[-1][1] + 1:
            out[-1] = (out[-1][0], end)
        else:
            out.append((start, end))
    return out
