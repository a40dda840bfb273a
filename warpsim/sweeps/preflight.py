"""Checks of a sweep request made before any simulation time is spent (``warpsim sweep``).

Everything knowable up front is refused here with one line that names the option, the value and
a fix: the seed, the world count against the memory it needs (estimated from one world of the
scene; the figure is in the message), the output paths, ``--rank`` / ``--where`` on parameters
that are not numbers and the syntax of a ``--ray`` address.
"""
from __future__ import annotations

import math
import os
import re

from ..core.memory import available_host_bytes
from ..strands.preflight import (STRAND_HOST_BYTES, STRAND_SOLVER_PARTICLE_BYTES, STRAND_VERTEX_HOST_BYTES,
                                 check_strand_memory, estimate_strand_bytes, format_bytes)

__all__ = ["HOST_BYTES_PER_WORLD", "LARGE_OUTPUT_BYTES", "STRAND_HOST_BYTES", "STRAND_SOLVER_PARTICLE_BYTES",
           "STRAND_VERTEX_HOST_BYTES", "available_host_bytes",
           "check_disk", "check_ray_address", "check_seed", "check_strand_memory", "check_worlds",
           "estimate_strand_bytes", "estimate_sweep_bytes", "format_bytes", "frame_time_note", "free_disk_bytes",
           "numeric_columns", "steps_note"]

HOST_BYTES_PER_WORLD = 4096
"""Host memory a world costs besides its particles [bytes]: its parameter dict, its table row,
its prim specs in the batch layer and the root's variant (a conservative round figure)."""

DEVICE_BYTES_PER_PARTICLE = 160
"""Device memory per particle of a batch [bytes]: state (positions, velocities, forces), the
last good positions, mass, inverse mass, radius, world index, initial arrays and integrator
temporaries (RK4 keeps four stages) (an upper estimate)."""

DEVICE_BYTES_PER_SPRING = 48
"""Device memory per spring [bytes]: two indices, rest length, stiffness, damping, CSR entries."""

WRITE_CHUNKS = 9
"""Chunks a sweep's writing holds in memory at most: one per worker process (8 at most) and the
one being gathered (:mod:`warpsim.usd.chunk_stage`)."""

HOST_BYTES_PER_PARTICLE = 96
"""Host memory per particle while frames are written [bytes]: the (N, P, 3) position and
velocity copies of a frame and the samples held until a chunk is saved."""


def check_seed(seed) -> int:
    """``--seed``: an integer in [0, 2**63)."""
    if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed < 2**63:
        raise ValueError(f"--seed {seed}: a seed is an integer in [0, 2^63), e.g. --seed 0")
    return seed


