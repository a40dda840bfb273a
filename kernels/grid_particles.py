"""Bookkeeping for particles that live on a MAC grid (particle level set markers, FLIP particles):
per-cell counts, the particle list ordered by cell octant (a stable sort; the P2G gathers of
kernels/flip.py read it) with a rank for each particle, culling of crowded cells, appends in cell order and stream compaction of the live
particles: no output position depends on the order threads run in. A particle is live when its
``alive`` value is non-zero and its index is below count[0]."""

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.func
def particle_cell(x: wp.vec3, origin: wp.vec3, inv_dx: float, nx: int, ny: int, nz: int) -> wp.vec3i:
    """Index of the cell containing x [m], clamped into the grid."""
    g = (x - origin) * inv_dx
    return wp.vec3i(
        wp.clamp(int(wp.floor(g[0])), 0, nx - 1),
        wp.clamp(int(wp.floor(g[1])), 0, ny - 1),
        wp.clamp(int(wp.floor(g[2])), 0, nz - 1),
    )


@wp.func
def half_bit(g: float, c: int) -> int:
    """1 when continuous index g lies in the upper half of cell c (or beyond it), else 0."""
    return wp.where(g - float(c) >= 0.5, 1, 0)


@wp.kernel
def count_per_cell(
    count: wp.array(dtype=int),
    pos: wp.array(dtype=wp.vec3),
    alive: wp.array(dtype=float),
    origin: wp.vec3,
    dx: float,
    cell_count_io: wp.array3d(dtype=int),
    octant_count_io: wp.array(dtype=int),
    keys_out: wp.array(dtype=int),
    ids_out: wp.array(dtype=int),
):
    """cell_count += 1 for the cell of every live particle and octant_count += 1 for its octant
    (flat cell index * 8 + the halves it lies in: x + 2 y + 4 z; integer atomics: the counts do not
    depend on the order); keys = that octant index (8 x the cell count for a dead particle, so it
    sorts last) and ids = p, the pairs that a stable sort turns into the octant-ordered list."""
    p = wp.tid()
    nx = cell_count_io.shape[0]
    ny = cell_count_io.shape[1]
    nz = cell_count_io.shape[2]
    key = 8 * nx * ny * nz
    if p < count[0] and alive[p] != 0.0:
        x = pos[p]
        c = particle_cell(x, origin, 1.0 / dx, nx, ny, nz)
        g = (x - origin) / dx
        wp.atomic_add(cell_count_io, c[0], c[1], c[2], 1)
        key = ((c[0] * ny + c[1]) * nz + c[2]) * 8 + half_bit(g[0], c[0]) + 2 * half_bit(g[1], c[1]) + 4 * half_bit(
            g[2], c[2])
        wp.atomic_add(octant_count_io, key, 1)
    keys_out[p] = key
    ids_out[p] = p


@wp.func
def count_below(ids: wp.array(dtype=int), begin: int, end: int, p: int) -> int:
    """How many of the increasing values ids[begin:end] are below p (binary search)."""
    lo = int(begin)
    hi = int(end)
    while lo < hi:
        mid = (lo + hi) / 2
        if ids[mid] < p:
            lo = mid + 1
        else:
            hi = mid
    return lo - begin


@wp.kernel
def rank_in_cell(keys: wp.array(dtype=int), ids: wp.array(dtype=int), octant_start: wp.array(dtype=int),
                 octant_count: wp.array(dtype=int), rank_out: wp.array(dtype=int)):
    """rank of the particle at sorted position s = how many live particles of its cell have a
    smaller index (the octant lists hold increasing indices: the sort is stable; a binary search
    in each of the cell's 8 lists), -1 for dead particles."""
    s = wp.tid()
    key = keys[s]
    p = ids[s]
    rank = int(-1)
    if key < octant_start.shape[0]:
        rank = int(0)
        first = key - key % 8
        for o in range(first, first + 8):
            begin = octant_start[o]
            rank += count_below(ids, begin, begin + octant_count[o], p)
    rank_out[p] = rank


@wp.kernel
def advance_count(emitted: wp.array(dtype=int), offsets: wp.array(dtype=int), capacity: int,
                  count_io: wp.array(dtype=int), next_id_io: wp.array(dtype=int)):
    """After an append in cell order (counts ``emitted`` per cell, ``offsets`` their exclusive
    prefix sum): count += the appended total, next_id += those that fitted below ``capacity``."""
    last = emitted.shape[0] - 1
    total = offsets[last] + emitted[last]
    base = count_io[0]
    count_io[0] = base + total
    next_id_io[0] = next_id_io[0] + wp.max(0, wp.min(total, capacity - base))


@wp.kernel
def cull_crowded(rank: wp.array(dtype=int), max_per_cell: int, alive_io: wp.array(dtype=float)):
    """Kill particles whose rank in their cell is >= max_per_cell."""
    p = wp.tid()
    if rank[p] >= max_per_cell:
        alive_io[p] = 0.0


@wp.kernel
def mark_live(count: wp.array(dtype=int), alive: wp.array(dtype=float), flags_out: wp.array(dtype=int)):
    p = wp.tid()
    flag = int(0)
    if p < count[0] and alive[p] != 0.0:
        flag = 1
    flags_out[p] = flag


@wp.kernel
def compact_vec3(flags: wp.array(dtype=int), scan: wp.array(dtype=int), src: wp.array(dtype=wp.vec3),
                 dst: wp.array(dtype=wp.vec3)):
    """dst[scan[p] - 1] = src[p] for flagged p (scan: inclusive prefix sum of flags)."""
    p = wp.tid()
    if flags[p] != 0:
        dst[scan[p] - 1] = src[p]


@wp.kernel
def compact_float(flags: wp.array(dtype=int), scan: wp.array(dtype=int), src: wp.array(dtype=float),
                  dst: wp.array(dtype=float)):
    p = wp.tid()
    if flags[p] != 0:
        dst[scan[p] - 1] = src[p]


@wp.kernel
def compact_int(flags: wp.array(dtype=int), scan: wp.array(dtype=int), src: wp.array(dtype=int),
                dst: wp.array(dtype=int)):
    p = wp.tid()
    if flags[p] != 0:
        dst[scan[p] - 1] = src[p]


@wp.kernel
def set_live_count(scan: wp.array(dtype=int), count_out: wp.array(dtype=int)):
    count_out[0] = scan[scan.shape[0] - 1]
