"""FLIP/PIC kernels: particle-to-grid and grid-to-particle transfers on a MAC grid with trilinear
weights, cell labels from particles, reseeding of sparse interior cells, pushing particles out
of solids, a particle signed-distance field for the liquid surface, and the particle density and
divergence target of the volume (density) correction. Layout: kernels/advect.py;
particle bookkeeping: kernels/grid_particles.py.

Particle-to-grid sums (face velocities, particle density) are gathers over the cell-sorted particle
list in a fixed order, so a run is bit-reproducible on every device; the scatters with float atomics
(``particles_to_grid``, ``particle_density``; faster on GPUs, the sum order then varies run to run)
serve ``FlipLiquid(deterministic=False)``."""

import warp as wp

from .advect import OFFSET_U, OFFSET_V, OFFSET_W, sample_at, sample_velocity
from .grid import AIR, FLUID, SOLID, axis_step, label_at

wp.set_module_options({"enable_backward": False})

CENTER = wp.constant(wp.vec3(0.5, 0.5, 0.5))


@wp.func
def hat_weight(g: float, node: int) -> float:
    """Weight of grid node ``node`` in the linear interpolation at continuous index g: 1 - t at
    floor(g), t at floor(g) + 1 (t = g - floor(g)), 0 elsewhere."""
    i0 = int(wp.floor(g))
    t = g - float(i0)
    w = float(0.0)
    if node == i0:
        w = 1.0 - t
    elif node == i0 + 1:
        w = t
    return w


@wp.func
def half_range(node: int, staggered: int, cells: int) -> wp.vec2i:
    """Half-cells (index 2 c + upper) whose particles can reach grid node ``node`` of one axis,
    clamped into the grid: cells node - 1 and node along a face's normal (``staggered``, nodes on
    cell faces), else the upper half of cell node - 1, cell node and the lower half of node + 1
    (nodes at cell centres). Returns (first, last)."""
    first = wp.where(staggered != 0, 2 * node - 2, 2 * node - 1)
    return wp.vec2i(wp.max(first, 0), wp.min(first + 3, 2 * cells - 1))


@wp.func
def octant_of(hx: int, hy: int, hz: int, ny: int, nz: int) -> int:
    """Octant index (flat cell * 8 + x + 2 y + 4 z halves) of half-cell indices (hx, hy, hz)."""
    return (((hx / 2) * ny + hy / 2) * nz + hz / 2) * 8 + hx % 2 + 2 * (hy % 2) + 4 * (hz % 2)


@wp.kernel
def gather_face_velocity(
    cell_count: wp.array3d(dtype=int),
    octant_start: wp.array(dtype=int),
    octant_count: wp.array(dtype=int),
    sorted_ids: wp.array(dtype=int),
    x: wp.array(dtype=wp.vec3),
    vel: wp.array(dtype=wp.vec3),
    axis: int,
    origin: wp.vec3,
    dx: float,
    f_out: wp.array3d(dtype=float),
):
    """P2G as a gather: face (i, j, k) of ``axis`` (u: 0, v: 1, w: 2) = sum_p w_p v_p[axis] /
    sum_p w_p over the particles whose trilinear stencil holds the face (0 where none does), w_p
    the trilinear weight. The candidates are the particles of the cell octants that can reach the
    face (:func:`half_range`), visited in octant order and, within one, by particle index
    (``GridParticles.count_cells``): a fixed order, so the sums are the same bits every run (float
    atomics add in arrival order). A one-cell-thick array (2D) weighs every particle 1 along z."""
    i, j, k = wp.tid()
    ny = cell_count.shape[1]
    nz = cell_count.shape[2]
    offset = wp.vec3(wp.where(axis == 0, 0.0, 0.5), wp.where(axis == 1, 0.0, 0.5), wp.where(axis == 2, 0.0, 0.5))
    flat_z = f_out.shape[2] == 1
    rx = half_range(i, wp.where(axis == 0, 1, 0), cell_count.shape[0])
    ry = half_range(j, wp.where(axis == 1, 1, 0), ny)
    rz = half_range(k, wp.where(axis == 2, 1, 0), nz)
    total = float(0.0)
    weight = float(0.0)
    for hx in range(rx[0], rx[1] + 1):
        for hy in range(ry[0], ry[1] + 1):
            for hz in range(rz[0], rz[1] + 1):
                o = octant_of(hx, hy, hz, ny, nz)
                start = octant_start[o]
                for e in range(start, start + octant_count[o]):
                    p = sorted_ids[e]
                    g = (x[p] - origin) / dx - offset
                    wa = hat_weight(g[0], i)
                    wb = wa * hat_weight(g[1], j)
                    wc = wb * wp.where(flat_z, 1.0, hat_weight(g[2], k))
                    if wc > 0.0:
                        total += wc * vel[p][axis]
                        weight += wc
    f_out[i, j, k] = wp.where(weight > 0.0, total / wp.max(weight, 1.0e-30), 0.0)


