"""Graph colouring for block-parallel solvers (``ws.VBD``): particles of one colour share no spring,
so a colour's particles can be updated at once.

:func:`greedy_colouring` is deterministic (Welsh-Powell order: most neighbours first, ties to the
lower index; each particle takes the smallest colour none of its neighbours has), so the same model
gets the same colours, hence the same bits, on every run. :func:`tile_colouring` repeats one body's
colours for copies of it (the 1,000-torus heap colours one torus), and :func:`colour_groups` lists
the particles colour by colour (CSR) in ascending index within a colour.
"""

from __future__ import annotations

import numpy as np


def greedy_colouring(particle_count: int, pairs) -> np.ndarray:
    """Colour of each particle, shape (particle_count,), int32 from 0, such that the two ends of every
    pair (springs (S, 2) particle indices) differ. ValueError for a pair out of range or joining a
    particle to itself."""
    n = int(particle_count)
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    if len(pairs):
        bad = np.flatnonzero((pairs.min(1) < 0) | (pairs.max(1) >= n))
        if len(bad):
            raise ValueError(f"colouring: pair {int(bad[0])} joins {pairs[bad[0]].tolist()}, outside particles "
                             f"0..{n - 1}; give pairs of the model's particles")
        same = np.flatnonzero(pairs[:, 0] == pairs[:, 1])
        if len(same):
            raise ValueError(f"colouring: pair {int(same[0])} joins particle {int(pairs[same[0], 0])} to itself; "
                             "remove it")
    both = np.concatenate([pairs, pairs[:, ::-1]]) if len(pairs) else np.zeros((0, 2), dtype=np.int64)
    order = np.lexsort((both[:, 1], both[:, 0]))
    both = both[order]
    offsets = np.searchsorted(both[:, 0], np.arange(n + 1))
    neighbours = both[:, 1]
    degree = np.diff(offsets)
    colour = np.full(n, -1, dtype=np.int64)
    for p in np.lexsort((np.arange(n), -degree)):  # most neighbours first, ties to the lower index
        taken = colour[neighbours[offsets[p]:offsets[p + 1]]]
        taken = np.unique(taken[taken >= 0])
        free = np.flatnonzero(np.arange(len(taken) + 1) != np.append(taken, -1)[: len(taken) + 1])
        colour[p] = int(free[0]) if len(free) else len(taken)
    return colour.astype(np.int32)


def tile_colouring(colours, copies: int) -> np.ndarray:
    """One body's colours (P,) repeated for ``copies`` copies laid end to end, shape (copies P,)
    (copies share no spring, so the colouring stays valid)."""
    return np.tile(np.asarray(colours, dtype=np.int32), int(copies))


def colour_groups(colours) -> tuple[np.ndarray, np.ndarray]:
    """(offsets (C + 1,), particles (P,)): colour c's particles are ``particles[offsets[c]:offsets[c + 1]]``,
    ascending."""
    colours = np.asarray(colours, dtype=np.int64)
    particles = np.argsort(colours, kind="stable").astype(np.int32)
    count = int(colours.max()) + 1 if len(colours) else 0
    offsets = np.searchsorted(colours[particles], np.arange(count + 1)).astype(np.int32)
    return offsets, particles
