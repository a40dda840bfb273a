"""Geometric multigrid transfers for the MAC-grid pressure Poisson operator (McAdams, Sifakis &
Teran 2010, "A parallel multigrid Poisson solver for fluids simulation on large grids").

Levels halve the cell counts of the coarsened axes (ceil(n / 2): an odd count is padded by one
cell that has no children). Prolongation P is cell-centred multilinear interpolation (weights
3/4, 1/4 per coarsened axis; a neighbour beyond the grid is clamped to the edge cell, which
mirrors the value across the wall); restriction is exactly ``scale * P^T`` (gathered, so no
atomics and a bitwise fixed linear map). Both only couple FLUID fine cells to FLUID coarse
cells, so AIR (Dirichlet, q = 0) and SOLID (Neumann) cells stay out of the coarse problems.
Flat vectors use the (i ny + j) nz + k layout of kernels/grid.py.
"""

import warp as wp

from .grid import AIR, FLUID, SOLID, cell_of

wp.set_module_options({"enable_backward": False})


@wp.kernel
def coarsen_labels(
    fine: wp.array3d(dtype=int), coarsen: wp.vec3i, air_first: int, coarse_out: wp.array3d(dtype=int)
):
    """Coarse label: AIR if any child is AIR, else FLUID if any is FLUID, else SOLID
    (``air_first`` = 0: FLUID first, then AIR; ``coarsen[a]`` = 1 where axis a is halved)."""
    I, J, K = wp.tid()
    has_fluid = int(0)
    has_air = int(0)
    for a in range(1 + coarsen[0]):
        for b in range(1 + coarsen[1]):
            for c in range(1 + coarsen[2]):
                i = I * (1 + coarsen[0]) + a
                j = J * (1 + coarsen[1]) + b
                k = K * (1 + coarsen[2]) + c
                if i < fine.shape[0] and j < fine.shape[1] and k < fine.shape[2]:
                    lab = fine[i, j, k]
                    if lab == FLUID:
                        has_fluid = 1
                    elif lab == AIR:
                        has_air = 1
    label = SOLID
    if has_fluid != 0 and (air_first == 0 or has_air == 0):
        label = FLUID
    elif has_air != 0:
        label = AIR
    coarse_out[I, J, K] = label


@wp.func
def _axis_weight(i: int, ci: int, n_coarse: int, coarsened: int) -> float:
    """P[i, ci] along one axis: fine cell i from coarse cell ci."""
    if coarsened == 0:
        return wp.where(i == ci, 1.0, 0.0)
    home = i / 2
    other = wp.clamp(home + 2 * (i % 2) - 1, 0, n_coarse - 1)
    w = float(0.0)
    if ci == home:
        w += 0.75
    if ci == other:
        w += 0.25
    return w


@wp.kernel
def restrict_residual(
    fine_labels: wp.array3d(dtype=int),
    coarse_labels: wp.array3d(dtype=int),
    r_fine: wp.array(dtype=float),
    coarsen: wp.vec3i,
    scale: float,
    b_coarse_out: wp.array(dtype=float),
):
    """b_coarse = scale P^T r_fine on FLUID coarse cells (0 elsewhere)."""
    I, J, K = wp.tid()
    cs = coarse_labels.shape
    fs = fine_labels.shape
    s = float(0.0)
    if coarse_labels[I, J, K] == FLUID:
        lo = wp.vec3i(I, J, K)
        hi = wp.vec3i(I, J, K)
        for a in range(3):
            if coarsen[a] != 0:
                lo[a] = wp.max(2 * lo[a] - 1, 0)
                hi[a] = wp.min(2 * hi[a] + 2, fs[a] - 1)
        for i in range(lo[0], hi[0] + 1):
            wx = _axis_weight(i, I, cs[0], coarsen[0])
            for j in range(lo[1], hi[1] + 1):
                wy = _axis_weight(j, J, cs[1], coarsen[1])
                for k in range(lo[2], hi[2] + 1):
                    w = wx * wy * _axis_weight(k, K, cs[2], coarsen[2])
                    if w != 0.0 and fine_labels[i, j, k] == FLUID:
                        s += w * r_fine[(i * fs[1] + j) * fs[2] + k]
    b_coarse_out[(I * cs[1] + J) * cs[2] + K] = scale * s


