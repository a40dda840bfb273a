"""Occupancy records of batched worlds: which cells of a grid each world's particles occupy, frame
by frame, as bits (``warpsim/worlds/occupancy.py`` drives these kernels).

Grid: cubic cells of side ``h`` [m] from corner ``lo`` [m], ``dims`` cells per axis counting one
extra layer on each side for everything beyond the grid (cell coordinate 0 and dims - 1), so
a particle outside the grid still marks the outside layer it lies in. Cell index
``(cx * dims.y + cy) * dims.z + cz``.

Bits: ``block_bits[w * cell_count + c]`` (uint32) has bit ``frame % 32`` set when a recorded
particle of world w lies in cell c during that frame. A frame first marks cells (plain stores of
the same value, ``record_cells``), then one thread per word sets the bit (``fold_cell_hits``): the
result does not depend on the order of the threads.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.func
def grid_cell(x: wp.vec3, lo: wp.vec3, inv_h: float, dims: wp.vec3i) -> int:
    """Index of the cell holding point ``x`` [m], the outside layers catching points beyond the
    grid; -1 for a non-finite point."""
    if not (wp.isfinite(x[0]) and wp.isfinite(x[1]) and wp.isfinite(x[2])):
        return -1
    c = wp.vec3i(0, 0, 0)
    for a in range(3):
        s = wp.floor((x[a] - lo[a]) * inv_h) + 1.0
        s = wp.clamp(s, 0.0, float(dims[a] - 1))
        c[a] = int(s)
    return (c[0] * dims[1] + c[1]) * dims[2] + c[2]


@wp.kernel
def record_cells(
    positions: wp.array(dtype=wp.vec3),
    world_particle_count: int,
    local_index: wp.array(dtype=int),
    lo: wp.vec3,
    inv_h: float,
    dims: wp.vec3i,
    frame: wp.array(dtype=int),
    frame_count: int,
    cell_hit: wp.array(dtype=wp.uint8),
    samples_out: wp.array(dtype=wp.vec3),
):
    """Launched over (world_count, K): particle ``w P + local_index[k]`` of world w marks its cell,
    ``cell_hit[w * cell_count + c] = 1`` (a plain store of the same value by every thread of the
    cell: no atomics, so a world's hundreds of particles in one cell do not serialise on one word);
    :func:`fold_cell_hits` then sets the frame's bit. When ``samples_out`` has entries, the position
    is also kept at ``samples_out[(w F + f) K + k]`` (F = frame_count, f = ``frame[0]``)."""
    w, k = wp.tid()
    K = local_index.shape[0]
    x = positions[w * world_particle_count + local_index[k]]
    f = frame[0]
    if samples_out.shape[0] > 0 and f < frame_count:
        samples_out[(w * frame_count + f) * K + k] = x
    c = grid_cell(x, lo, inv_h, dims)
    if c >= 0:
        cell_count = dims[0] * dims[1] * dims[2]
        cell_hit[w * cell_count + c] = wp.uint8(1)


@wp.kernel
def fold_cell_hits(cell_hit: wp.array(dtype=wp.uint8), frame: wp.array(dtype=int),
                   block_bits: wp.array(dtype=wp.uint32)):
    """One thread per (world, cell): a marked cell sets bit ``frame[0] % 32`` of its word (one
    writer per word) and the mark is cleared for the next frame."""
    i = wp.tid()
    if cell_hit[i] != wp.uint8(0):
        block_bits[i] = block_bits[i] | (wp.uint32(1) << wp.uint32(frame[0] % 32))
        cell_hit[i] = wp.uint8(0)


@wp.kernel
def next_record_frame(frame: wp.array(dtype=int)):
    """frame[0] += 1 (advanced inside a captured graph)."""
    frame[0] = frame[0] + 1
