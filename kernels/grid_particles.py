"""Bookkeeping for particles that live on a MAC grid (particle level set markers, FLIP particles):
per-cell counts with a rank for each particle, culling of crowded cells, and stream compaction of
the live particles. A particle is live when its ``alive`` value is non-zero and its index is below
count[0]."""

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


@wp.kernel
def count_per_cell(
    count: wp.array(dtype=int),
    pos: wp.array(dtype=wp.vec3),
    alive: wp.array(dtype=float),
    origin: wp.vec3,
    dx: float,
    cell_count_io: wp.array3d(dtype=int),
    rank_out: wp.array(dtype=int),
):
    """cell_count += 1 for the cell of every live particle; rank = its arrival order in that cell."""
    p = wp.tid()
    rank_out[p] = -1
    if p >= count[0] or alive[p] == 0.0:
        return
    c = particle_cell(pos[p], origin, 1.0 / dx, cell_count_io.shape[0], cell_count_io.shape[1],
                      cell_count_io.shape[2])
    rank_out[p] = wp.atomic_add(cell_count_io, c[0], c[1], c[2], 1)


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
