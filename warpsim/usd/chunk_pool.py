"""The part of :class:`warpsim.usd.writer.UsdCacheWriter` that hands chunks to worker processes.

With ``workers > 0`` a chunk's samples are staged (:mod:`warpsim.usd.chunk_stage`) instead of
authored, and :meth:`WorkerChunks._submit` hands the finished chunk to a worker
(:mod:`warpsim.usd.chunk_author`, through :mod:`warpsim.process_pool`). The writer then completes
the workers' chunks in order: renames each into place (the worker saved and synced it), and
indexes them and rewrites the root listing them in groups, so the crash-safety rules hold as when
the writer authors them itself: a chunk is listed only once complete, index and root agree.
"""
from __future__ import annotations

import os
import time

from ..core.safe_files import clear_temporary, disk_full
from . import chunk_index
from .value_types import pxr_modules as _pxr

__all__ = ["ROOT_EVERY", "WorkerChunks"]

ROOT_EVERY = 0.0
"""Seconds at least between two rewrites of the root while worker processes write the chunks,
besides eight times the last rewrite's time (a root of 2,000 worlds takes 0.4 s, one of a few
worlds a millisecond: its chunks are listed as they complete): completed chunks are listed in groups."""


class WorkerChunks:
    """Mixin of :class:`warpsim.usd.writer.UsdCacheWriter`: its chunks written by worker processes."""

    def _declare_specs(self, layer, manifest):  # pragma: no cover - the writer's own (UsdCacheWriter)
        raise NotImplementedError

    def _start_pool(self):
        """Start the ``workers`` processes and the shared memory pool of their chunks."""
        from ..process_pool import BlockPool, ProcessPool

        self._pool = ProcessPool(self.workers)
        self._blocks = BlockPool()  # the shared memory of written chunks, reused by the next ones

    def _chunk_specs(self) -> str:
        """A chunk's specs (``_declare_specs(manifest=True)``) as ``.usda`` text, made once (the
        manifest's text, kept by ``_seal``)."""
        if self._specs_text is None:
            Sdf, _, _ = _pxr()
            layer = Sdf.Layer.CreateAnonymous(".usda")
            self._declare_specs(layer, manifest=True)
            self._specs_text = layer.ExportToString()
        return self._specs_text

    def _warm_workers(self):
        """Have each worker parse a chunk's specs now (:func:`warpsim.usd.chunk_author.prepare_specs`),
        while this process steps: with many worlds that parse takes seconds a chunk's job then skips."""
        text = self._chunk_specs()
        for _ in range(self.workers):
            self._pool.submit("warpsim.usd.chunk_author:prepare_specs", text)

    def _submit(self, chunk):
        """Hand a staged chunk to a worker; complete the chunks already done (in order) and wait
        for the oldest while more than ``workers`` are out (their samples hold memory)."""
        clear_temporary(chunk.tmp_path)  # a leftover, or a planted link: removed, never followed
        job = chunk.stage.job(chunk.tmp_path, self._chunk_specs(), self.save_bytes, self.durable)
        self._inflight.append((chunk, self._pool.submit("warpsim.usd.chunk_author:author_chunk", job)))
        self._reap(wait_all=False)

    def _reap(self, wait_all):
        """Complete the workers' chunks in order (``wait_all``: every chunk out; else those done,
        and the oldest while more than ``workers`` are out): rename each into place, then index
        them and rewrite the root once listing them all, at most every few root writes' time
        (a root of many worlds takes a while to write) and always when ``wait_all``."""
        while self._inflight:
            chunk, future = self._inflight[0]
            if not (wait_all or future.done() or len(self._inflight) > self.workers):
                break
            self._inflight.popleft()
            self._complete(chunk, future)
        if self._unlisted and (wait_all or time.monotonic() >= self._root_due):
            self._list_completed()

    def _complete(self, chunk, future):
        """Wait for a worker's chunk and rename it into place (listed later: :meth:`_list_completed`)."""
        from ..process_pool import RemoteError

        self._target = chunk.final_path
        try:
            chunk.digest = future.result()  # the file's (size, CRC-32), read by the worker
        except RemoteError as exc:  # the worker's error, as this process would have raised it
            code = exc.errno if exc.errno is not None else disk_full(exc)
            if code is not None or exc.kind in ("OSError", "FileNotFoundError", "PermissionError"):
                raise OSError(code, f"{exc} ({os.path.basename(chunk.tmp_path)})") from None
            raise RuntimeError(f"writing {os.path.basename(chunk.final_path)}: {exc.kind}: {exc}") from None
        finally:
            chunk.stage.release()
        self._replace(chunk.tmp_path, chunk.final_path, synced=True, sync_folder=False)  # (the worker synced it)
        self._unlisted.append(chunk)

    def _list_completed(self):
        """Index the renamed chunks and rewrite the root listing them (a kill before this leaves
        them unlisted: a resumed run removes and rewrites them)."""
        done, self._unlisted = self._unlisted, []
        if self.durable:  # the renames made durable, once for the group, before anything lists them
            self._sync_folder()
        self._target = self._index_file
        for chunk in done:
            chunk_index.append_record(self._index_file, chunk_index.record(
                chunk.final_path, chunk.start, chunk.end, chunk.stats, self.run_id, chunk.digest), self.durable)
            self.chunks.append([chunk.start, chunk.end, os.path.basename(chunk.final_path)])
        t0 = time.monotonic()
        try:
            self._write_root()
        except BaseException:
            del self.chunks[-len(done):]  # the root on disk still lists the chunks before these
            raise
        self._root_due = time.monotonic() + max(ROOT_EVERY, 8.0 * (time.monotonic() - t0))

    def _stop_pool(self, wait=True):
        """End the chunk workers (after :meth:`flush`, or dropping what is out on a failure)."""
        pool, self._pool = self._pool, None
        if pool is not None:
            pool.close(wait=wait)
        blocks, self._blocks = self._blocks, None
        if blocks is not None:
            blocks.close()
