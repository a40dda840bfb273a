"""Level-set kernels: re-distancing and the particle level set (Enright, Fedkiw, Ferziger and
Mitchell 2002). phi lives at cell centres (layout: kernels/advect.py), phi < 0 inside the liquid.

Re-distancing keeps the zero level set: cells with a sign change to a neighbour get the distance
to the plane through the linear axis crossings (exact for planar interfaces), then every other
cell relaxes to the solution of the Godunov-discretised eikonal equation |grad phi| = 1 by
parallel (Jacobi) fast-sweeping updates, capped at ``max_dist``.

Marker particles: sign s = +1 (outside, phi > 0) or -1 (inside), radius r in [r_min, r_max];
s = 0 marks a deleted particle. A particle has escaped when s phi(x_p) < -r; escaped particles
rebuild phi around them from their spheres phi_p(x) = s (r - |x - x_p|).
"""

import warp as wp

from .advect import sample_at
from .grid import cell_of

wp.set_module_options({"enable_backward": False})

CENTER = wp.constant(wp.vec3(0.5, 0.5, 0.5))
BIG = wp.constant(1.0e6)


@wp.func
def _axis_neighbour(phi: wp.array3d(dtype=float), i: int, j: int, k: int, axis: int, side: int) -> wp.vec2:
    """(exists, value) of the neighbour of (i, j, k) along axis on side (0: -1, 1: +1)."""
    c = wp.vec3i(i, j, k)
    c[axis] = c[axis] + 2 * side - 1
    if c[axis] < 0 or c[axis] >= phi.shape[axis]:
        return wp.vec2(0.0, 0.0)
    return wp.vec2(1.0, phi[c[0], c[1], c[2]])


@wp.kernel
def redistance_init(
    phi_in: wp.array3d(dtype=float),
    dx: float,
    max_dist: float,
    phi_out: wp.array3d(dtype=float),
    fixed_out: wp.array3d(dtype=int),
):
    """Interface cells (a neighbour of the other sign): phi = s / sqrt(sum_a 1/d_a^2) with d_a the
    nearest linear crossing along axis a, fixed = 1. Other cells: phi = s max_dist, fixed = 0."""
    i, j, k = wp.tid()
    p = phi_in[i, j, k]
    inside = p < 0.0
    s = wp.where(inside, -1.0, 1.0)
    inv2 = float(0.0)
    crossing = int(0)
    at_zero = int(0)
    for a in range(3):
        da = float(BIG)
        for side in range(2):
            n = _axis_neighbour(phi_in, i, j, k, a, side)
            if n[0] > 0.0 and ((n[1] < 0.0) != inside):
                crossing = 1
                denom = wp.abs(p) + wp.abs(n[1])
                t = float(0.0)
                if denom > 0.0:
                    t = wp.abs(p) / denom
                da = wp.min(da, t * dx)
        if da < BIG:
            if da <= 1.0e-7 * dx:
                at_zero = 1
            else:
                inv2 += 1.0 / (da * da)
    if crossing == 1:
        d = float(0.0)
        if at_zero == 0:
            d = 1.0 / wp.sqrt(inv2)
        phi_out[i, j, k] = s * d
        fixed_out[i, j, k] = 1
    else:
        phi_out[i, j, k] = s * max_dist
        fixed_out[i, j, k] = 0


@wp.func
def _min_abs_neighbour(phi: wp.array3d(dtype=float), i: int, j: int, k: int, axis: int) -> float:
    m = float(BIG)
    for side in range(2):
        n = _axis_neighbour(phi, i, j, k, axis, side)
        if n[0] > 0.0:
            m = wp.min(m, wp.abs(n[1]))
    return m


@wp.kernel
def redistance_sweep(
    phi_in: wp.array3d(dtype=float), fixed: wp.array3d(dtype=int), dx: float, phi_out: wp.array3d(dtype=float)
):
    """One Jacobi pass of the Godunov eikonal update (Zhao 2005) on non-fixed cells; |phi| only decreases."""
    i, j, k = wp.tid()
    p = phi_in[i, j, k]
    if fixed[i, j, k] != 0:
        phi_out[i, j, k] = p
        return
    a = _min_abs_neighbour(phi_in, i, j, k, 0)
    b = _min_abs_neighbour(phi_in, i, j, k, 1)
    c = _min_abs_neighbour(phi_in, i, j, k, 2)
    # sort a <= b <= c
    if a > b:
        t = a
        a = b
        b = t
    if b > c:
        t = b
        b = c
        c = t
    if a > b:
        t = a
        a = b
        b = t
    d = a + dx
    if d > b:
        d = 0.5 * (a + b + wp.sqrt(wp.max(2.0 * dx * dx - (a - b) * (a - b), 0.0)))
        if d > c:
            s = a + b + c
            d = (s + wp.sqrt(wp.max(s * s - 3.0 * (a * a + b * b + c * c - dx * dx), 0.0))) / 3.0
    mag = wp.min(wp.abs(p), d)
    phi_out[i, j, k] = wp.where(p < 0.0, -mag, mag)


