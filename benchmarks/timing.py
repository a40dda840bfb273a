"""Shared timer for the benchmark scripts (run as ``python benchmarks/NAME.py``)."""

import re
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


def eager_and_graph(step, period, calls, device, rounds=3):
    """(eager, graph) seconds per step of ``step`` (one call: one step) taken ``period`` at a time, eagerly
    and replayed from one CUDA graph of ``period`` steps; the fastest of ``rounds`` alternating rounds of
    ``calls`` x ``period`` steps each (the state moves on between rounds: one round of each is not a fair
    comparison)."""

    def steps():
        for _ in range(period):
            step()

    with wp.ScopedCapture(device=device) as capture:
        steps()
    eager, graph = [], []
    for _ in range(rounds):
        eager.append(time_per_call(steps, calls, device) / period)
        graph.append(time_per_call(lambda: wp.capture_launch(capture.graph), calls, device) / period)
    return min(eager), min(graph)


def activity_name(result) -> str:
    """The kernel's Python name of one ``wp.timing_end`` result (``"forward kernel query_pairs_c0c45f87"`` ->
    ``"query_pairs"``; built-ins and copies as Warp names them, e.g. ``"builtin kernel bvh_refit_kernel"``)."""
    name = (result.name or "?").split("(")[0].strip()
    kernel = re.fullmatch(r"(?:forward|backward) kernel (\w+?)(?:_[0-9a-f]{8})?", name)
    return kernel.group(1) if kernel else name
