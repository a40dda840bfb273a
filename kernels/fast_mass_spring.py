"""Fast mass-spring step: backward Euler as local-global iterations with one constant matrix
(Liu, Bargteil, O'Brien and Kavan, "Fast Simulation of Mass-Spring Systems", SIGGRAPH Asia 2013;
``warpsim.core.fast_mass_spring.FastMassSpring`` drives these kernels).

A backward Euler step of springs is the minimiser of the incremental potential

    g(x) = 1/(2 h^2) |x - y|_M^2 + sum_s k_s/2 |x_i - x_j - d_s|^2 + damping,    y = x0 + h v0 + h^2 M^-1 f_ext,

with each spring's direction d_s (length L_s) free: fixing x, the best d_s is L_s (x_i - x_j) / |x_i - x_j|
(the local step); fixing the d_s, g is quadratic in x with the constant matrix

    A = M + h C_L + h^2 K_L    (K_L, C_L the springs' stiffness and damping Laplacians)

(the global step: x = A^-1 b). Each iteration lowers g (block coordinate descent, tested); stopped
early, the step is not backward Euler's, and where h^2 k / m is large the energy can rise (measured in
``tests/test_fast_mass_spring.py``). Springs are damped isotropically, c_s (v_j - v_i), not only along
the spring as ``Springs`` damps: the damping stays in the constant matrix.

The particles are copies of one body of P particles (copy t holds particles t P .. t P + P - 1), all
with the same springs, masses, stiffnesses and rest lengths, so A^-1 (P x P, dense, float32) is
stored once and the global step of every copy is one matrix product: the right-hand sides of copy
t's x, y and z coordinates are rows 3t, 3t + 1, 3t + 2 of B (3T x P) and X = B A^-1 (A symmetric).
The product is tiled (``wp.tile_matmul``); each output element sums its row in the same order
whatever the number of copies, so a copy's result does not depend on the others (bit for bit).
"""

import warp as wp

wp.set_module_options({"enable_backward": False})

TILE_THREADS = 256
"""Threads of a tile block on CUDA (the CPU runs a tile block on one thread)."""


@wp.kernel
def predict(q: wp.array(dtype=wp.vec3), qd: wp.array(dtype=wp.vec3), f_ext: wp.array(dtype=wp.vec3),
            inv_mass: wp.array(dtype=float), h: float, q0_out: wp.array(dtype=wp.vec3),
            y_out: wp.array(dtype=wp.vec3)):
    """Keep the start positions (q0), the inertial target y = q0 + h v0 + h^2 f_ext / m [m]; the
    first iterate is y."""
    i = wp.tid()
    x = q[i]
    y = x + h * qd[i] + (h * h * inv_mass[i]) * f_ext[i]
    q0_out[i] = x
    y_out[i] = y
    q[i] = y


@wp.kernel
def local_rhs(q: wp.array(dtype=wp.vec3), q0: wp.array(dtype=wp.vec3), y: wp.array(dtype=wp.vec3),
              mass: wp.array(dtype=float), entry_offsets: wp.array(dtype=int), entry_other: wp.array(dtype=int),
              entry_rest: wp.array(dtype=float), entry_stiffness: wp.array(dtype=float),
              entry_damping: wp.array(dtype=float), proximal: wp.array(dtype=float), body_size: int,
              rhs_out: wp.array2d(dtype=float)):
    """Local step and right-hand side for particle i (copy t, column c = i - t P): b_i = m_i y_i +
    w_c q_i + sum over the springs of column c (the copy's CSR row, in its fixed order) of h^2 k_s d_s
    + h c_s (q0_i - q0_j), with j = t P + the spring's other end, d_s = L_s (q_i - q_j) / |q_i - q_j|
    the spring's best direction at the current iterate and w_c = ``proximal`` (contact vertices:
    h^2 k_c, the pull toward the contact-projected iterate; A holds w on its diagonal) [kg m].
    ``entry_stiffness`` and ``entry_damping`` hold h^2 k_s and h c_s. The spring tables are one
    copy's (small: they stay in cache). Written to B (3T x P, row major): row 3 t + coordinate."""
    i = wp.tid()
    t = i / body_size
    col = i - t * body_size
    base = t * body_size
    xi = q[i]
    x0 = q0[i]
    b = mass[i] * y[i] + proximal[col] * xi
    for a in range(entry_offsets[col], entry_offsets[col + 1]):
        j = base + entry_other[a]
        u = xi - q[j]
        l = wp.length(u)
        d = wp.vec3()
        if l > 1.0e-12:
            d = u * (entry_rest[a] / l)
        b = b + entry_stiffness[a] * d + entry_damping[a] * (x0 - q0[j])
    rhs_out[3 * t, col] = b[0]
    rhs_out[3 * t + 1, col] = b[1]
    rhs_out[3 * t + 2, col] = b[2]


