"""Occupancy records of batched worlds: which cells of a grid each world's particles occupy, frame
by frame, as bits (``warpsim/browse/occupancy.py`` drives these kernels).

Grid: cubic cells of side ``h`` [m] from corner ``lo`` [m], ``dims`` cells per axis counting one
extra layer on each side for everything beyond the grid (cell coordinate 0 and dims - 1), so
a particle outside the grid still marks the outside layer it lies in. Cell index
``(cx * dims.y + cy) * dims.z + cz``.

Bits: ``block_bits[w * cell_count + c]`` (uint32) has bit ``frame % 32`` set when a recorded
particle of world w lies in cell c during that frame. A frame first marks cells (plain stores of
the same value, ``record_cells``), then one thread per word sets the bit (``fold_cell_hits``): the
result does not depend on the order of the threads.

Inside the step (``CellMarks``): the shared-topology world step (``kernels/world_step.py``) marks
the cells of the positions it has just computed in registers at a frame's last sub-step (no second
pass over the positions); the block-per-world kernel then folds its own world's marks into the
bits after the block's barrier (one lane per word). Worlds flagged as blown up in that frame are
frozen at their last good positions after the step, so ``redo_blown_worlds`` re-marks them from
those, as a separate pass would have. Every 32 frames ``count_world_words`` and
``take_world_words`` compact the block's nonzero words on the device, world by world in cell
order, so only the occupied (cell, word) pairs move to the host.
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


@wp.struct
class CellMarks:
    """Where a stepping kernel marks the cells of a frame's final positions (``cell_hit``: world_count
    x cell_count, empty: marking off) and, for kernels that hold a whole world, folds them into
    ``bits`` (bit ``frame[0] % 32``). Grid as :func:`grid_cell`."""

    lo: wp.vec3
    inv_h: float
    dims: wp.vec3i
    cell_hit: wp.array(dtype=wp.uint8)
    bits: wp.array(dtype=wp.uint32)
    frame: wp.array(dtype=int)


@wp.func
def mark_cell(marks: CellMarks, w: int, x: wp.vec3):
    """World w's particle at ``x`` [m] marks its cell (a plain store of 1; nothing when marking is off)."""
    if marks.cell_hit.shape[0] > 0:
        c = grid_cell(x, marks.lo, marks.inv_h, marks.dims)
        if c >= 0:
            marks.cell_hit[w * (marks.dims[0] * marks.dims[1] * marks.dims[2]) + c] = wp.uint8(1)


@wp.func
def fold_world_marks(marks: CellMarks, w: int, lane: int, lanes: int):
    """Lane ``lane`` of ``lanes`` folds world w's marked cells lane, lane + lanes, ... into bit
    ``frame[0] % 32`` of their words and clears the marks (one writer per word)."""
    if marks.cell_hit.shape[0] > 0:
        cell_count = marks.dims[0] * marks.dims[1] * marks.dims[2]
        bit = wp.uint32(1) << wp.uint32(marks.frame[0] % 32)
        c = lane
        while c < cell_count:
            i = w * cell_count + c
            if marks.cell_hit[i] != wp.uint8(0):
                marks.bits[i] = marks.bits[i] | bit
                marks.cell_hit[i] = wp.uint8(0)
            c += lanes


@wp.kernel
def redo_blown_worlds(
    positions: wp.array(dtype=wp.vec3),
    world_particle_count: int,
    world_blown_frame: wp.array(dtype=int),
    frame_counter: wp.array(dtype=int),
    lo: wp.vec3,
    inv_h: float,
    dims: wp.vec3i,
    frame: wp.array(dtype=int),
    block_bits: wp.array(dtype=wp.uint32),
):
    """One thread per world: a world flagged as blown up in this frame (``world_blown_frame[w] ==
    frame_counter[0]``) was frozen at its last good positions after the step had marked its cells:
    clear this frame's bit of its words and set it again from the positions it now has."""
    w = wp.tid()
    if world_blown_frame[w] != frame_counter[0]:
        return
    cell_count = dims[0] * dims[1] * dims[2]
    bit = wp.uint32(1) << wp.uint32(frame[0] % 32)
    keep = ~bit
    for c in range(cell_count):
        block_bits[w * cell_count + c] = block_bits[w * cell_count + c] & keep
    for p in range(world_particle_count):
        c = grid_cell(positions[w * world_particle_count + p], lo, inv_h, dims)
        if c >= 0:
            block_bits[w * cell_count + c] = block_bits[w * cell_count + c] | bit


@wp.kernel
def count_world_words(block_bits: wp.array(dtype=wp.uint32), cell_count: int, counts: wp.array(dtype=int)):
    """counts[w + 1] = the nonzero words of world w (counts[0] is left 0 for the running sum)."""
    w = wp.tid()
    n = int(0)
    for c in range(cell_count):
        if block_bits[w * cell_count + c] != wp.uint32(0):
            n += 1
    counts[w + 1] = n


@wp.kernel
def take_world_words(block_bits: wp.array(dtype=wp.uint32), cell_count: int, start: wp.array(dtype=int),
                     cells_out: wp.array(dtype=wp.uint32), words_out: wp.array(dtype=wp.uint32)):
    """World w's nonzero words in cell order go to ``start[w]`` .. (the running sum of
    :func:`count_world_words`) as (cell, word) pairs, and the block is cleared for the next 32 frames."""
    w = wp.tid()
    k = start[w]
    for c in range(cell_count):
        i = w * cell_count + c
        b = block_bits[i]
        if b != wp.uint32(0):
            cells_out[k] = wp.uint32(c)
            words_out[k] = b
            block_bits[i] = wp.uint32(0)
            k += 1