@wp.func
def _splat(sum_io: wp.array3d(dtype=float), weight_io: wp.array3d(dtype=float), g: wp.vec3, value: float):
    """Add value with trilinear weights at continuous index g (stencil nodes outside are skipped)."""
    i0 = int(wp.floor(g[0]))
    j0 = int(wp.floor(g[1]))
    k0 = int(wp.floor(g[2]))
    t = g - wp.vec3(float(i0), float(j0), float(k0))
    for a in range(2):
        i = i0 + a
        wa = wp.where(a == 0, 1.0 - t[0], t[0])
        if i >= 0 and i < sum_io.shape[0]:
            for b in range(2):
                j = j0 + b
                wb = wa * wp.where(b == 0, 1.0 - t[1], t[1])
                if j >= 0 and j < sum_io.shape[1]:
                    for c in range(2):
                        k = k0 + c
                        wc = wb * wp.where(c == 0, 1.0 - t[2], t[2])
                        if sum_io.shape[2] == 1:
                            k = 0
                            wc = wb * wp.where(c == 0, 1.0, 0.0)
                        if k >= 0 and k < sum_io.shape[2] and wc > 0.0:
                            wp.atomic_add(sum_io, i, j, k, wc * value)
                            wp.atomic_add(weight_io, i, j, k, wc)


@wp.kernel
def particles_to_grid(
    count: wp.array(dtype=int),
    x: wp.array(dtype=wp.vec3),
    vel: wp.array(dtype=wp.vec3),
    alive: wp.array(dtype=float),
    origin: wp.vec3,
    dx: float,
    u_sum: wp.array3d(dtype=float),
    u_weight: wp.array3d(dtype=float),
    v_sum: wp.array3d(dtype=float),
    v_weight: wp.array3d(dtype=float),
    w_sum: wp.array3d(dtype=float),
    w_weight: wp.array3d(dtype=float),
):
    """P2G scatter: accumulate weighted particle velocity components and weights on the faces with
    float atomics (``FlipLiquid(deterministic=False)``; the default gathers, :func:`gather_face_velocity`)."""
    p = wp.tid()
    if p >= count[0] or alive[p] == 0.0:
        return
    g = (x[p] - origin) / dx
    q = vel[p]
    _splat(u_sum, u_weight, g - OFFSET_U, q[0])
    _splat(v_sum, v_weight, g - OFFSET_V, q[1])
    _splat(w_sum, w_weight, g - OFFSET_W, q[2])


@wp.kernel
def normalize_faces(sum_: wp.array3d(dtype=float), weight: wp.array3d(dtype=float), f_out: wp.array3d(dtype=float)):
    """f = sum / weight where some particle contributed, else 0."""
    i, j, k = wp.tid()
    w = weight[i, j, k]
    f_out[i, j, k] = wp.where(w > 0.0, sum_[i, j, k] / wp.max(w, 1.0e-30), 0.0)


@wp.kernel
def label_from_counts(cell_count: wp.array3d(dtype=int), solid_phi: wp.array3d(dtype=float),
                      labels_out: wp.array3d(dtype=int)):
    """SOLID inside solids, FLUID where particles are, else AIR."""
    i, j, k = wp.tid()
    label = AIR
    if solid_phi[i, j, k] < 0.0:
        label = SOLID
    elif cell_count[i, j, k] > 0:
        label = FLUID
    labels_out[i, j, k] = label


