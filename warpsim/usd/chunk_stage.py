"""A chunk's samples gathered for a worker process (:mod:`warpsim.usd.chunk_author`).

The writing process calls :meth:`ChunkStage.add` with each field's values as it would author
them (one field: one attribute in every world; values ``(N, ...)`` arrays or ``N`` arrays of any
length), frame after frame; fixed-shape values are copied into shared memory (one block per
field, ``capacity`` frames long), others are kept as copies and pickled with the job.
:meth:`job` returns the :func:`warpsim.usd.chunk_author.chunk_job`; :meth:`release` frees the
shared memory once the worker has answered.
"""
from __future__ import annotations

import numpy as np

from ..process_pool import SharedBlock
from .chunk_author import chunk_job

__all__ = ["ChunkStage"]


class ChunkStage:
    """The samples of one chunk of at most ``capacity`` frames (see the module docstring);
    ``blocks``: a :class:`warpsim.process_pool.BlockPool` the shared memory comes from and goes
    back to (None: fresh blocks, freed by :meth:`release`)."""

    def __init__(self, capacity, blocks=None):
        self.capacity = int(capacity)
        self.pool = blocks
        self.times = []
        self.keys = {}  # field key -> index
        self.fields = []  # (paths, type_name, on_change)
        self.blocks = []  # per field: SharedBlock, or None (values kept in ``lists``)
        self.shapes = []  # per field: (shape, dtype) of one frame's values in its block
        self.lists = []  # per field: [frame][world] arrays (fields without a block)
        self._filled = 0  # fields given a value in the current frame

    @property
    def nbytes(self) -> int:
        """Bytes held in shared memory [bytes]."""
        return sum(b.nbytes for b in self.blocks if b is not None)

    def add(self, time, key, paths, type_name, on_change, values):
        """One field's values in the frame at ``time`` (a new time starts the next frame)."""
        if not self.times or self.times[-1] != time:
            self._check_frame()
            if len(self.times) >= self.capacity:
                raise ValueError(f"a chunk holds {self.capacity} frames; got a frame at time {time} beyond them")
            self.times.append(time)
            self._filled = 0
        f = len(self.times) - 1
        k = self.keys.get(key)
        if k is None:
            if f:
                raise ValueError(f"{paths[0]}: a value that the chunk's first frame did not have (frame at {time}); "
                                 "every time-varying attribute needs a value in every frame")
            k = self.keys[key] = len(self.fields)
            self.fields.append((list(paths), type_name, bool(on_change)))
            block = None
            if isinstance(values, np.ndarray) and values.size:
                size = self.capacity * values.nbytes
                block = self.pool.take(size) if self.pool is not None else SharedBlock(size)
            self.blocks.append(block)
            self.shapes.append((values.shape, values.dtype) if block is not None else None)
            self.lists.append([] if block is None else None)
        block = self.blocks[k]
        if block is not None and not (isinstance(values, np.ndarray) and (values.shape, values.dtype) == self.shapes[k]):
            self._to_list(k, f)  # a shape that changed: this field's frames are kept as copies from here on
            block = None
        if block is not None:
            shape, dtype = self.shapes[k]
            block.array(f * values.nbytes, shape, dtype)[...] = values
        else:
            self.lists[k].append([_copy(v) for v in values])
        self._filled += 1

    def _to_list(self, k, frames):
        shape, dtype = self.shapes[k]
        block = self.blocks[k]
        view = block.array(0, (self.capacity, *shape), dtype)
        self.lists[k] = [[_copy(v) for v in view[f]] for f in range(frames)]
        del view
        self._free(block)
        self.blocks[k] = None
        self.shapes[k] = None

    def _check_frame(self):
        if self.times and self._filled != len(self.fields):
            raise ValueError(f"the frame at time {self.times[-1]} gave {self._filled} of the chunk's "
                             f"{len(self.fields)} time-varying attributes; every one needs a value in every frame")

    def job(self, tmp_path, specs, save_bytes, durable) -> dict:
        """The worker's job for this chunk (the frames added so far)."""
        self._check_frame()
        frames = len(self.times)
        blocks = []
        for k, block in enumerate(self.blocks):
            if block is None:
                blocks.append(("list", self.lists[k]))
            else:
                shape, dtype = self.shapes[k]
                blocks.append(("shm", block.ref(0, (frames, *shape), dtype)))
        return chunk_job(tmp_path, specs, self.fields, self.times, blocks, save_bytes, durable)

    def release(self):
        """Free the shared memory (after the worker answered, or when the chunk is dropped)."""
        for block in self.blocks:
            if block is not None:
                self._free(block)
        self.blocks = [None] * len(self.blocks)

    def _free(self, block):
        if self.pool is not None:
            self.pool.give(block)
        else:
            block.release()


def _copy(value):
    """A value kept for a later frame: arrays copied (the caller may reuse its buffer), scalars as given."""
    return np.array(value, copy=True) if isinstance(value, np.ndarray) else value
