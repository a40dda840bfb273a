"""Position-based fluid (PBF, an SPH-family method) kernels.

Conventions:

* ``h`` is the smoothing kernel's *support radius* [m]: W(r) = 0 for r >= h.
* Neighbour lists (:class:`NeighborList`) hold, for particle i, the indices j != i with
  |x_i - x_j| < h (true distance, filtered from the hash-grid candidates) at the predicted
  positions of a step; later passes of the step evaluate the same pairs at moved positions
  (the kernels vanish beyond h) and cache each pair's kernel gradient for the next correction.
* Inner loops use :func:`pair_terms`: constants precomputed in :class:`FluidParams`, no
  data-dependent branches, one square root and one division per pair.
* Boundaries are signed-distance boundaries: every plane, capsule (sphere) and triangle mesh at
  signed distance ``d`` (> 0 on the fluid side) contributes the solid fraction ``phi(d)`` of the
  kernel (the half-space beyond a wall at distance ``d``, tabulated by the host on [0, h]) and its
  gradient ``phi'(d) n``; boundaries combine as ``1 - prod(1 - phi_b)`` and add
  ``rest_density * phi`` to the density. Particles are projected back to at least ``radius``
  from every boundary.
* Only particles ``0 .. active_count-1`` exist; launches use ``dim = active_count``.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})

KERNEL_CUBIC = wp.constant(0)
KERNEL_WENDLAND = wp.constant(1)
PI = wp.constant(3.14159265358979)


@wp.struct
class FluidParams:
    """Per-solver constants (see ``warpsim.sph.ParticleFluid``)."""

    h: float  # support radius [m]
    kernel: int  # KERNEL_CUBIC or KERNEL_WENDLAND
    rest_density: float  # [kg/m^3]
    mass: float  # particle mass [kg]
    radius: float  # particle radius [m], half the spacing: closest approach to a boundary
    gravity: wp.vec3  # [m/s^2]
    relaxation: float  # PBF constraint-force mixing epsilon [1/m^2]
    viscosity: float  # XSPH coefficient (dimensionless, 0..1)
    vorticity: float  # vorticity-confinement strength [m/s^2 per 1/s]
    surface_tension: float  # Akinci et al. (2013) cohesion coefficient gamma [1/s^2]
    wall_friction: float  # velocity damping rate k at boundaries [1/s]: v *= exp(-k phi dt)
    # derived constants, set by the host (``warpsim.sph.ParticleFluid``) from the ones above
    inv_h: float  # 1 / h [1/m]
    h2: float  # h^2 [m^2]
    w_scale: float  # mass * W normalisation [kg/m^3] (cubic: m 8/(pi h^3); Wendland: m 21/(2 pi h^3))
    g_scale: float  # (mass / rest_density) * dW/dr normalisation [1/m] (cubic 48/(pi h^4), Wendland 210/(pi h^4))
    self_density: float  # mass * W(0) [kg/m^3]


@wp.struct
class Boundaries:
    """Signed-distance boundaries. Planes: n . x = offset with n toward the fluid. Capsules (a
    sphere is a capsule with a == b): the points within ``radius`` of segment [a, b], solid
    (sign +1, fluid outside) or a hollow container (sign -1, fluid inside). Meshes: wp.Mesh ids
    in world space, closed solids (solid 1: fluid outside, inside found by the mesh's sign query)
    or thin two-sided surfaces (solid 0), thickened by ``mesh_thickness`` [m]."""

    plane_normals: wp.array(dtype=wp.vec3)
    plane_offsets: wp.array(dtype=float)
    capsule_a: wp.array(dtype=wp.vec3)
    capsule_b: wp.array(dtype=wp.vec3)
    capsule_radii: wp.array(dtype=float)
    capsule_signs: wp.array(dtype=float)
    mesh_ids: wp.array(dtype=wp.uint64)
    mesh_thickness: wp.array(dtype=float)
    mesh_solid: wp.array(dtype=int)
    phi_table: wp.array(dtype=float)  # solid volume fraction beyond a wall at d = k h / (count - 1)
    dphi_table: wp.array(dtype=float)  # its derivative d phi / d d [1/m]


@wp.struct
class NeighborList:
    """Per-particle neighbour lists: particle i's k-th neighbour is
    ``index[i * stride_i + k * stride_k]``, k < count[i] <= capacity. warpsim uses row-major
    (stride_k = 1): on an H200 at 1M particles it ran a dam-break step at the example_sph step
    size in 2.48 ms against 2.94 ms for column-major (stride_i = 1, coalesced across threads).

    ``grad_factor`` (same layout) caches each pair's kernel gradient from the last density
    evaluation: ``(m / rho0) grad_i W_ij = grad_factor * (x_i - x_j)`` [1/m^2], so a position
    correction gathers it without re-evaluating the kernel, when ``cache_gradients`` != 0 (the
    CPU's choice; GPUs re-evaluate it, cheaper there than writing and reading it back)."""

    count: wp.array(dtype=int)
    index: wp.array(dtype=int)
    grad_factor: wp.array(dtype=float)
    stride_i: int
    stride_k: int
    capacity: int
    cache_gradients: int


# ------------------------------------------------------------------------------------ kernels
@wp.func
def kernel_w(r: float, h: float, kind: int) -> float:
    """Smoothing kernel W(r) [1/m^3], support radius h (cubic spline or Wendland C2, 3D)."""
    q = r / h
    if q >= 1.0:
        return 0.0
    if kind == KERNEL_CUBIC:
        k = 8.0 / (PI * h * h * h)
        if q <= 0.5:
            return k * (6.0 * q * q * q - 6.0 * q * q + 1.0)
        t = 1.0 - q
        return 2.0 * k * t * t * t
    t = 1.0 - q
    return 21.0 / (2.0 * PI * h * h * h) * t * t * t * t * (1.0 + 4.0 * q)


@wp.func
def kernel_dw(r: float, h: float, kind: int) -> float:
    """dW/dr [1/m^4]; the gradient is kernel_dw(|r|) * r / |r|."""
    q = r / h
    if q >= 1.0:
        return 0.0
    if kind == KERNEL_CUBIC:
        l = 48.0 / (PI * h * h * h * h)
        if q <= 0.5:
            return l * q * (3.0 * q - 2.0)
        t = 1.0 - q
        return -l * t * t
    t = 1.0 - q
    return -21.0 / (2.0 * PI * h * h * h * h) * 20.0 * q * t * t * t


@wp.func
def cohesion_spline(r: float, h: float) -> float:
    """Akinci et al. (2013) cohesion spline C(r) [1/m^3]: repulsive below h/2, attractive above."""
    if r >= h or r <= 0.0:
        return 0.0
    h3 = h * h * h
    c = 32.0 / (PI * h3 * h3 * h3)
    a = (h - r) * (h - r) * (h - r) * r * r * r
    if 2.0 * r > h:
        return c * a
    return c * (2.0 * a - h3 * h3 / 64.0)


@wp.func
def pair_terms(p: FluidParams, r2: float) -> wp.vec2:
    """(m W(r), f) of a pair at squared distance r2 [m^2]: the density contribution [kg/m^3] and
    the gradient factor f [1/m^2] with (m / rho0) grad_i W_ij = f (x_i - x_j). Any r2 >= 0 (zero
    beyond h), without data-dependent branches and with constants precomputed: this is the inner
    loop of every density pass."""
    r = wp.sqrt(r2)
    q = r * p.inv_h
    t = wp.max(1.0 - q, 0.0)
    if p.kernel == KERNEL_CUBIC:
        u = wp.max(0.5 - q, 0.0)
        # one expression for both spline pieces, no select: W = k (2 t^3 - 8 u^3) equals
        # k (6 q^3 - 6 q^2 + 1) for q <= 1/2 and 2 k t^3 above; dW/dr = l (4 u^2 - t^2) equals
        # l q (3 q - 2) below and -l t^2 above (at r = 0 the numerator is exactly 0)
        w = p.w_scale * (2.0 * t * t * t - 8.0 * u * u * u)
        return wp.vec2(w, p.g_scale * (4.0 * u * u - t * t) / wp.max(r, 1.0e-30))
    t3 = t * t * t
    return wp.vec2(p.w_scale * t3 * t * (1.0 + 4.0 * q), -p.g_scale * p.inv_h * t3)


@wp.func
def pair_density(p: FluidParams, r: float) -> float:
    """m W(r) [kg/m^3] alone (the first component of :func:`pair_terms`, without its division)."""
    q = r * p.inv_h
    t = wp.max(1.0 - q, 0.0)
    if p.kernel == KERNEL_CUBIC:
        u = wp.max(0.5 - q, 0.0)
        return p.w_scale * (2.0 * t * t * t - 8.0 * u * u * u)
    return p.w_scale * t * t * t * t * (1.0 + 4.0 * q)


# -------------------------------------------------------------------------------- boundaries
@wp.func
def wall_lookup(table: wp.array(dtype=float), d: float, h: float) -> float:
    """Linear interpolation of a table sampled at d = k h / (n - 1), k = 0..n-1; 0 beyond h."""
    n = table.shape[0]
    s = wp.max(d, 0.0) / h * float(n - 1)
    if s >= float(n - 1):
        return 0.0
    k = int(s)
    t = s - float(k)
    return table[k] * (1.0 - t) + table[k + 1] * t


@wp.func
def wall_term(b: Boundaries, d: float, n: wp.vec3, h: float) -> wp.vec4:
    """(phi'(d) n, phi(d)) for a wall at signed distance d with fluid-side normal n; a particle
    behind the wall (d < 0) sees 1 - phi(-d)."""
    if d >= h:
        return wp.vec4(0.0)
    phi = wall_lookup(b.phi_table, d, h)
    if d < 0.0:
        phi = 1.0 - wall_lookup(b.phi_table, -d, h)
    g = wall_lookup(b.dphi_table, wp.abs(d), h) * n
    return wp.vec4(g[0], g[1], g[2], phi)


@wp.func
def capsule_distance(b: Boundaries, s: int, x: wp.vec3) -> wp.vec4:
    """(fluid-side normal, signed distance) to capsule s."""
    a = b.capsule_a[s]
    ab = b.capsule_b[s] - a
    t = float(0.0)
    l2 = wp.dot(ab, ab)
    if l2 > 0.0:
        t = wp.clamp(wp.dot(x - a, ab) / l2, 0.0, 1.0)
    dx = x - (a + t * ab)
    l = wp.length(dx)
    n = wp.vec3(0.0, 1.0, 0.0)
    if l > 1.0e-12:
        n = dx / l
    sign = b.capsule_signs[s]
    n = sign * n
    return wp.vec4(n[0], n[1], n[2], sign * (l - b.capsule_radii[s]))


@wp.func
def mesh_distance(b: Boundaries, m: int, x: wp.vec3, max_dist: float) -> wp.vec4:
    """(fluid-side normal, signed distance) to mesh m thickened by its thickness; d = max_dist
    when nothing is within reach."""
    mesh = b.mesh_ids[m]
    thick = b.mesh_thickness[m]
    sign = float(1.0)
    face = int(0)
    u = float(0.0)
    v = float(0.0)
    if b.mesh_solid[m] != 0:
        q = wp.mesh_query_point_sign_normal(mesh, x, max_dist + thick)
        if not q.result:
            return wp.vec4(0.0, 1.0, 0.0, max_dist)
        sign = q.sign
        face = q.face
        u = q.u
        v = q.v
    else:
        q = wp.mesh_query_point_no_sign(mesh, x, max_dist + thick)
        if not q.result:
            return wp.vec4(0.0, 1.0, 0.0, max_dist)
        face = q.face
        u = q.u
        v = q.v
    c = wp.mesh_eval_position(mesh, face, u, v)
    dx = x - c
    l = wp.length(dx)
    n = sign * wp.mesh_eval_face_normal(mesh, face)
    if l > 1.0e-9:
        n = sign * dx / l
    return wp.vec4(n[0], n[1], n[2], sign * l - thick)


@wp.func
def union_term(acc: wp.vec4, t: wp.vec4) -> wp.vec4:
    """Combine a boundary's (phi' n, phi) with the accumulated (grad F, F) of the fluid fraction
    F = prod_b (1 - phi_b), so solid regions shared by two walls (edges, corners) count once."""
    g = wp.vec3(acc[0], acc[1], acc[2]) * (1.0 - t[3]) - acc[3] * wp.vec3(t[0], t[1], t[2])
    return wp.vec4(g[0], g[1], g[2], acc[3] * (1.0 - t[3]))


@wp.func
def boundary_density(b: Boundaries, x: wp.vec3, h: float) -> wp.vec4:
    """Boundary density gradient / rest density (xyz) [1/m] and boundary density / rest density
    (w) at x: phi = 1 - prod_b (1 - phi_b) over every plane, sphere and mesh (exact for one
    wall, and overlaps of walls at edges and corners are not counted twice)."""
    acc = wp.vec4(0.0, 0.0, 0.0, 1.0)
    for p in range(b.plane_offsets.shape[0]):
        n = b.plane_normals[p]
        d = wp.dot(n, x) - b.plane_offsets[p]
        if d < h:  # most particles are beyond the reach of most walls
            acc = union_term(acc, wall_term(b, d, n, h))
    for s in range(b.capsule_radii.shape[0]):
        sd = capsule_distance(b, s, x)
        acc = union_term(acc, wall_term(b, sd[3], wp.vec3(sd[0], sd[1], sd[2]), h))
    for m in range(b.mesh_thickness.shape[0]):
        md = mesh_distance(b, m, x, h)
        acc = union_term(acc, wall_term(b, md[3], wp.vec3(md[0], md[1], md[2]), h))
    return wp.vec4(-acc[0], -acc[1], -acc[2], 1.0 - acc[3])


@wp.func
def project_planes(b: Boundaries, x: wp.vec3, radius: float) -> wp.vec3:
    """Move x to at least ``radius`` in front of every plane (planes are cheap: every iteration)."""
    y = x
    for p in range(b.plane_offsets.shape[0]):
        n = b.plane_normals[p]
        d = wp.dot(n, y) - b.plane_offsets[p]
        if d < radius:
            y = y + (radius - d) * n
    return y


@wp.func
def project_shapes(b: Boundaries, x: wp.vec3, radius: float) -> wp.vec3:
    """Move x out of every capsule (sphere) and mesh to at least ``radius`` from its surface."""
    y = x
    for s in range(b.capsule_radii.shape[0]):
        sd = capsule_distance(b, s, y)
        if sd[3] < radius:
            y = y + (radius - sd[3]) * wp.vec3(sd[0], sd[1], sd[2])
    for m in range(b.mesh_thickness.shape[0]):
        md = mesh_distance(b, m, y, 2.0 * radius)
        if md[3] < radius:
            y = y + (radius - md[3]) * wp.vec3(md[0], md[1], md[2])
    return y


# ---------------------------------------------------------------------------------- stages
@wp.func
def store_density_constraint(
    p: FluidParams,
    b: Boundaries,
    i: int,
    xi: wp.vec3,
    rho_fluid: float,
    grad_fluid: wp.vec3,
    sum_grad2: float,
    with_stats: int,
    density_out: wp.array(dtype=float),
    lambda_out: wp.array(dtype=float),
    boundary_grad_out: wp.array(dtype=wp.vec3),
    compression_out: wp.array(dtype=float),
):
    """Add the boundaries to particle i's density sums and store rho_i, its PBF multiplier
    lambda_i = -C_i / (sum_k |grad_k C_i|^2 + eps) of C_i = max(rho_i / rho0 - 1, 0), and the
    boundary gradient. with_stats != 0 also stores C in compression_out[i] (summed and maximised
    in a fixed order by ``warpsim.core.reduction`` for :func:`iteration_control`: no float
    atomics, so the iteration count is the same run to run)."""
    bd = boundary_density(b, xi, p.h)
    rho = rho_fluid + p.rest_density * bd[3]
    gb = wp.vec3(bd[0], bd[1], bd[2])
    grad_i = grad_fluid + gb
    c = wp.max(rho / p.rest_density - 1.0, 0.0)
    lam = -c / (sum_grad2 + wp.dot(grad_i, grad_i) + p.relaxation)
    density_out[i] = rho
    lambda_out[i] = lam
    boundary_grad_out[i] = gb
    if with_stats != 0:
        compression_out[i] = c


@wp.func
def list_neighbors(grid: wp.uint64, p: FluidParams, x: wp.array(dtype=wp.vec3), self_index: int, xi: wp.vec3,
                   first_fluid: int, with_density: int, nb_out: NeighborList, base: int):
    """The neighbour list of the particle at ``xi`` (hash-grid candidates j != ``self_index`` with
    |x_i - x_j| < h, indices into ``x``, stored from ``base`` up to the list's capacity), in the
    grid's candidate order. With ``with_density`` != 0 also, in the same fixed order, the density
    sum rho = m W(0) + sum_j m W_ij [kg/m^3], sum_j grad W_ij terms (the pair gradient cached when
    the list caches them), sum |grad W_ij|^2 r^2 over the particles j >= ``first_fluid`` and the
    density of those below it (boundary particles). Returns (all candidates within h: may exceed the
    capacity, rho, grad sum, gradient-square sum, boundary density)."""
    capacity = nb_out.capacity
    count = int(0)
    rho = p.self_density
    rho_boundary = float(0.0)
    grad_sum = wp.vec3(0.0)
    grad2 = float(0.0)
    query = wp.hash_grid_query(grid, xi, p.h)
    j = int(0)
    while wp.hash_grid_query_next(query, j):
        rij = xi - x[j]
        r2 = wp.dot(rij, rij)
        if r2 < p.h2 and j != self_index:
            if count < capacity:
                k = base + count * nb_out.stride_k
                nb_out.index[k] = j
                if with_density != 0:
                    wf = pair_terms(p, r2)
                    rho += wf[0]
                    grad_sum += wf[1] * rij
                    if j < first_fluid:
                        rho_boundary += wf[0]
                    else:
                        grad2 += wf[1] * wf[1] * r2
                    if nb_out.cache_gradients != 0:
                        nb_out.grad_factor[k] = wf[1]
            count += 1
    return count, rho, grad_sum, grad2, rho_boundary


@wp.func
def close_neighbor_list(nb_out: NeighborList, i: int, count: int, overflow_out: wp.array(dtype=int)) -> int:
    """Store particle i's list length (at most the capacity; overflow_out[0] receives the largest
    count that did not fit) and return it."""
    if count > nb_out.capacity:
        wp.atomic_max(overflow_out, 0, count)
        count = nb_out.capacity
    nb_out.count[i] = count
    return count


@wp.kernel
def find_neighbors_density(
    grid: wp.uint64,
    p: FluidParams,
    b: Boundaries,
    x: wp.array(dtype=wp.vec3),
    with_density: int,
    with_stats: int,
    nb_out: NeighborList,
    overflow_out: wp.array(dtype=int),
    density_out: wp.array(dtype=float),
    lambda_out: wp.array(dtype=float),
    boundary_grad_out: wp.array(dtype=wp.vec3),
    compression_out: wp.array(dtype=float),
):
    """Neighbour list of each particle (hash-grid candidates kept when |x_i - x_j| < h, j != i).
    With with_density != 0 it is fused with the first density evaluation
    (:func:`store_density_constraint`) and fills the pair gradient cache, saving a pass over the
    list (the CPU's choice); else only the list is built (on GPUs, where evaluating pairs inside
    the candidate loop would leave most threads of a warp idle) and the outputs after
    ``overflow_out`` are not touched. overflow_out[0] receives the largest count that did not fit
    (0 when all fit)."""
    tid = wp.tid()
    i = wp.hash_grid_point_id(grid, tid)
    xi = x[i]
    count, rho, grad_i, sum_grad2, unused = list_neighbors(grid, p, x, i, xi, 0, with_density, nb_out,
                                                           i * nb_out.stride_i)
    close_neighbor_list(nb_out, i, count, overflow_out)
    if with_density != 0:
        store_density_constraint(p, b, i, xi, rho, grad_i, sum_grad2, with_stats, density_out, lambda_out,
                                 boundary_grad_out, compression_out)


@wp.kernel
def predict_positions(
    p: FluidParams,
    b: Boundaries,
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    dt: float,
    x_pred_out: wp.array(dtype=wp.vec3),
):
    """x* = x + dt (v + dt g), kept in front of every plane."""
    i = wp.tid()
    x_pred_out[i] = project_planes(b, x[i] + dt * (v[i] + dt * p.gravity), p.radius)


@wp.kernel
def solve_density_lambda(
    p: FluidParams,
    b: Boundaries,
    x: wp.array(dtype=wp.vec3),
    nb: NeighborList,
    with_stats: int,
    counter: wp.array(dtype=int),
    limit: int,
    density_out: wp.array(dtype=float),
    lambda_out: wp.array(dtype=float),
    boundary_grad_out: wp.array(dtype=wp.vec3),
    compression_out: wp.array(dtype=float),
):
    """PBF (Macklin and Mueller 2013): density rho_i = sum_j m W_ij + rho0 phi_boundary over the
    neighbour list at the current positions and the multiplier lambda_i
    (:func:`store_density_constraint`); refreshes the list's gradient cache. Does nothing when
    counter[0] >= limit (the iteration loop's last correction needs no new multipliers)."""
    if counter[0] >= limit:
        return
    i = wp.tid()
    xi = x[i]
    rho = p.self_density
    grad_i = wp.vec3(0.0)
    sum_grad2 = float(0.0)
    e = i * nb.stride_i
    end = e + nb.count[i] * nb.stride_k
    while e < end:
        rij = xi - x[nb.index[e]]
        r2 = wp.dot(rij, rij)
        wf = pair_terms(p, r2)
        rho += wf[0]
        grad_i += wf[1] * rij
        sum_grad2 += wf[1] * wf[1] * r2
        if nb.cache_gradients != 0:
            nb.grad_factor[e] = wf[1]
        e += nb.stride_k
    store_density_constraint(p, b, i, xi, rho, grad_i, sum_grad2, with_stats, density_out, lambda_out,
                             boundary_grad_out, compression_out)


@wp.kernel
def solve_density_correct(
    p: FluidParams,
    b: Boundaries,
    x: wp.array(dtype=wp.vec3),
    nb: NeighborList,
    lam: wp.array(dtype=float),
    boundary_grad: wp.array(dtype=wp.vec3),
    lambda_sum_io: wp.array(dtype=float),
    x_out: wp.array(dtype=wp.vec3),
):
    """Jacobi position correction dx_i = sum_j m/rho0 (lambda_i + lambda_j) grad W_ij +
    lambda_i grad phi_boundary (gradients from the list's cache, i.e. at the positions ``x`` of
    the density pass that computed ``lam``), then kept in front of every plane. lambda_sum
    accumulates the applied multipliers over a step (zeroed by the host before the first)."""
    i = wp.tid()
    xi = x[i]
    li = lam[i]
    dx = li * boundary_grad[i]
    e = i * nb.stride_i
    end = e + nb.count[i] * nb.stride_k
    while e < end:
        j = nb.index[e]
        rij = xi - x[j]
        gf = float(0.0)
        if nb.cache_gradients != 0:
            gf = nb.grad_factor[e]
        else:
            gf = pair_terms(p, wp.dot(rij, rij))[1]
        dx += ((li + lam[j]) * gf) * rij
        e += nb.stride_k
    x_out[i] = project_planes(b, xi + dx, p.radius)
    lambda_sum_io[i] = lambda_sum_io[i] + li


@wp.kernel
def iteration_control(
    stats: wp.array(dtype=float),
    n: int,
    tolerance: float,
    peak_tolerance: float,
    min_iterations: int,
    max_iterations: int,
    advance: int,
    counter_io: wp.array(dtype=int),
    total_io: wp.array(dtype=int),
    go_out: wp.array(dtype=int),
):
    """One thread: counts ``advance`` more corrections (counter_io[0] this step or solve, total_io[0]
    overall) and sets go_out[0] = 1 while another one is due: fewer than ``max_iterations`` so far
    and fewer than ``min_iterations`` (DFSPH's solves: 1 and 2; PBF: 0), or the mean error
    stats[0] / n (PBF: the sum of the particles' compression C) at least
    ``tolerance`` (tolerance 0: always), or the largest compression stats[1] at least
    ``peak_tolerance``, or, for the step's first correction, that largest compression at least
    ``tolerance``. Both keep
    a local compression from building up over steps that stop early (or skip the solve) because
    the mean (over a fluid mostly at or below rest density) is small: the compression a step leaves becomes velocity,
    ~ C spacing / dt, so an unchecked C would kick harder the smaller the steps (and CFL
    sub-stepping, dt ~ spacing / v_max, then feeds the kick back into ever smaller steps). Runs
    on the device, so the loop (``wp.capture_while``) needs no host read-back in a CUDA graph."""
    it = counter_io[0] + advance
    counter_io[0] = it
    total_io[0] = total_io[0] + advance
    total = stats[0]
    peak = stats[1]
    go = int(0)
    due = it < min_iterations or total >= tolerance * float(n) or peak >= peak_tolerance
    if it < max_iterations and (due or (it == 0 and peak >= tolerance)):
        go = 1
    go_out[0] = go


@wp.kernel
def project_boundaries(p: FluidParams, b: Boundaries, x_io: wp.array(dtype=wp.vec3)):
    """Move particles out of capsules, spheres and meshes (then planes again): no particle leaks."""
    i = wp.tid()
    y = project_shapes(b, x_io[i], p.radius)
    x_io[i] = project_planes(b, y, p.radius)


@wp.func
def step_velocity(x_old: wp.array(dtype=wp.vec3), x_new: wp.array(dtype=wp.vec3), i: int,
                  inv_dt: float) -> wp.vec3:
    """PBF velocity (x_new - x_old) / dt of particle i [m/s]."""
    return (x_new[i] - x_old[i]) * inv_dt


@wp.kernel
def update_velocities(
    p: FluidParams,
    x_io: wp.array(dtype=wp.vec3),
    x_new: wp.array(dtype=wp.vec3),
    lambda_sum: wp.array(dtype=float),
    dt: float,
    v_out: wp.array(dtype=wp.vec3),
    pressure_out: wp.array(dtype=float),
):
    """v = (x_new - x) / dt, x = x_new; pressure p = -rho0 sum(lambda) / dt^2 [Pa]: the correction
    sum_j V (L_i + L_j) grad W_ij of L = sum(lambda) is the SPH gradient of L, and it equals dt^2
    times the pressure acceleration -grad p / rho0."""
    i = wp.tid()
    v_out[i] = step_velocity(x_io, x_new, i, 1.0 / dt)
    x_io[i] = x_new[i]
    pressure_out[i] = -p.rest_density * lambda_sum[i] / (dt * dt)


@wp.kernel
def compute_curl_normals(
    p: FluidParams,
    x_old: wp.array(dtype=wp.vec3),
    x: wp.array(dtype=wp.vec3),
    dt: float,
    density: wp.array(dtype=float),
    nb: NeighborList,
    curl_out: wp.array(dtype=wp.vec3),
    normal_out: wp.array(dtype=wp.vec3),
):
    """At positions x with velocities v = (x - x_old) / dt: vorticity
    w_i = sum_j m/rho_j grad_i W_ij x (v_j - v_i) [1/s] (the SPH curl of v) and Akinci's surface
    normal n_i = h sum_j m/rho_j grad_i W_ij (dimensionless)."""
    i = wp.tid()
    xi = x[i]
    inv_dt = 1.0 / dt
    vi = step_velocity(x_old, x, i, inv_dt)
    w = wp.vec3(0.0)
    nrm = wp.vec3(0.0)
    e = i * nb.stride_i
    end = e + nb.count[i] * nb.stride_k
    while e < end:
        j = nb.index[e]
        rij = xi - x[j]
        g = (pair_terms(p, wp.dot(rij, rij))[1] * p.rest_density / density[j]) * rij
        w += wp.cross(g, step_velocity(x_old, x, j, inv_dt) - vi)
        nrm += g
        e += nb.stride_k
    curl_out[i] = w
    normal_out[i] = p.h * nrm


@wp.kernel
def apply_velocity_filters(
    p: FluidParams,
    b: Boundaries,
    x_old: wp.array(dtype=wp.vec3),
    x: wp.array(dtype=wp.vec3),
    density: wp.array(dtype=float),
    nb: NeighborList,
    curl: wp.array(dtype=wp.vec3),
    normal: wp.array(dtype=wp.vec3),
    use_curl: int,
    lambda_sum: wp.array(dtype=float),
    dt: float,
    v_out: wp.array(dtype=wp.vec3),
    pressure_out: wp.array(dtype=float),
):
    """The step's velocities v = (x - x_old) / dt, filtered: XSPH viscosity (symmetric weights
    2m/(rho_i + rho_j), so momentum is conserved), boundary friction, vorticity confinement
    (Fedkiw et al. 2001, as in PBF) and Akinci et al. (2013) surface tension (cohesion +
    curvature, pairwise antisymmetric); and the pressure as in :func:`update_velocities`."""
    i = wp.tid()
    xi = x[i]
    inv_dt = 1.0 / dt
    vi = step_velocity(x_old, x, i, inv_dt)
    rhoi = density[i]
    h = p.h
    dv = wp.vec3(0.0)
    eta = wp.vec3(0.0)
    accel = wp.vec3(0.0)
    e = i * nb.stride_i
    end = e + nb.count[i] * nb.stride_k
    while e < end:
        j = nb.index[e]
        e += nb.stride_k
        rij = xi - x[j]
        r2 = wp.dot(rij, rij)
        r = wp.sqrt(r2)
        rhoj = density[j]
        dv += (2.0 * pair_density(p, r) / (rhoi + rhoj)) * (step_velocity(x_old, x, j, inv_dt) - vi)
        if use_curl != 0:
            eta += (pair_terms(p, r2)[1] * p.rest_density / rhoj * wp.length(curl[j])) * rij
            if p.surface_tension > 0.0 and r > 1.0e-9 * h:
                kij = 2.0 * p.rest_density / (rhoi + rhoj)
                coh = (-p.surface_tension * p.mass * cohesion_spline(r, h) / r) * rij
                curv = -p.surface_tension * (normal[i] - normal[j])
                accel += kij * (coh + curv)
    vnew = vi + p.viscosity * dv
    if p.wall_friction > 0.0:
        phi = boundary_density(b, xi, h)[3]
        vnew = vnew * wp.exp(-p.wall_friction * phi * dt)
    if use_curl != 0 and p.vorticity > 0.0:
        le = wp.length(eta)
        if le > 1.0e-9:
            accel += p.vorticity * wp.cross(eta / le, curl[i])
    v_out[i] = vnew + dt * accel
    pressure_out[i] = -p.rest_density * lambda_sum[i] / (dt * dt)


@wp.kernel
def reduce_speed(v: wp.array(dtype=wp.vec3), x: wp.array(dtype=wp.vec3), out: wp.array(dtype=float)):
    """out[0] = max |v| [m/s]; a non-finite position or velocity makes it +inf and records the
    particle's index in out[1] (as a float)."""
    i = wp.tid()
    vi = v[i]
    xi = x[i]
    s = wp.length(vi)
    finite = wp.isfinite(vi) and wp.isfinite(xi)
    if not finite:
        s = 1.0e30
        wp.atomic_min(out, 1, float(i))
    wp.atomic_max(out, 0, s)


@wp.kernel
def compression(density: wp.array(dtype=float), rest_density: float, c_out: wp.array(dtype=float)):
    """c = max(rho/rho0 - 1, 0) per particle (reduced in a fixed order by the host)."""
    i = wp.tid()
    c_out[i] = wp.max(density[i] / rest_density - 1.0, 0.0)


# ------------------------------------------------------------------------- emitters and sinks
@wp.kernel
def emit_particles(
    offsets: wp.array(dtype=wp.vec3),
    origin: wp.vec3,
    velocity: wp.vec3,
    start: int,
    first_id: int,
    x_out: wp.array(dtype=wp.vec3),
    v_out: wp.array(dtype=wp.vec3),
    ids_out: wp.array(dtype=int),
):
    """Write particle start + k at origin + offsets[k] with ``velocity`` and id first_id + k."""
    k = wp.tid()
    x_out[start + k] = origin + offsets[k]
    v_out[start + k] = velocity
    ids_out[start + k] = first_id + k


@wp.kernel
def mark_alive(
    x: wp.array(dtype=wp.vec3),
    sink_lower: wp.array(dtype=wp.vec3),
    sink_upper: wp.array(dtype=wp.vec3),
    alive_out: wp.array(dtype=int),
    removed_io: wp.array(dtype=int),
):
    """alive = 0 for particles inside a sink box [lower, upper] (counted in removed_io[sink] of
    the first such sink), else 1."""
    i = wp.tid()
    xi = x[i]
    alive = int(1)
    for s in range(sink_lower.shape[0]):
        lo = sink_lower[s]
        hi = sink_upper[s]
        inside = xi[0] >= lo[0] and xi[0] <= hi[0] and xi[1] >= lo[1] and xi[1] <= hi[1]
        if inside and xi[2] >= lo[2] and xi[2] <= hi[2] and alive == 1:
            alive = 0
            wp.atomic_add(removed_io, s, 1)
    alive_out[i] = alive


@wp.func
def move_particle(
    src: int,
    dst: int,
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    ids: wp.array(dtype=int),
    x_out: wp.array(dtype=wp.vec3),
    v_out: wp.array(dtype=wp.vec3),
    ids_out: wp.array(dtype=int),
):
    """Copy particle src's position, velocity and id to slot dst of the output arrays."""
    x_out[dst] = x[src]
    v_out[dst] = v[src]
    ids_out[dst] = ids[src]


@wp.kernel
def compact_particles(
    alive: wp.array(dtype=int),
    slot: wp.array(dtype=int),
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    ids: wp.array(dtype=int),
    x_out: wp.array(dtype=wp.vec3),
    v_out: wp.array(dtype=wp.vec3),
    ids_out: wp.array(dtype=int),
):
    """Stable compaction: a living particle i moves to slot[i] (exclusive prefix sum of alive)."""
    i = wp.tid()
    if alive[i] != 0:
        move_particle(i, slot[i], x, v, ids, x_out, v_out, ids_out)


@wp.kernel
def gather_sorted(
    grid: wp.uint64,
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    ids: wp.array(dtype=int),
    x_out: wp.array(dtype=wp.vec3),
    v_out: wp.array(dtype=wp.vec3),
    ids_out: wp.array(dtype=int),
):
    """Reorder particles into the hash grid's cell order (neighbours become neighbours in memory)."""
    tid = wp.tid()
    move_particle(wp.hash_grid_point_id(grid, tid), tid, x, v, ids, x_out, v_out, ids_out)