@wp.kernel
def grid_to_particles(
    count: wp.array(dtype=int),
    x: wp.array(dtype=wp.vec3),
    alive: wp.array(dtype=float),
    flip_ratio: float,
    u: wp.array3d(dtype=float),
    v: wp.array3d(dtype=float),
    w: wp.array3d(dtype=float),
    u_old: wp.array3d(dtype=float),
    v_old: wp.array3d(dtype=float),
    w_old: wp.array3d(dtype=float),
    origin: wp.vec3,
    dx: float,
    vel_io: wp.array(dtype=wp.vec3),
):
    """G2P: v_p = r (v_p + u_new(x_p) - u_old(x_p)) + (1 - r) u_new(x_p), r the FLIP ratio
    (1 = pure FLIP, 0 = pure PIC)."""
    p = wp.tid()
    if p >= count[0] or alive[p] == 0.0:
        return
    inv_dx = 1.0 / dx
    new = sample_velocity(u, v, w, origin, inv_dx, x[p])
    old = sample_velocity(u_old, v_old, w_old, origin, inv_dx, x[p])
    vel_io[p] = flip_ratio * (vel_io[p] + new - old) + (1.0 - flip_ratio) * new


@wp.kernel
def push_out_of_solids(
    count: wp.array(dtype=int),
    solid_phi: wp.array3d(dtype=float),
    origin: wp.vec3,
    dx: float,
    x_io: wp.array(dtype=wp.vec3),
):
    """Particles inside a solid (trilinear solid_phi < 0) move out along its gradient."""
    p = wp.tid()
    if p >= count[0]:
        return
    inv_dx = 1.0 / dx
    x = x_io[p]
    d = sample_at(solid_phi, CENTER, origin, inv_dx, x)
    if d < 0.0:
        h = 0.5 * dx
        gx = sample_at(solid_phi, CENTER, origin, inv_dx, x + wp.vec3(h, 0.0, 0.0)) - sample_at(
            solid_phi, CENTER, origin, inv_dx, x - wp.vec3(h, 0.0, 0.0))
        gy = sample_at(solid_phi, CENTER, origin, inv_dx, x + wp.vec3(0.0, h, 0.0)) - sample_at(
            solid_phi, CENTER, origin, inv_dx, x - wp.vec3(0.0, h, 0.0))
        gz = sample_at(solid_phi, CENTER, origin, inv_dx, x + wp.vec3(0.0, 0.0, h)) - sample_at(
            solid_phi, CENTER, origin, inv_dx, x - wp.vec3(0.0, 0.0, h))
        n = wp.vec3(gx, gy, gz)
        ln = wp.length(n)
        if ln > 0.0:
            x_io[p] = x - (d - 0.01 * dx) * n / ln