# ---------------------------------------------------------------- particle level set


@wp.func
def phi_gradient(phi: wp.array3d(dtype=float), origin: wp.vec3, inv_dx: float, dx: float, x: wp.vec3) -> wp.vec3:
    """Central-difference gradient of the trilinear phi at x (step dx/2)."""
    h = 0.5 * dx
    gx = sample_at(phi, CENTER, origin, inv_dx, x + wp.vec3(h, 0.0, 0.0)) - sample_at(
        phi, CENTER, origin, inv_dx, x - wp.vec3(h, 0.0, 0.0))
    gy = sample_at(phi, CENTER, origin, inv_dx, x + wp.vec3(0.0, h, 0.0)) - sample_at(
        phi, CENTER, origin, inv_dx, x - wp.vec3(0.0, h, 0.0))
    gz = sample_at(phi, CENTER, origin, inv_dx, x + wp.vec3(0.0, 0.0, h)) - sample_at(
        phi, CENTER, origin, inv_dx, x - wp.vec3(0.0, 0.0, h))
    return wp.vec3(gx, gy, gz) / dx


@wp.kernel
def pls_seed(
    phi: wp.array3d(dtype=float),
    origin: wp.vec3,
    dx: float,
    dim: int,
    band: float,
    per_cell: int,
    seed: int,
    r_min: float,
    r_max: float,
    cell_count: wp.array3d(dtype=int),
    count: wp.array(dtype=int),
    write: int,
    emitted_io: wp.array(dtype=int),
    offsets: wp.array(dtype=int),
    pos_out: wp.array(dtype=wp.vec3),
    radius_out: wp.array(dtype=float),
    sign_out: wp.array(dtype=float),
):
    """Top up every cell with |phi| < band [m] at its centre from cell_count to ``per_cell`` particles
    (alternating signs), each attracted toward a random target level s * [r_min, band] along the
    normal (Enright et al. 2002); particles that miss their side are dropped. Two passes append in
    cell order: write = 0 counts each cell's particles into emitted_io[cell] (flat index), write = 1
    puts them at count[0] + offsets[cell] + m' (offsets: exclusive prefix sum of the counts), up to
    the arrays' capacity; the host then advances count[0]."""
    i, j, k = wp.tid()
    if wp.abs(phi[i, j, k]) >= band:
        return
    inv_dx = 1.0 / dx
    nx = phi.shape[0]
    ny = phi.shape[1]
    nz = phi.shape[2]
    lower = origin + wp.vec3(float(i), float(j), float(k)) * dx
    flat = (i * ny + j) * nz + k
    emitted = int(0)
    for m in range(cell_count[i, j, k], per_cell):
        state = wp.rand_init(seed, flat * per_cell + m)
        x = lower + wp.vec3(wp.randf(state), wp.randf(state), wp.randf(state)) * dx
        if dim == 2:
            x = wp.vec3(x[0], x[1], origin[2] + 0.5 * dx)
        s = wp.where(m % 2 == 0, 1.0, -1.0)
        goal = s * (r_min + wp.randf(state) * (band - r_min))
        for it in range(4):
            g = phi_gradient(phi, origin, inv_dx, dx, x)
            gl = wp.length(g)
            if gl > 1.0e-6:
                x = x + (goal - sample_at(phi, CENTER, origin, inv_dx, x)) * g / (gl * gl)
        sp = s * sample_at(phi, CENTER, origin, inv_dx, x)
        inside_box = x[0] >= origin[0] and x[1] >= origin[1] and x[2] >= origin[2]
        inside_box = inside_box and x[0] <= origin[0] + float(nx) * dx and x[1] <= origin[1] + float(ny) * dx
        inside_box = inside_box and x[2] <= origin[2] + float(nz) * dx
        if sp >= r_min and sp <= band and inside_box:
            slot = count[0] + offsets[flat] + emitted
            if write != 0 and slot < pos_out.shape[0]:
                pos_out[slot] = x
                radius_out[slot] = wp.clamp(sp, r_min, r_max)
                sign_out[slot] = s
            emitted += 1
    if write == 0:
        emitted_io[flat] = emitted


