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


def time_per_graph_launch(fn, steps, device):
    """Seconds per replay of ``fn`` captured once as a CUDA graph on ``device``."""
    with wp.ScopedCapture(device=device) as capture:
        fn()
    return time_per_call(lambda: wp.capture_launch(capture.graph), steps, device)