@wp.kernel
def reseed_interior(
    cell_count: wp.array3d(dtype=int),
    labels: wp.array3d(dtype=int),
    open_mask: int,
    min_per_cell: int,
    density: wp.array3d(dtype=float),
    min_density: float,
    seed: int,
    dim: int,
    u: wp.array3d(dtype=float),
    v: wp.array3d(dtype=float),
    w: wp.array3d(dtype=float),
    origin: wp.vec3,
    dx: float,
    count: wp.array(dtype=int),
    next_id: wp.array(dtype=int),
    write: int,
    emitted_io: wp.array(dtype=int),
    offsets: wp.array(dtype=int),
    x_out: wp.array(dtype=wp.vec3),
    vel_out: wp.array(dtype=wp.vec3),
    alive_out: wp.array(dtype=float),
    id_out: wp.array(dtype=int),
):
    """Interior FLUID cells (every neighbour FLUID or SOLID) holding fewer than min_per_cell
    particles and whose hat-weighted ``density`` is below ``min_density`` (pass a huge value to
    ignore it) get new ones at random positions with the grid velocity. Two passes append in cell
    order: write = 0 stores each cell's new-particle count in emitted_io[cell] (flat index; zero it
    first), write = 1 puts particle m' of the cell at slot count[0] + offsets[cell] + m' with id
    next_id[0] + offsets[cell] + m' (offsets: exclusive prefix sum of the counts), up to the arrays'
    capacity; the host then advances count[0] and next_id[0] (``GridParticles.finish_append``)."""
    i, j, k = wp.tid()
    n = cell_count[i, j, k]
    if labels[i, j, k] != FLUID or n >= min_per_cell or density[i, j, k] >= min_density:
        return
    c = wp.vec3i(i, j, k)
    for a in range(dim):
        for s in range(2):
            if label_at(labels, open_mask, c + axis_step(a) * (2 * s - 1)) == AIR:
                return
    flat = (i * labels.shape[1] + j) * labels.shape[2] + k
    if write == 0:
        emitted_io[flat] = min_per_cell - n
        return
    inv_dx = 1.0 / dx
    lower = origin + wp.vec3(float(i), float(j), float(k)) * dx
    for m in range(n, min_per_cell):
        state = wp.rand_init(seed, flat * min_per_cell + m)
        x = lower + wp.vec3(wp.randf(state), wp.randf(state), wp.randf(state)) * dx
        if dim == 2:
            x = wp.vec3(x[0], x[1], origin[2] + 0.5 * dx)
        rank = offsets[flat] + m - n
        slot = count[0] + rank
        if slot < x_out.shape[0]:
            x_out[slot] = x
            vel_out[slot] = sample_velocity(u, v, w, origin, inv_dx, x)
            alive_out[slot] = 1.0
            id_out[slot] = next_id[0] + rank


@wp.kernel
def particle_sdf(
    count: wp.array(dtype=int),
    x: wp.array(dtype=wp.vec3),
    alive: wp.array(dtype=float),
    radius: float,
    origin: wp.vec3,
    dx: float,
    phi_io: wp.array3d(dtype=float),
):
    """phi = min(phi, |x_c - x_p| - radius) at the cell centres within 2 cells of each particle
    (the union of particle spheres; initialise phi to a positive cap first)."""
    p = wp.tid()
    if p >= count[0] or alive[p] == 0.0:
        return
    xp = x[p]
    g = (xp - origin) / dx - CENTER
    i0 = int(wp.floor(g[0]))
    j0 = int(wp.floor(g[1]))
    k0 = int(wp.floor(g[2]))
    for a in range(-1, 3):
        i = i0 + a
        if i >= 0 and i < phi_io.shape[0]:
            for b in range(-1, 3):
                j = j0 + b
                if j >= 0 and j < phi_io.shape[1]:
                    for c in range(-1, 3):
                        k = k0 + c
                        if k >= 0 and k < phi_io.shape[2]:
                            xc = origin + (wp.vec3(float(i), float(j), float(k)) + CENTER) * dx
                            wp.atomic_min(phi_io, i, j, k, wp.length(xc - xp) - radius)


# ---------------------------------------------------------------- density correction


