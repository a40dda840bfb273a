"""Launch helpers shared by every solver: ``cached_launch`` (a recorded ``wp.Launch`` replayed
without re-packing its arguments on the CPU) and ``recording`` / ``recording_tape`` (the
``wp.Tape`` that warpsim code is recording on, so that stages whose forward and backward kernels
differ, e.g. the springs' fixed-order gather, can record the backward kernel by hand).

Warp has no public call that names the tape being recorded: a tape entered through ``recording``
is known here; a plain ``with wp.Tape():`` still records every launch whose arrays require
gradients (``cached_launch`` never caches those), so gradients stay correct either way.
"""

from __future__ import annotations

import contextlib
import ctypes

import warp as wp

_TAPE: list = [None]
"""The tape entered through ``recording`` (or None)."""


@contextlib.contextmanager
def recording(tape: wp.Tape):
    """``with recording(tape):`` is ``with tape:`` that warpsim's stages can see
    (``recording_tape``); used by ``warpsim.diff.Rollout``."""
    if _TAPE[0] is not None:
        raise RuntimeError("warpsim: a tape is already recording; finish it before entering another")
    with tape:
        _TAPE[0] = tape
        try:
            yield tape
        finally:
            _TAPE[0] = None


def recording_tape():
    """The ``wp.Tape`` entered through ``recording`` that records now, or None."""
    return _TAPE[0]


def cached_launch(kernel, dim, inputs, device, cache: dict, key=None, size: int = 8) -> None:
    """``wp.launch(kernel, dim, inputs)`` through a recorded ``wp.Launch`` kept in ``cache`` per
    (dim, arrays by identity, scalars by value): on the CPU packing a launch's arguments costs
    ~1-2 us each, a recorded launch replays without it. At most ``size`` entries (then cleared);
    each entry keeps its arrays referenced, so their ids cannot be reused while it lives. While a
    tape entered with ``recording`` records, while a graph is being captured, and whenever an
    input array requires gradients (so a plain ``wp.Tape`` records it), it launches plainly (they see only
    ``wp.launch``). ``key``: the caller's own hashable stand-in for (dim, inputs) with the same
    meaning (cheaper than the generic one)."""
    if _TAPE[0] is not None or (device if isinstance(device, wp.Device) else wp.get_device(device)).is_capturing:
        wp.launch(kernel, dim, inputs=list(inputs), device=device)
        return
    if key is None:
        key = (dim, *(id(a) if isinstance(a, wp.array) else (type(a).__name__, tuple(a) if hasattr(a, "__len__") else a)
                      for a in inputs))
    entry = cache.get(key)
    if entry is None:
        if any(isinstance(a, wp.array) and a.requires_grad for a in inputs):  # any tape records it
            wp.launch(kernel, dim, inputs=list(inputs), device=device)
            return
        if len(cache) >= size:
            cache.clear()
        cmd = wp.launch(kernel, dim, inputs=list(inputs), device=device, record_cmd=True)
        cmd.launch()  # this call's launch (it also fills Warp's struct-type cache _cpu_replay reads)
        cache[key] = (_cpu_replay(cmd) or cmd.launch, inputs)
        return
    entry[0]()


def _cpu_replay(cmd):
    """A callable that runs the recorded CPU launch ``cmd`` with its argument struct packed once
    (what ``wp.Launch.launch`` does on the CPU, less re-packing ~10 ctypes fields per call:
    ~8 us a launch), or None where that path does not apply (CUDA, tiled launches, Warp
    internals not as expected: then ``cmd.launch`` is used)."""
    try:
        if not cmd.device.is_cpu or cmd.block_dim > 1 or cmd.adjoint:
            return None
        params = cmd.params
        struct, fields = cmd.kernel._invoke_cache[(tuple(type(p) for p in params[1:]), False)]
        args = struct()
        for i, field in enumerate(fields):
            setattr(args, field[0], params[1 + i])
        forward, bounds, packed = cmd.hooks.forward, ctypes.byref(params[0]), ctypes.byref(args)
    except (AttributeError, KeyError, TypeError, ValueError):
        return None

    def replay(args=args, params=params):  # the defaults keep the packed structs alive
        forward(bounds, packed)

    return replay
