"""Per-world picks over particles grouped by world, at once instead of one world at a time."""
from __future__ import annotations

import numpy as np

__all__ = ["any_per_world", "first_extreme"]


def first_extreme(values, order, start, largest=True):
    """Per world: (the particle holding its first largest (``largest``) or smallest value, as
    np.argmax / np.argmin over its particles in ``order`` picks it, -1 for a world without
    particles or with a NaN among its values; that value, NaN for those worlds). ``values``: one
    per particle; ``order``: the particles sorted by world (stably); ``start`` (W + 1,): each
    world's first position in ``order``."""
    values, order, start = np.asarray(values), np.asarray(order), np.asarray(start)
    W, n = len(start) - 1, len(order)
    index, extreme = np.full(W, -1, dtype=np.int64), np.full(W, np.nan)
    sizes = np.diff(start)
    full = np.flatnonzero(sizes > 0)
    if not len(full):
        return index, extreme
    v = values[order]
    ext = (np.maximum if largest else np.minimum).reduceat(v, start[full])  # NaN where a world holds one
    seg = np.repeat(np.arange(len(full)), sizes[full])
    first = np.minimum.reduceat(np.where(v == ext[seg], np.arange(n), n), start[full])
    found = first < n
    index[full[found]] = order[first[found]]
    extreme[full[found]] = ext[found]
    return index, extreme


def any_per_world(flags, order, start):
    """Per world: whether any of its particles' ``flags`` is set (``order``, ``start``: as
    :func:`first_extreme`; False for a world without particles)."""
    start = np.asarray(start)
    out = np.zeros(len(start) - 1, dtype=bool)
    full = np.flatnonzero(np.diff(start) > 0)
    if len(full):
        out[full] = np.add.reduceat(np.asarray(flags, dtype=np.int64)[np.asarray(order)], start[full]) > 0
    return out