@wp.kernel
def gather_particle_density(
    octant_start: wp.array(dtype=int),
    octant_count: wp.array(dtype=int),
    sorted_ids: wp.array(dtype=int),
    x: wp.array(dtype=wp.vec3),
    origin: wp.vec3,
    dx: float,
    rho_out: wp.array3d(dtype=float),
):
    """rho = sum of the trilinear (hat) weights of every live particle at this cell centre
    [particles per cell]. Stencil nodes beyond the grid fold back onto the edge cell (a mirror
    image across the wall), so a uniform packing of n particles per cell reads n up to the walls; a
    one-cell-thick axis (2D) puts the whole weight in its single layer. A gather over the particles
    of the cell octants around (octant order, then particle index: the same bits every run)."""
    i, j, k = wp.tid()
    nx = rho_out.shape[0]
    ny = rho_out.shape[1]
    nz = rho_out.shape[2]
    rx = half_range(i, 0, nx)
    ry = half_range(j, 0, ny)
    rz = half_range(k, 0, nz)
    rho = float(0.0)
    for hx in range(rx[0], rx[1] + 1):
        for hy in range(ry[0], ry[1] + 1):
            for hz in range(rz[0], rz[1] + 1):
                o = octant_of(hx, hy, hz, ny, nz)
                start = octant_start[o]
                for e in range(start, start + octant_count[o]):
                    g = (x[sorted_ids[e]] - origin) / dx - CENTER
                    i0 = int(wp.floor(g[0]))
                    j0 = int(wp.floor(g[1]))
                    k0 = int(wp.floor(g[2]))
                    t = g - wp.vec3(float(i0), float(j0), float(k0))
                    # every stencil node (a, b, c) that folds onto this cell adds its weight, in stencil order
                    for a in range(2):
                        if wp.clamp(i0 + a, 0, nx - 1) == i:
                            wa = wp.where(a == 0, 1.0 - t[0], t[0])
                            for b in range(2):
                                if wp.clamp(j0 + b, 0, ny - 1) == j:
                                    wb = wa * wp.where(b == 0, 1.0 - t[1], t[1])
                                    for c in range(2):
                                        if wp.clamp(k0 + c, 0, nz - 1) == k:
                                            wc = wb * wp.where(c == 0, 1.0 - t[2], t[2])
                                            if wc > 0.0:
                                                rho += wc
    rho_out[i, j, k] = rho


@wp.kernel
def particle_density(
    count: wp.array(dtype=int),
    x: wp.array(dtype=wp.vec3),
    alive: wp.array(dtype=float),
    origin: wp.vec3,
    dx: float,
    rho_io: wp.array3d(dtype=float),
):
    """rho += trilinear (hat) weights of every live particle at the cell centres [particles per
    cell]. Stencil nodes beyond the grid fold back onto the edge cell (a mirror image across the
    wall), so a uniform packing of n particles per cell reads n up to the walls; a one-cell-thick
    axis (2D) puts the whole weight in its single layer. Zero rho first. Float atomics
    (``FlipLiquid(deterministic=False)``; the default gathers, :func:`gather_particle_density`)."""
    p = wp.tid()
    if p >= count[0] or alive[p] == 0.0:
        return
    g = (x[p] - origin) / dx - CENTER
    i0 = int(wp.floor(g[0]))
    j0 = int(wp.floor(g[1]))
    k0 = int(wp.floor(g[2]))
    t = g - wp.vec3(float(i0), float(j0), float(k0))
    nx = rho_io.shape[0]
    ny = rho_io.shape[1]
    nz = rho_io.shape[2]
    for a in range(2):
        i = wp.clamp(i0 + a, 0, nx - 1)
        wa = wp.where(a == 0, 1.0 - t[0], t[0])
        for b in range(2):
            j = wp.clamp(j0 + b, 0, ny - 1)
            wb = wa * wp.where(b == 0, 1.0 - t[1], t[1])
            for c in range(2):
                k = wp.clamp(k0 + c, 0, nz - 1)
                wc = wb * wp.where(c == 0, 1.0 - t[2], t[2])
                if wc > 0.0:
                    wp.atomic_add(rho_io, i, j, k, wc)


@wp.kernel
def density_divergence_target(
    rho: wp.array3d(dtype=float),
    labels: wp.array3d(dtype=int),
    open_mask: int,
    rest: float,
    strength: float,
    max_target: float,
    target_out: wp.array3d(dtype=float),
):
    """Divergence a position correction needs to bring the particle density back to ``rest``:
    s = strength (rho / rest - 1), capped at max_target, at FLUID cells (0 elsewhere). Cells with
    AIR among their 26 neighbours are partly empty, or their hat kernel reaches into partly empty
    cells, so there only compression (s > 0) counts."""
    i, j, k = wp.tid()
    s = float(0.0)
    if labels[i, j, k] == FLUID:
        s = strength * (rho[i, j, k] / rest - 1.0)
        if s < 0.0:
            for a in range(-1, 2):
                for b in range(-1, 2):
                    for c in range(-1, 2):
                        if label_at(labels, open_mask, wp.vec3i(i + a, j + b, k + c)) == AIR:
                            s = 0.0
        s = wp.min(s, max_target)
    target_out[i, j, k] = s
