"""Fixed-order reductions: sums and maxima whose float result does not depend on thread scheduling,
so a run gives the same bits on every device, every time (float atomics add in arrival order).

Two stages, both with a fixed summation order:

1. a stage's own kernel (see ``sum_max_strided`` here, ``fluid_sums`` in kernels/grid.py) gives
   each of S slots the values at indices s, s + S, s + 2S, ... in increasing order, one thread per
   slot (neighbouring threads read neighbouring values, so loads coalesce on GPUs);
2. :func:`reduce_rows` folds ``group`` consecutive rows into one, level after level, until one
   row is left (host: ``warpsim.core.reduction.FixedOrderReduction``).

Partials are 2D (rows, columns): columns below ``first_max_column`` are sums, the others maxima.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})

LOWEST = wp.constant(-3.4e38)  # the identity of max for float32 values


@wp.kernel
def sum_max_strided(values: wp.array(dtype=float), count: int, partial_out: wp.array2d(dtype=float)):
    """partial_out[s] = (sum, max) of values[s], values[s + S], ... below ``count`` (S =
    partial_out.shape[0] slots), added in index order; an empty slot holds (0, LOWEST)."""
    s = wp.tid()
    stride = partial_out.shape[0]
    total = float(0.0)
    peak = float(LOWEST)
    i = s
    while i < count:
        value = values[i]
        total += value
        peak = wp.max(peak, value)
        i += stride
    partial_out[s, 0] = total
    partial_out[s, 1] = peak


@wp.kernel
def reduce_rows(partial: wp.array2d(dtype=float), group: int, first_max_column: int,
                out: wp.array2d(dtype=float)):
    """out[r, q] = sum (q < first_max_column) or max (otherwise) of partial[r * group + m, q],
    m = 0 .. group - 1 (rows beyond partial's end skipped), in row order."""
    r, q = wp.tid()
    begin = r * group
    end = wp.min(begin + group, partial.shape[0])
    use_max = q >= first_max_column
    value = wp.where(use_max, LOWEST, 0.0)
    for m in range(begin, end):
        x = partial[m, q]
        if use_max:
            value = wp.max(value, x)
        else:
            value += x
    out[r, q] = value
