"""MAC-grid operators: solid voxelisation, cell labels, divergence, the pressure Poisson operator
(with ghost-fluid free-surface weights) and its preconditioners, pressure-gradient subtraction,
free-slip solid walls and velocity extrapolation.

Layout: see kernels/advect.py. Cell labels are AIR, FLUID, SOLID. Cells outside the grid are
SOLID walls, except on the sides whose bit is set in ``open_mask`` (bit 0: -x, 1: +x, 2: -y,
3: +y, 4: -z, 5: +z), where they are AIR at pressure 0.

Pressure units: the solver works with q = p dt / (rho dx) [m/s], so a face velocity update is
``u -= q[b] - q[a]`` and the Poisson system per fluid cell c reads
``sum_n w_n (q_c - q_n) = -D_c`` with D_c = dx * div(u)_c the net outflow (sum of outward face
velocities), w_n = 1 for fluid neighbours, 1/theta for air neighbours (ghost fluid,
theta = phi_c / (phi_c - phi_n) in [THETA_MIN, 1]) and no term for solid neighbours.
Non-fluid cells carry the identity row (q = 0), so the operator keeps a fixed size.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})

AIR = wp.constant(0)
FLUID = wp.constant(1)
SOLID = wp.constant(2)
THETA_MIN = wp.constant(0.01)
FAR = wp.constant(1.0e6)


@wp.func
def axis_step(axis: int) -> wp.vec3i:
    if axis == 0:
        return wp.vec3i(1, 0, 0)
    if axis == 1:
        return wp.vec3i(0, 1, 0)
    return wp.vec3i(0, 0, 1)


@wp.func
def label_at(labels: wp.array3d(dtype=int), open_mask: int, c: wp.vec3i) -> int:
    """Label of cell c; outside the grid: SOLID wall or AIR on open sides."""
    for a in range(3):
        if c[a] < 0:
            if (open_mask >> (2 * a)) & 1 != 0:
                return AIR
            return SOLID
        if c[a] >= labels.shape[a]:
            if (open_mask >> (2 * a + 1)) & 1 != 0:
                return AIR
            return SOLID
    return labels[c[0], c[1], c[2]]


@wp.func
def ghost_theta(phi: wp.array3d(dtype=float), use_phi: int, c: wp.vec3i, n: wp.vec3i) -> float:
    """Fraction of the way from fluid cell c to air cell n where the surface lies (1 without phi)."""
    if use_phi == 0:
        return 1.0
    for a in range(3):
        if n[a] < 0 or n[a] >= phi.shape[a]:
            return 1.0
    pc = phi[c[0], c[1], c[2]]
    pn = phi[n[0], n[1], n[2]]
    theta = float(1.0)
    if pn - pc > 0.0:
        theta = pc / (pc - pn)
    return wp.clamp(theta, THETA_MIN, 1.0)


# ---------------------------------------------------------------- solids and labels


@wp.kernel
def solid_phi_spheres(
    centers: wp.array(dtype=wp.vec3),
    radii: wp.array(dtype=float),
    origin: wp.vec3,
    dx: float,
    solid_phi_io: wp.array3d(dtype=float),
):
    """solid_phi = min(solid_phi, |x - c| - r) at cell centres for every sphere [m]."""
    i, j, k = wp.tid()
    x = origin + (wp.vec3(float(i), float(j), float(k)) + wp.vec3(0.5)) * dx
    d = solid_phi_io[i, j, k]
    for s in range(centers.shape[0]):
        d = wp.min(d, wp.length(x - centers[s]) - radii[s])
    solid_phi_io[i, j, k] = d


@wp.kernel
def solid_phi_boxes(
    lowers: wp.array(dtype=wp.vec3),
    uppers: wp.array(dtype=wp.vec3),
    origin: wp.vec3,
    dx: float,
    solid_phi_io: wp.array3d(dtype=float),
):
    """solid_phi = min(solid_phi, signed distance to each axis-aligned box) at cell centres [m]."""
    i, j, k = wp.tid()
    x = origin + (wp.vec3(float(i), float(j), float(k)) + wp.vec3(0.5)) * dx
    d = solid_phi_io[i, j, k]
    for s in range(lowers.shape[0]):
        c = 0.5 * (lowers[s] + uppers[s])
        h = 0.5 * (uppers[s] - lowers[s])
        q = wp.vec3(wp.abs(x[0] - c[0]), wp.abs(x[1] - c[1]), wp.abs(x[2] - c[2])) - h
        outside = wp.length(wp.vec3(wp.max(q[0], 0.0), wp.max(q[1], 0.0), wp.max(q[2], 0.0)))
        inside = wp.min(wp.max(q[0], wp.max(q[1], q[2])), 0.0)
        d = wp.min(d, outside + inside)
    solid_phi_io[i, j, k] = d


@wp.kernel
def solid_phi_mesh(
    mesh: wp.uint64, origin: wp.vec3, dx: float, max_dist: float, solid_phi_io: wp.array3d(dtype=float)
):
    """solid_phi = min(solid_phi, signed distance to a closed wp.Mesh) at cell centres [m]
    (cells farther than max_dist keep their value)."""
    i, j, k = wp.tid()
    x = origin + (wp.vec3(float(i), float(j), float(k)) + wp.vec3(0.5)) * dx
    q = wp.mesh_query_point_sign_normal(mesh, x, max_dist)
    if q.result:
        cp = wp.mesh_eval_position(mesh, q.face, q.u, q.v)
        d = q.sign * wp.length(x - cp)
        solid_phi_io[i, j, k] = wp.min(solid_phi_io[i, j, k], d)


@wp.kernel
def label_cells(
    solid_phi: wp.array3d(dtype=float),
    phi: wp.array3d(dtype=float),
    use_phi: int,
    labels_out: wp.array3d(dtype=int),
):
    """SOLID where solid_phi < 0; else FLUID where phi < 0 (or everywhere when use_phi = 0); else AIR."""
    i, j, k = wp.tid()
    label = FLUID
    if solid_phi[i, j, k] < 0.0:
        label = SOLID
    elif use_phi != 0 and phi[i, j, k] >= 0.0:
        label = AIR
    labels_out[i, j, k] = label


# ---------------------------------------------------------------- boundary conditions


@wp.kernel
def enforce_solid_faces(labels: wp.array3d(dtype=int), open_mask: int, axis: int, f_io: wp.array3d(dtype=float)):
    """Free-slip static solids: the normal velocity on faces touching a SOLID cell (or a closed
    domain wall) is 0; tangential components are left free."""
    i, j, k = wp.tid()
    c = wp.vec3i(i, j, k)
    a = c - axis_step(axis)
    if label_at(labels, open_mask, a) == SOLID or label_at(labels, open_mask, c) == SOLID:
        f_io[i, j, k] = 0.0


@wp.kernel
def compute_divergence(
    u: wp.array3d(dtype=float),
    v: wp.array3d(dtype=float),
    w: wp.array3d(dtype=float),
    labels: wp.array3d(dtype=int),
    dx: float,
    div_out: wp.array3d(dtype=float),
):
    """div(u) [1/s] at FLUID cells (0 elsewhere)."""
    i, j, k = wp.tid()
    d = float(0.0)
    if labels[i, j, k] == FLUID:
        d = (u[i + 1, j, k] - u[i, j, k] + v[i, j + 1, k] - v[i, j, k] + w[i, j, k + 1] - w[i, j, k]) / dx
    div_out[i, j, k] = d


@wp.kernel
def pressure_rhs(
    div: wp.array3d(dtype=float),
    labels: wp.array3d(dtype=int),
    target: wp.array3d(dtype=float),
    use_target: int,
    dx: float,
    rhs_out: wp.array(dtype=float),
):
    """rhs = -dx (div(u) - target) at FLUID cells, 0 elsewhere [m/s] (minus each cell's net outflow
    beyond the wanted one), flattened (i, j, k) -> (i ny + j) nz + k. ``target`` [1/s] is the
    divergence the projection should leave (read only when use_target != 0)."""
    i, j, k = wp.tid()
    d = float(0.0)
    if labels[i, j, k] == FLUID:
        d = div[i, j, k]
        if use_target != 0:
            d = d - target[i, j, k]
    rhs_out[(i * div.shape[1] + j) * div.shape[2] + k] = -dx * d


@wp.kernel
def pressure_coefficients(
    labels: wp.array3d(dtype=int),
    phi: wp.array3d(dtype=float),
    use_phi: int,
    open_mask: int,
    diag_out: wp.array3d(dtype=float),
    plus_x_out: wp.array3d(dtype=float),
    plus_y_out: wp.array3d(dtype=float),
    plus_z_out: wp.array3d(dtype=float),
):
    """Per cell: the diagonal of the Poisson operator and its couplings to the +x, +y, +z
    neighbours (-1 between two FLUID cells, else 0). Non-fluid cells get diag = 1."""
    i, j, k = wp.tid()
    c = wp.vec3i(i, j, k)
    diag = float(0.0)
    plus = wp.vec3(0.0)
    if labels[i, j, k] == FLUID:
        for a in range(3):
            for s in range(2):
                n = c + axis_step(a) * (2 * s - 1)
                ln = label_at(labels, open_mask, n)
                if ln == FLUID:
                    diag += 1.0
                    if s == 1:
                        plus[a] = -1.0
                elif ln == AIR:
                    diag += 1.0 / ghost_theta(phi, use_phi, c, n)
    else:
        diag = 1.0
    diag_out[i, j, k] = diag
    plus_x_out[i, j, k] = plus[0]
    plus_y_out[i, j, k] = plus[1]
    plus_z_out[i, j, k] = plus[2]


@wp.func
def _off_diagonal_product(
    plus_x: wp.array3d(dtype=float),
    plus_y: wp.array3d(dtype=float),
    plus_z: wp.array3d(dtype=float),
    x: wp.array(dtype=float),
    i: int,
    j: int,
    k: int,
) -> float:
    """sum over the 6 neighbours n of A[c, n] x[n] for cell c = (i, j, k)."""
    ny = plus_x.shape[1]
    nz = plus_x.shape[2]
    c = (i * ny + j) * nz + k
    s = float(0.0)
    if i + 1 < plus_x.shape[0]:
        s += plus_x[i, j, k] * x[c + ny * nz]
    if i > 0:
        s += plus_x[i - 1, j, k] * x[c - ny * nz]
    if j + 1 < ny:
        s += plus_y[i, j, k] * x[c + nz]
    if j > 0:
        s += plus_y[i, j - 1, k] * x[c - nz]
    if k + 1 < nz:
        s += plus_z[i, j, k] * x[c + 1]
    if k > 0:
        s += plus_z[i, j, k - 1] * x[c - 1]
    return s


@wp.kernel
def apply_pressure_operator(
    diag: wp.array3d(dtype=float),
    plus_x: wp.array3d(dtype=float),
    plus_y: wp.array3d(dtype=float),
    plus_z: wp.array3d(dtype=float),
    x: wp.array(dtype=float),
    y: wp.array(dtype=float),
    alpha: float,
    beta: float,
    z_out: wp.array(dtype=float),
):
    """z = alpha A x + beta y for the matrix-free Poisson operator (flattened cell vectors)."""
    i, j, k = wp.tid()
    c = (i * diag.shape[1] + j) * diag.shape[2] + k
    ax = diag[i, j, k] * x[c] + _off_diagonal_product(plus_x, plus_y, plus_z, x, i, j, k)
    yc = float(0.0)
    if beta != 0.0:
        yc = beta * y[c]
    z_out[c] = alpha * ax + yc


@wp.kernel
def apply_jacobi(diag: wp.array(dtype=float), x: wp.array(dtype=float), y: wp.array(dtype=float),
                 alpha: float, beta: float, z_out: wp.array(dtype=float)):
    """z = alpha D^-1 x + beta y (Jacobi preconditioner)."""
    c = wp.tid()
    yc = float(0.0)
    if beta != 0.0:
        yc = beta * y[c]
    z_out[c] = alpha * x[c] / diag[c] + yc


@wp.kernel
def gauss_seidel_color(
    diag: wp.array3d(dtype=float),
    plus_x: wp.array3d(dtype=float),
    plus_y: wp.array3d(dtype=float),
    plus_z: wp.array3d(dtype=float),
    r: wp.array(dtype=float),
    color: int,
    first: int,
    z_io: wp.array(dtype=float),
):
    """One red-black Gauss-Seidel half sweep of A z = r on cells with (i + j + k) % 2 == color
    (``first`` = 1: z starts at 0, so neighbours are not read). A zero diagonal (a FLUID cell with
    only SOLID neighbours, e.g. a pocket on a coarse multigrid level) gives z = 0 there."""
    i, j, k = wp.tid()
    if (i + j + k) % 2 != color:
        return
    c = (i * diag.shape[1] + j) * diag.shape[2] + k
    s = float(0.0)
    if first == 0:
        s = _off_diagonal_product(plus_x, plus_y, plus_z, z_io, i, j, k)
    d = diag[i, j, k]
    z_io[c] = wp.where(d > 0.0, (r[c] - s) / wp.max(d, 1.0e-30), 0.0)


@wp.kernel
def axpby(x: wp.array(dtype=float), y: wp.array(dtype=float), alpha: float, beta: float,
          z_out: wp.array(dtype=float)):
    """z = alpha x + beta y (y ignored when beta = 0, so it may alias z)."""
    c = wp.tid()
    yc = float(0.0)
    if beta != 0.0:
        yc = beta * y[c]
    z_out[c] = alpha * x[c] + yc


@wp.func
def cell_of(flat: int, ny: int, nz: int) -> wp.vec3i:
    """(i, j, k) of the cell at flat (row-major) index ``flat`` of a grid with ny x nz cells per i."""
    nyz = ny * nz
    i = flat / nyz
    r = flat - i * nyz
    j = r / nz
    return wp.vec3i(i, j, r - j * nz)


@wp.kernel
def fluid_sums(labels: wp.array3d(dtype=int), open_mask: int, rhs: wp.array(dtype=float),
               partial_out: wp.array2d(dtype=float)):
    """partial_out[s] = (sum of rhs, FLUID cells, FLUID faces next to AIR) over the FLUID cells
    s, s + S, s + 2S, ... (flat index, S = partial_out.shape[0] slots, one thread each), added in
    index order; ``warpsim.core.reduction.FixedOrderReduction.finish`` then folds the slots in a fixed
    order, so the totals are the same bits every run (no float atomics)."""
    s = wp.tid()
    stride = partial_out.shape[0]
    total = float(0.0)
    cells = float(0.0)
    air = float(0.0)
    flat = s
    count = labels.shape[0] * labels.shape[1] * labels.shape[2]
    while flat < count:
        c = cell_of(flat, labels.shape[1], labels.shape[2])
        if labels[c[0], c[1], c[2]] == FLUID:
            for a in range(3):
                for side in range(2):
                    if label_at(labels, open_mask, c + axis_step(a) * (2 * side - 1)) == AIR:
                        air += 1.0
            total += rhs[flat]
            cells += 1.0
        flat += stride
    partial_out[s, 0] = total
    partial_out[s, 1] = cells
    partial_out[s, 2] = air


@wp.kernel
def remove_rhs_mean(labels: wp.array3d(dtype=int), sums: wp.array(dtype=float), rhs_io: wp.array(dtype=float)):
    """Closed domains (no FLUID cell touches AIR): make the rhs compatible (zero mean over FLUID
    cells), so the singular Neumann problem has a solution."""
    i, j, k = wp.tid()
    if sums[2] > 0.0 or sums[1] == 0.0 or labels[i, j, k] != FLUID:
        return
    c = (i * labels.shape[1] + j) * labels.shape[2] + k
    rhs_io[c] = rhs_io[c] - sums[0] / sums[1]


@wp.kernel
def subtract_pressure_gradient(
    q: wp.array(dtype=float),
    labels: wp.array3d(dtype=int),
    phi: wp.array3d(dtype=float),
    use_phi: int,
    open_mask: int,
    axis: int,
    f_io: wp.array3d(dtype=float),
):
    """u -= q[b] - q[a] on faces between cells a (lower) and b (upper) along ``axis`` when at
    least one is FLUID and neither is SOLID; an AIR side uses the ghost pressure
    q_ghost = q_fluid (1 - 1/theta) (pressure 0 on the surface)."""
    i, j, k = wp.tid()
    b = wp.vec3i(i, j, k)
    a = b - axis_step(axis)
    la = label_at(labels, open_mask, a)
    lb = label_at(labels, open_mask, b)
    if la == SOLID or lb == SOLID:
        return
    ny = labels.shape[1]
    nz = labels.shape[2]
    if la == FLUID and lb == FLUID:
        f_io[i, j, k] = f_io[i, j, k] - (q[(b[0] * ny + b[1]) * nz + b[2]] - q[(a[0] * ny + a[1]) * nz + a[2]])
    elif la == FLUID:
        f_io[i, j, k] = f_io[i, j, k] + q[(a[0] * ny + a[1]) * nz + a[2]] / ghost_theta(phi, use_phi, a, b)
    elif lb == FLUID:
        f_io[i, j, k] = f_io[i, j, k] - q[(b[0] * ny + b[1]) * nz + b[2]] / ghost_theta(phi, use_phi, b, a)


# ---------------------------------------------------------------- extrapolation


@wp.kernel
def mark_fluid_faces(labels: wp.array3d(dtype=int), open_mask: int, axis: int, valid_out: wp.array3d(dtype=int)):
    """valid = 1 on faces with a FLUID cell on either side (their velocity is known)."""
    i, j, k = wp.tid()
    c = wp.vec3i(i, j, k)
    valid = 0
    if label_at(labels, open_mask, c) == FLUID or label_at(labels, open_mask, c - axis_step(axis)) == FLUID:
        valid = 1
    valid_out[i, j, k] = valid


@wp.kernel
def extrapolate_layer(
    valid_in: wp.array3d(dtype=int),
    f_in: wp.array3d(dtype=float),
    zero_invalid: int,
    valid_out: wp.array3d(dtype=int),
    f_out: wp.array3d(dtype=float),
):
    """One layer of extrapolation: an invalid value becomes the mean of its valid neighbours (values
    still invalid are set to 0 when zero_invalid = 1)."""
    i, j, k = wp.tid()
    if valid_in[i, j, k] != 0:
        valid_out[i, j, k] = 1
        f_out[i, j, k] = f_in[i, j, k]
        return
    s = float(0.0)
    n = int(0)
    for a in range(3):
        for d in range(2):
            c = wp.vec3i(i, j, k) + axis_step(a) * (2 * d - 1)
            if c[a] >= 0 and c[a] < f_in.shape[a] and valid_in[c[0], c[1], c[2]] != 0:
                s += f_in[c[0], c[1], c[2]]
                n += 1
    if n > 0:
        valid_out[i, j, k] = 1
        f_out[i, j, k] = s / float(n)
    else:
        valid_out[i, j, k] = 0
        f_out[i, j, k] = wp.where(zero_invalid != 0, 0.0, f_in[i, j, k])
