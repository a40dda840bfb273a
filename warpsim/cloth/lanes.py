"""Blocks of the cloth "lanes" step (``kernels/cloth_lanes.py``), built once per model on the host.

Particles are grouped by the pattern of their CSR spring row (entry k joins particle p to
p + delta_k, in the row's order); each pattern's particles are cut into blocks of eight: runs of
eight consecutive indices first (their loads are contiguous), the rest eight at a time in index
order, the last block of a pattern padded with repeats of its first particle. Consecutive
blocks come first.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..kernels.cloth_lanes import LANES, ROW_MAX


@dataclass
class LaneBlocks:
    """Host arrays of the lanes step. ``particles`` (blocks, 8) int32; ``info`` (blocks, 4) int32 =
    (first pattern entry, row length, first slot, consecutive 0/1); ``deltas`` (entries,) int32;
    ``slot_springs`` (slots, 8) int32: the spring of each lane's row entry; ``utilisation``:
    particles / lanes; the first ``runs`` blocks are the consecutive ones."""

    particles: np.ndarray
    info: np.ndarray
    deltas: np.ndarray
    slot_springs: np.ndarray
    utilisation: float
    runs: int


def row_patterns(offsets: np.ndarray, springs: np.ndarray, ends: np.ndarray, n: int):
    """(pattern id per particle, patterns (count, ROW_MAX) of deltas, row lengths per pattern)
    for a CSR spring list with rows of at most ROW_MAX entries (ends: (springs, 2))."""
    lengths = np.diff(offsets)
    row = np.repeat(np.arange(n), lengths)
    other = np.where(ends[springs, 0] == row, ends[springs, 1], ends[springs, 0])
    keys = np.zeros((n, ROW_MAX + 1), dtype=np.int64)
    keys[:, 0] = lengths
    position = np.arange(len(springs)) - offsets[row]
    keys[row, 1 + position] = other - row
    patterns, pid = np.unique(keys, axis=0, return_inverse=True)
    return pid.reshape(-1), patterns[:, 1:], patterns[:, 0]


def _cut(ids: np.ndarray):
    """(runs of eight consecutive ids as their first ids, the other ids in order)."""
    firsts, rest = [], []
    if len(ids) == 0:
        return firsts, ids
    breaks = np.flatnonzero(np.diff(ids) != 1) + 1
    for run in np.split(ids, breaks):
        full = len(run) // LANES * LANES
        firsts.extend(run[:full:LANES].tolist())
        rest.append(run[full:])
    return firsts, np.concatenate(rest)


def build_lane_blocks(offsets, springs, ends, n: int) -> LaneBlocks:
    """Blocks for the model's CSR spring list (``particle_spring_offsets``, ``particle_springs``,
    ``spring_indices`` as (springs, 2)); raises ValueError when a row is longer than ROW_MAX."""
    offsets, springs = np.asarray(offsets, dtype=np.int64), np.asarray(springs, dtype=np.int64)
    ends = np.asarray(ends, dtype=np.int64).reshape(-1, 2)
    longest = int(np.diff(offsets).max()) if n else 0
    if longest > ROW_MAX:
        raise ValueError(f"mode='lanes' handles particles with at most {ROW_MAX} springs; this model has a particle "
                         f"with {longest}; use mode='owner' or None (automatic)")
    pid, patterns, lengths = row_patterns(offsets, springs, ends, n)
    order = np.argsort(pid, kind="stable")
    bounds = np.searchsorted(pid[order], np.arange(len(patterns) + 1))
    blocks, info, deltas, slot_springs = [], [], [], []
    for t in range(len(patterns)):
        count = int(lengths[t])
        start = len(deltas)
        deltas.extend(patterns[t, :count].tolist())
        firsts, rest = _cut(order[bounds[t]:bounds[t + 1]])
        chunks = [(np.arange(f, f + LANES), 1) for f in firsts]
        for a in range(0, len(rest), LANES):
            chunk = rest[a:a + LANES]
            chunks.append((np.concatenate([chunk, np.repeat(chunk[:1], LANES - len(chunk))]), 0))
        for lanes, run in chunks:
            info.append((start, count, len(slot_springs), run))
            blocks.append(lanes)
            slot_springs.extend(springs[offsets[lanes][None, :] + np.arange(count)[:, None]].tolist())
    info_array = np.array(info, dtype=np.int32).reshape(-1, 4)
    order = np.argsort(-info_array[:, 3], kind="stable")  # runs first
    particles = np.array(blocks, dtype=np.int32).reshape(-1, LANES)[order]
    return LaneBlocks(particles, info_array[order], np.array(deltas or [0], dtype=np.int32),
                      np.array(slot_springs, dtype=np.int32).reshape(-1, LANES), n / max(particles.size, 1),
                      int(info_array[:, 3].sum()))
