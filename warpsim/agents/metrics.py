"""Flock and crowd metrics on the host (NumPy): polarization, radius of gyration, nearest-neighbour
distances and segregation."""

from __future__ import annotations

import numpy as np


# --------------------------------------------------------------------------------------
# Metrics (host, NumPy)
# --------------------------------------------------------------------------------------
def polarization(velocities) -> float:
    """Order parameter phi = |sum of unit headings| / n in [0, 1] (= |sum v| / (n v0) at a
    common speed v0); about 0.92 / sqrt(n) for random headings in 3-D."""
    v = np.asarray(velocities, dtype=np.float64).reshape(-1, 3)
    s = np.linalg.norm(v, axis=1)
    u = v[s > 0] / s[s > 0, None]
    return float(np.linalg.norm(u.sum(axis=0)) / max(len(v), 1))


def radius_of_gyration(positions) -> float:
    """sqrt(mean |x - mean(x)|^2) [m]."""
    x = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    return float(np.sqrt(((x - x.mean(axis=0)) ** 2).sum(axis=1).mean()))


def _pair_deltas(x, rows, box):
    d = x[None, :, :] - x[rows, None, :]
    if box is not None:
        lo, hi, wrap = box
        L = np.asarray(hi) - np.asarray(lo)
        for ax in range(3):
            if wrap[ax]:
                d[..., ax] -= L[ax] * np.round(d[..., ax] / L[ax])
    return d


def nearest_distances(positions, box=None, mask=None, chunk=512) -> np.ndarray:
    """Distance [m] from each agent to its nearest other agent (minimum image for a periodic
    ``box`` = (lower, upper, wrap flags), e.g. ``flock.box``); ``mask(i_rows, j)`` (bool (r, n))
    restricts the pairs. O(n^2) in chunks."""
    x = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    n = len(x)
    out = np.full(n, np.inf)
    for start in range(0, n, chunk):
        rows = np.arange(start, min(start + chunk, n))
        dist = np.linalg.norm(_pair_deltas(x, rows, box), axis=2)
        dist[np.arange(len(rows)), rows] = np.inf
        if mask is not None:
            dist = np.where(mask(rows), dist, np.inf)
        out[rows] = dist.min(axis=1)
    return out


def same_group_fraction(positions, groups, k=5, box=None) -> float:
    """Mean share of each agent's k nearest neighbours that belong to its own group (species):
    segregation index, compared with the share expected for a random mixture."""
    x = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    g = np.asarray(groups)
    n = len(x)
    total = 0.0
    for start in range(0, n, 512):
        rows = np.arange(start, min(start + 512, n))
        dist = np.linalg.norm(_pair_deltas(x, rows, box), axis=2)
        dist[np.arange(len(rows)), rows] = np.inf
        nn = np.argsort(dist, axis=1)[:, :k]
        total += (g[nn] == g[rows, None]).sum()
    return float(total / (n * k))
