"""Shared timer for the benchmark scripts (run as ``python benchmarks/NAME.py``)."""

import time

import warp as wp


def time_per_call(fn, steps, device=None):
    """Seconds per call of ``fn`` over ``steps`` calls, after one warm-up call (kernel compiles);
    synchronises ``device`` around the loop when given (GPU work is asynchronous)."""
    fn()
    if device is not None:
        wp.synchronize_device(device)
    t0 = time.perf_counter()
    for _ in range(steps):
        fn()
    if device is not None:
        wp.synchronize_device(device)
    return (time.perf_counter() - t0) / steps