@wp.kernel
def prolong_add(
    fine_labels: wp.array3d(dtype=int),
    coarse_labels: wp.array3d(dtype=int),
    x_coarse: wp.array(dtype=float),
    coarsen: wp.vec3i,
    x_fine_io: wp.array(dtype=float),
):
    """x_fine += P x_coarse on FLUID fine cells (coarse values read from FLUID coarse cells only)."""
    i, j, k = wp.tid()
    fs = fine_labels.shape
    if fine_labels[i, j, k] != FLUID:
        return
    cs = coarse_labels.shape
    f = wp.vec3i(i, j, k)
    home = wp.vec3i(0)
    other = wp.vec3i(0)
    for a in range(3):
        if coarsen[a] != 0:
            home[a] = f[a] / 2
            other[a] = wp.clamp(home[a] + 2 * (f[a] % 2) - 1, 0, cs[a] - 1)
        else:
            home[a] = f[a]
            other[a] = f[a]
    s = float(0.0)
    for a in range(2):
        ci = wp.where(a == 0, home[0], other[0])
        wx = wp.where(a == 0, wp.where(coarsen[0] != 0, 0.75, 1.0), wp.where(coarsen[0] != 0, 0.25, 0.0))
        for b in range(2):
            cj = wp.where(b == 0, home[1], other[1])
            wy = wp.where(b == 0, wp.where(coarsen[1] != 0, 0.75, 1.0), wp.where(coarsen[1] != 0, 0.25, 0.0))
            for c in range(2):
                ck = wp.where(c == 0, home[2], other[2])
                wz = wp.where(c == 0, wp.where(coarsen[2] != 0, 0.75, 1.0), wp.where(coarsen[2] != 0, 0.25, 0.0))
                w = wx * wy * wz
                if w != 0.0 and coarse_labels[ci, cj, ck] == FLUID:
                    s += w * x_coarse[(ci * cs[1] + cj) * cs[2] + ck]
    x_fine_io[(i * fs[1] + j) * fs[2] + k] += s


@wp.kernel
def sum_fluid_closed(labels: wp.array3d(dtype=int), domain_sums: wp.array(dtype=float), x: wp.array(dtype=float),
                     partial_out: wp.array2d(dtype=float)):
    """partial_out[s, 0] = sum of x[c] over the FLUID cells c = s, s + S, ... (S slots, one thread
    each, index order), only in a closed domain (``domain_sums`` from grid.fluid_sums: [2] = 0 FLUID
    faces on AIR, [1] > 0 FLUID cells; else 0); the host folds the slots in a fixed order
    (``warpsim.core.reduction``), so the sum is the same bits every run."""
    s = wp.tid()
    total = float(0.0)
    if domain_sums[2] == 0.0 and domain_sums[1] > 0.0:
        count = labels.shape[0] * labels.shape[1] * labels.shape[2]
        c = s
        while c < count:
            cell = cell_of(c, labels.shape[1], labels.shape[2])
            if labels[cell[0], cell[1], cell[2]] == FLUID:
                total += x[c]
            c += partial_out.shape[0]
    partial_out[s, 0] = total


@wp.kernel
def remove_fluid_mean_closed(labels: wp.array3d(dtype=int), domain_sums: wp.array(dtype=float),
                             x_sum: wp.array(dtype=float), x_in: wp.array(dtype=float), x_out: wp.array(dtype=float)):
    """x_out = x_in minus its FLUID mean (x_sum[0] / FLUID count) in a closed domain, else x_in
    (the orthogonal projection off the Neumann null space, constants on the FLUID cells)."""
    i, j, k = wp.tid()
    c = (i * labels.shape[1] + j) * labels.shape[2] + k
    v = x_in[c]
    if domain_sums[2] == 0.0 and domain_sums[1] > 0.0 and labels[i, j, k] == FLUID:
        v = v - x_sum[0] / domain_sums[1]
    x_out[c] = v