@wp.kernel
def pls_scatter_escaped(
    phi: wp.array3d(dtype=float),
    origin: wp.vec3,
    dx: float,
    count: wp.array(dtype=int),
    pos: wp.array(dtype=wp.vec3),
    radius: wp.array(dtype=float),
    sign: wp.array(dtype=float),
    max_escape: float,
    phi_plus: wp.array3d(dtype=float),
    phi_minus: wp.array3d(dtype=float),
):
    """Escaped particles (-max_escape <= s phi(x_p) < -r) raise phi_plus (s = +1, by max) or lower
    phi_minus (s = -1, by min) at the 8 cell centres around them with their sphere phi_p. Particles
    escaped deeper than max_escape mark a feature the grid lost long ago; they are not used."""
    p = wp.tid()
    if p >= count[0]:
        return
    s = sign[p]
    if s == 0.0:
        return
    inv_dx = 1.0 / dx
    x = pos[p]
    r = radius[p]
    sp = s * sample_at(phi, CENTER, origin, inv_dx, x)
    if sp >= -r or sp < -max_escape:
        return
    g = (x - origin) * inv_dx - CENTER
    i0 = int(wp.floor(g[0]))
    j0 = int(wp.floor(g[1]))
    k0 = int(wp.floor(g[2]))
    for a in range(2):
        for b in range(2):
            for c in range(2):
                i = wp.clamp(i0 + a, 0, phi.shape[0] - 1)
                j = wp.clamp(j0 + b, 0, phi.shape[1] - 1)
                k = wp.clamp(k0 + c, 0, phi.shape[2] - 1)
                xc = origin + (wp.vec3(float(i), float(j), float(k)) + CENTER) * dx
                if phi.shape[2] == 1:
                    xc = wp.vec3(xc[0], xc[1], x[2])
                value = s * (r - wp.length(xc - x))
                if s > 0.0:
                    wp.atomic_max(phi_plus, i, j, k, value)
                else:
                    wp.atomic_min(phi_minus, i, j, k, value)


@wp.kernel
def pls_merge(phi_plus: wp.array3d(dtype=float), phi_minus: wp.array3d(dtype=float),
              phi_out: wp.array3d(dtype=float)):
    """phi = phi_plus where |phi_plus| <= |phi_minus|, else phi_minus."""
    i, j, k = wp.tid()
    a = phi_plus[i, j, k]
    b = phi_minus[i, j, k]
    phi_out[i, j, k] = wp.where(wp.abs(a) <= wp.abs(b), a, b)


@wp.kernel
def pls_adjust_radii(
    phi: wp.array3d(dtype=float),
    origin: wp.vec3,
    dx: float,
    r_min: float,
    r_max: float,
    delete_beyond: float,
    delete_escaped_beyond: float,
    count: wp.array(dtype=int),
    pos: wp.array(dtype=wp.vec3),
    radius_io: wp.array(dtype=float),
    sign_io: wp.array(dtype=float),
):
    """r = clamp(s phi(x_p), r_min, r_max); particles deeper than ``delete_beyond`` [m] on their own
    side, or escaped deeper than ``delete_escaped_beyond`` [m] into the other side, are deleted (s = 0)."""
    p = wp.tid()
    if p >= count[0]:
        return
    s = sign_io[p]
    if s == 0.0:
        return
    sp = s * sample_at(phi, CENTER, origin, 1.0 / dx, pos[p])
    if sp > delete_beyond or sp < -delete_escaped_beyond:
        sign_io[p] = 0.0
    else:
        radius_io[p] = wp.clamp(sp, r_min, r_max)


@wp.kernel
def liquid_volume(
    phi: wp.array3d(dtype=float),
    solid_phi: wp.array3d(dtype=float),
    eps: float,
    cell_volume: float,
    partial_out: wp.array2d(dtype=float),
):
    """partial_out[s, 0] = sum of cell_volume H_eps(-phi) over the non-solid cells s, s + S, ...
    (flat index, S slots, one thread each, index order), H_eps the smoothed Heaviside of half
    width eps [m]; folded in a fixed order by ``warpsim.core.reduction`` into the sub-cell accurate
    liquid volume [m^3] (area in 2D with a unit-thick slab), the same bits every run."""
    s = wp.tid()
    total = float(0.0)
    flat = s
    count = phi.shape[0] * phi.shape[1] * phi.shape[2]
    while flat < count:
        c = cell_of(flat, phi.shape[1], phi.shape[2])
        if solid_phi[c[0], c[1], c[2]] >= 0.0:
            x = -phi[c[0], c[1], c[2]]
            h = float(0.0)
            if x >= eps:
                h = 1.0
            elif x > -eps:
                h = 0.5 * (1.0 + x / eps + wp.sin(wp.pi * x / eps) / wp.pi)
            total += h * cell_volume
        flat += partial_out.shape[0]
    partial_out[s, 0] = total