def check_worlds(n, available=None) -> int:
    """``--worlds`` before anything is sampled: >= 1, and its parameter dicts and rows alone fit
    in the host memory ``available`` [bytes] (default: what the system has now)."""
    if isinstance(n, bool) or not isinstance(n, int):
        raise ValueError(f"--worlds {n!r}: give a whole number of worlds, e.g. --worlds 64")
    if n < 1:
        raise ValueError(f"--worlds {n}: it must be >= 1")
    available = available_host_bytes() if available is None else int(available)
    need = n * HOST_BYTES_PER_WORLD
    if need > available:
        fit = max(available // HOST_BYTES_PER_WORLD, 1)
        raise ValueError(f"--worlds {n}: their parameters and table rows alone need about {format_bytes(need)} of "
                         f"memory ({HOST_BYTES_PER_WORLD} bytes a world), this machine has {format_bytes(available)} "
                         f"free; use at most about --worlds {fit}, or spread the sweep with --ray --batch-size B")
    return n


def estimate_sweep_bytes(particles, springs, worlds, batch_worlds=None) -> dict:
    """Estimated memory of a sweep of ``worlds`` worlds of ``particles`` particles and ``springs``
    springs each, run in batches of ``batch_worlds`` (default all): ``{"device", "host"}`` [bytes]."""
    b = worlds if batch_worlds is None else min(worlds, batch_worlds)
    device = b * (particles * DEVICE_BYTES_PER_PARTICLE + springs * DEVICE_BYTES_PER_SPRING)
    host = worlds * HOST_BYTES_PER_WORLD + b * particles * HOST_BYTES_PER_PARTICLE
    # chunks on their way to the disk: a chunk of up to 24 frames of points and velocities (24 bytes
    # a particle and frame), one per worker process and the one being gathered (at most 9 of 128 MiB)
    host += min(WRITE_CHUNKS * (128 << 20), WRITE_CHUNKS * b * particles * 24 * 24)
    return {"device": device, "host": host}


def check_sweep_memory(scene_name, particles, springs, worlds, device, batch_worlds=None):
    """Refuse (ValueError with the figures) a sweep whose estimate exceeds the device's free
    memory (CUDA) or the host's available memory (always)."""
    import warp as wp

    need = estimate_sweep_bytes(particles, springs, worlds, batch_worlds)
    dev = wp.get_device(device)
    what = f"{worlds} worlds of {scene_name} ({particles} particles, {springs} springs each)"
    fix = "use fewer --worlds" + ("" if batch_worlds else ", or --ray --batch-size B to run them in batches")
    if dev.is_cuda:
        free = int(getattr(dev, "free_memory", 0) or 0)
        if free and need["device"] > free:
            raise ValueError(f"--worlds {worlds}: {what} need about {format_bytes(need['device'])} on {dev}, which "
                             f"has {format_bytes(free)} free; {fix}")
        host_need = need["host"]
    else:
        host_need = need["host"] + need["device"]
    available = available_host_bytes()
    if host_need > available:
        raise ValueError(f"--worlds {worlds}: {what} need about {format_bytes(host_need)} of memory, this machine "
                         f"has {format_bytes(available)} free; {fix}")
    return need


LARGE_OUTPUT_BYTES = 10 << 20
"""Bytes of output above which a sweep says how much it will write before its first step."""


def free_disk_bytes(path) -> int:
    """Bytes free on the disk that holds ``path`` (its nearest existing folder)."""
    import shutil

    folder = os.path.abspath(os.fspath(path))
    while not os.path.isdir(folder) and os.path.dirname(folder) != folder:
        folder = os.path.dirname(folder)
    return int(shutil.disk_usage(folder).free)


def check_disk(out, need, detail="", free=None) -> str | None:
    """Refuse (ValueError naming the sizes and fixes) a sweep whose output ``out`` needs ``need``
    bytes where its disk has less free (``free``: default what it has now); else the line a
    large sweep (>= ``LARGE_OUTPUT_BYTES``) prints before its first step (None for a small one)."""
    free = free_disk_bytes(out) if free is None else int(free)
    where = os.path.relpath(os.path.dirname(os.path.abspath(os.fspath(out)))) + os.sep
    if need > free:
        raise ValueError(f"--out {out}: the sweep writes about {format_bytes(need)}{detail}, the disk holding "
                         f"{where} has {format_bytes(free)} free; free some space, write elsewhere with --out, or use "
                         "fewer --worlds or --frames")
    if need < LARGE_OUTPUT_BYTES:
        return None
    return f"writing about {format_bytes(need)} to {where}{detail}; the disk has {format_bytes(free)} free"


STEPS_NOTE = 1000
"""Steps a frame above which a run says how many before the first frame."""

LONG_RUN_NOTE = 60.0
"""Seconds a run is estimated to take (by the scene's ``frame_seconds``) above which it says so
before the first frame."""


def steps_note(scene, frame_dt, substeps, frames) -> str | None:
    """One line before the first frame when a frame takes many steps (> ``STEPS_NOTE``) or the
    automatic count stopped at its cap (``AUTO_MAX_SUBSTEPS``), with the figures; None otherwise."""
    from ..core.stability import AUTO_MAX_SUBSTEPS, AUTO_SAFETY

    try:
        steps = int(scene.frame_steps(frame_dt, substeps))
        limit = scene.stability()
    except (AttributeError, TypeError, ValueError, NotImplementedError):
        return None
    by = ""
    wanted = None
    if limit is not None and math.isfinite(getattr(limit, "dt", math.inf)) and limit.dt > 0:
        by = f", set by {limit.who()} (stability limit {limit.dt:.3g} s)"
        wanted = math.ceil(frame_dt / (AUTO_SAFETY * limit.dt) - 1e-9)
    frames = int(frames)
    total = steps * frames
    if steps == AUTO_MAX_SUBSTEPS and wanted is not None and wanted > steps:
        return (f"the automatic step count stopped at its cap of {AUTO_MAX_SUBSTEPS:,} steps a frame (step "
                f"{frame_dt / steps:.3g} s); the stability limit {limit.dt:.3g} s of {limit.who()} wants {wanted:,}: "
                "the step stays above it and the run may blow up; lower the stiffness or use integrator "
                "implicit_euler")
    seconds = _frame_seconds(scene, frame_dt, substeps)
    if steps > STEPS_NOTE:
        run = f": {frames} frames take {total:,} steps" if frames >= 1 else ""
        if seconds is not None and frames >= 1:
            run += f", about {_when(seconds * frames)}"
        return f"{steps:,} steps a frame (step {frame_dt / steps:.3g} s{by}){run}; lower the stiffness (or --fps) for fewer"
    if seconds is not None and frames >= 1 and seconds * frames > LONG_RUN_NOTE:
        from ..strands.preflight import estimate_basis

        return (f"{frames} frames of {steps:,} steps each take about {_when(seconds * frames)} ({_when(seconds)} a "
                f"frame, estimated {estimate_basis(getattr(scene, 'device', 'cpu'))}); fewer frames or a smaller "
                "scene is faster (Ctrl-C keeps the frames written)")
    return None


def _frame_seconds(scene, frame_dt, substeps):
    """The scene's own estimate of a frame's seconds (``scene.frame_seconds``), None without one."""
    try:
        seconds = float(scene.frame_seconds(frame_dt, substeps))
    except (AttributeError, TypeError, ValueError, NotImplementedError):
        return None
    return seconds if math.isfinite(seconds) else None


def _when(seconds):
    from ..strands.preflight import format_seconds

    return format_seconds(seconds)


FRAME_TIME_NOTE = 10.0
"""Seconds a frame after the first may take before a run estimates the whole run's time."""

LONG_REST_NOTE = 600.0
"""Seconds the rest of a run, estimated from a measured frame, may take before it is said even
when each frame is short."""


def frame_time_note(seconds, frames_left, device, frame=2, measured="stepping and writing",
                    fix="fewer frames or a smaller scene") -> str | None:
    """After frame ``frame`` took ``seconds`` [s] (``measured``: what the time covers): one line
    estimating the remaining ``frames_left`` frames from that measured frame, when the frame took
    longer than ``FRAME_TIME_NOTE`` or the rest longer than ``LONG_REST_NOTE``; None otherwise.
    ``frame`` is the second frame a run computes: the first compiles and loads Warp's kernels, so
    its time says nothing of the rest (a cloth run whose first frame took minutes then ran at
    several frames a second); no ratio between devices is assumed."""
    rest = seconds * frames_left
    if frames_left <= 0 or (seconds <= FRAME_TIME_NOTE and rest <= LONG_REST_NOTE):
        return None
    when = f"{rest / 3600:.3g} h" if rest >= 3600 else f"{rest / 60:.3g} min" if rest >= 60 else f"{rest:.3g} s"
    faster = "a CUDA device (--device cuda:0), " if str(device) == "cpu" else ""
    return (f"frame {frame} took {seconds:.3g} s on {device} ({measured}; frame {frame - 1}, which compiles Warp's "
            f"kernels, left out): estimated from frame {frame}, the other {frames_left} frames take about {when}; "
            f"{faster}{fix} is faster (Ctrl-C keeps the frames written)")


_HOST = re.compile(r"^(?:\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9](?:[A-Za-z0-9.-]*[A-Za-z0-9])?)$")


def check_ray_address(address):
    """``--ray ADDRESS`` syntax: ``local`` (no address), ``auto``, ``HOST:PORT`` or
    ``ray://HOST:PORT``; returns ``(host, port)`` (None for local / auto). ValueError naming the
    address and the forms otherwise."""
    if address in (None, "local", "auto"):
        return None
    text = str(address).strip()
    forms = "give HOST:PORT (e.g. 10.0.0.5:6379), ray://HOST:PORT (e.g. ray://head:10001), auto, or --ray alone " \
            "for a local cluster"
    body = text[len("ray://"):] if text.startswith("ray://") else text
    host, sep, port = body.rpartition(":")
    if not sep or not host or not _HOST.match(host) or not port.isdigit():
        raise ValueError(f"--ray {address!r} is not a cluster address; {forms}")
    if not 1 <= int(port) <= 65535:
        raise ValueError(f"--ray {address!r}: port {port} is outside 1..65535; {forms}")
    return host.strip("[]"), int(port)


def numeric_columns(world_params) -> set:
    """Names of the parameters of ``world_params`` (dicts) that hold one number in every world
    (the ones ``--rank`` / ``--where`` can compare)."""
    if not world_params:
        return set()
    out = set()
    for key in world_params[0]:
        if all(isinstance(p.get(key), (int, float)) for p in world_params):
            out.add(key)
    return out