def tile_product(tile: int):
    """The global step's kernel with square tiles of ``tile``: X = B A^-1 for one (tile x tile)
    output block, B (3T x P), A^-1 (P x P, symmetric), the inner dimension in tile steps in a fixed
    order (tiles past the edges read zeros). Made at import for the sizes in ``GLOBAL_SOLVE``."""
    size = wp.constant(tile)

    def global_solve(rhs: wp.array2d(dtype=float), inverse: wp.array2d(dtype=float), x_out: wp.array2d(dtype=float)):
        i, j = wp.tid()
        acc = wp.tile_zeros(shape=(size, size), dtype=float)
        steps = (inverse.shape[0] + size - 1) / size
        for k in range(steps):
            a = wp.tile_load(rhs, shape=(size, size), offset=(i * size, k * size))
            b = wp.tile_load(inverse, shape=(size, size), offset=(k * size, j * size))
            wp.tile_matmul(a, b, acc)
        wp.tile_store(x_out, acc, offset=(i * size, j * size))

    return wp.Kernel(global_solve, key=f"global_solve_{tile}")


GLOBAL_SOLVE = {tile: tile_product(tile) for tile in (32, 64)}
"""Tile size -> global-step kernel: 32 on the CPU and for small batches (less padding), 64 on CUDA
for large ones (twice the arithmetic per byte loaded; ``benchmarks/RESULTS.md``)."""


@wp.kernel
def scatter_positions(x: wp.array2d(dtype=float), body_size: int, q_out: wp.array(dtype=wp.vec3)):
    """q_i = the global step's solution for particle i (rows 3 t .. 3 t + 2, column i - t P of X)."""
    i = wp.tid()
    t = i / body_size
    col = i - t * body_size
    q_out[i] = wp.vec3(x[3 * t, col], x[3 * t + 1, col], x[3 * t + 2, col])


@wp.kernel
def chebyshev_step(q: wp.array(dtype=wp.vec3), omega: float, older_io: wp.array(dtype=wp.vec3),
                   old_io: wp.array(dtype=wp.vec3)):
    """Chebyshev semi-iterative acceleration (Wang, "A Chebyshev Semi-Iterative Approach for
    Accelerating Projective and Position-based Dynamics", 2015): x_{k+1} = x_{k-1} + omega_{k+1}
    (x_hat_{k+1} - x_{k-1}), x_hat the plain iterate in q; keeps the last two iterates."""
    i = wp.tid()
    x = older_io[i] + omega * (q[i] - older_io[i])
    older_io[i] = old_io[i]
    old_io[i] = x
    q[i] = x


@wp.kernel
def finish_step(q: wp.array(dtype=wp.vec3), q0: wp.array(dtype=wp.vec3), inv_h: float, qd_out: wp.array(dtype=wp.vec3)):
    """Backward Euler's velocity v1 = (x1 - x0) / h [m/s]."""
    i = wp.tid()
    qd_out[i] = (q[i] - q0[i]) * inv_h
