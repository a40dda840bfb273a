"""Preconditioned conjugate-gradient kernels for 3x3 block systems (``warpsim.core.block_cg``):
every scalar lives on the device (``scalars`` = [r.z, r.r, p.Ap, (r.z)_new, tol^2, |b|^2]), so a
solve runs eagerly or inside a graph capture. Dot products are block partial sums added in a
fixed order, so the iteration count and the result are bit-reproducible."""

import warp as wp

wp.set_module_options({"enable_backward": False})

DOT_BLOCK = wp.constant(256)


@wp.kernel
def cg_dots(
    a: wp.array(dtype=wp.vec3),
    b: wp.array(dtype=wp.vec3),
    c: wp.array(dtype=wp.vec3),
    d: wp.array(dtype=wp.vec3),
    stride: int,
    slot_cd: int,
    partial_out: wp.array(dtype=float),
):
    """Block partial sums of a_i . b_i into partial_out[block] and, when slot_cd >= 0, of c_i . d_i
    into partial_out[blocks + block]. Launched with dim (blocks, DOT_BLOCK) and block_dim
    DOT_BLOCK: each thread strides over the arrays by ``stride`` = blocks * DOT_BLOCK, then a
    block-wide tile sum (a fixed tree) gives the block's value, added once onto the zero slot
    (exact); ``cg_sum_partials`` adds the blocks in a fixed order and clears the slots (the same
    bits every run; no allocation, so it can sit inside a conditional graph node)."""
    block, lane = wp.tid()
    i = block * DOT_BLOCK + lane
    n = a.shape[0]
    ab = float(0.0)  # noqa: UP018 (a mutable loop variable in Warp)
    cd = float(0.0)  # noqa: UP018
    while i < n:
        ab += wp.dot(a[i], b[i])
        if slot_cd >= 0:
            cd += wp.dot(c[i], d[i])
        i += stride
    # one add per slot onto 0 (cg_sum_partials clears them): exact, so order does not matter
    wp.tile_atomic_add(partial_out, wp.tile_sum(wp.tile(ab)), offset=block)
    if slot_cd >= 0:
        wp.tile_atomic_add(partial_out, wp.tile_sum(wp.tile(cd)), offset=stride / DOT_BLOCK + block)


@wp.kernel
def cg_sum_partials(partials: wp.array(dtype=float), blocks: int, slot_ab: int, slot_cd: int,
                    scalars_io: wp.array(dtype=float)):
    """scalars[slot_ab] += the ``blocks`` partial sums of ``cg_dots`` (and scalars[slot_cd] += the
    second set when slot_cd >= 0), clearing them. One block of DOT_BLOCK threads (dim (1,
    DOT_BLOCK)): lane l adds partials l, l + DOT_BLOCK, ... in order, a tile sum (a fixed tree)
    adds the lanes, and one add lands on the slot, which the caller cleared: the same bits every
    run."""
    block, lane = wp.tid()
    ab = float(0.0)  # noqa: UP018
    cd = float(0.0)  # noqa: UP018
    k = lane
    while k < blocks:
        ab += partials[k]
        partials[k] = 0.0
        if slot_cd >= 0:
            cd += partials[blocks + k]
            partials[blocks + k] = 0.0
        k += DOT_BLOCK
    wp.tile_atomic_add(scalars_io, wp.tile_sum(wp.tile(ab)), offset=slot_ab)
    if slot_cd >= 0:
        wp.tile_atomic_add(scalars_io, wp.tile_sum(wp.tile(cd)), offset=slot_cd)


@wp.kernel
def cg_start(
    b: wp.array(dtype=wp.vec3),
    inverse: wp.array(dtype=wp.mat33),
    x_out: wp.array(dtype=wp.vec3),
    r_out: wp.array(dtype=wp.vec3),
    z_out: wp.array(dtype=wp.vec3),
    p_out: wp.array(dtype=wp.vec3),
    scalars_out: wp.array(dtype=float),
):
    """x = 0, r = b, z = P^-1 r, p = z; clears the dot-product slots r.z and r.r."""
    i = wp.tid()
    if i == 0:
        scalars_out[0] = 0.0
        scalars_out[1] = 0.0
    r = b[i]
    z = inverse[i] * r
    x_out[i] = wp.vec3()
    r_out[i] = r
    z_out[i] = z
    p_out[i] = z


@wp.kernel
def cg_init_scalars(
    scalars: wp.array(dtype=float),
    rtol: float,
    atol: float,
    max_iterations: int,
    iteration_out: wp.array(dtype=int),
    condition_out: wp.array(dtype=int),
):
    """scalars = [r.z, r.r, p.Ap, (r.z)_new, tol^2, b.b]: tol^2 = max(atol, rtol |b|)^2 with
    |b|^2 = r.r at the start; iteration = 0; condition = (r.r > tol^2 and max_iterations > 0);
    clears the p.Ap slot."""
    bb = scalars[1]
    scalars[2] = 0.0
    tol = wp.max(atol, rtol * wp.sqrt(bb))
    scalars[4] = tol * tol
    scalars[5] = bb
    iteration_out[0] = 0
    c = 0
    if bb > tol * tol and max_iterations > 0:
        c = 1
    condition_out[0] = c


@wp.kernel
def cg_update_x_r(
    scalars: wp.array(dtype=float),
    p: wp.array(dtype=wp.vec3),
    Ap: wp.array(dtype=wp.vec3),
    inverse: wp.array(dtype=wp.mat33),
    x_io: wp.array(dtype=wp.vec3),
    r_io: wp.array(dtype=wp.vec3),
    z_out: wp.array(dtype=wp.vec3),
):
    """alpha = r.z / p.Ap; x += alpha p; r -= alpha Ap; z = P^-1 r; clears the r.r and (r.z)_new
    slots (read by nobody here) for the dot products that follow."""
    i = wp.tid()
    if i == 0:
        scalars[1] = 0.0
        scalars[3] = 0.0
    pAp = scalars[2]
    alpha = 0.0
    if pAp > 0.0:
        alpha = scalars[0] / pAp
    x_io[i] = x_io[i] + alpha * p[i]
    r = r_io[i] - alpha * Ap[i]
    r_io[i] = r
    z_out[i] = inverse[i] * r


@wp.kernel
def cg_update_p(scalars: wp.array(dtype=float), z: wp.array(dtype=wp.vec3), p_io: wp.array(dtype=wp.vec3)):
    """beta = (r.z)_new / r.z; p = z + beta p."""
    i = wp.tid()
    rz = scalars[0]
    beta = 0.0
    if rz > 0.0:
        beta = scalars[3] / rz
    p_io[i] = z[i] + beta * p_io[i]


@wp.kernel
def cg_end_iteration(
    scalars: wp.array(dtype=float),
    max_iterations: int,
    iteration_io: wp.array(dtype=int),
    condition_out: wp.array(dtype=int),
):
    """r.z <- (r.z)_new; iteration += 1; condition = (r.r > tol^2 and iteration < max); clears
    the p.Ap slot."""
    scalars[0] = scalars[3]
    scalars[2] = 0.0
    it = iteration_io[0] + 1
    iteration_io[0] = it
    c = 0
    if scalars[1] > scalars[4] and it < max_iterations:
        c = 1
    condition_out[0] = c
