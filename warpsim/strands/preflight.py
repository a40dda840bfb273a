"""Sizes and times of a groom checked before anything of it is built (the ``hair`` scene; the
sweep's preflight re-exports the memory check).

The estimate covers every array a groom's build makes: the scalp lattice and the groomed polylines
(``(strands, 160, 3)`` float64 and their temporaries), the builder's lists and the model, the
implicit step's scratch, the dense Jacobians the stability limit takes of a sample of strands
(``warpsim.strands.stability``: ``(S, 3 segments, 3 segments)`` float64 matrices, S <= 48) and the
head's poses of a frame's steps (``HeadPoses``: two transforms a step). Each check raises a
ValueError naming the parameter, its value, the estimate and a fix.
"""

from __future__ import annotations

import math

from ..core.memory import available_host_bytes

__all__ = ["DENSE_MATRICES", "FRAME_SECONDS_LIMIT", "POSE_BYTES_PER_STEP", "STEP_SECONDS", "STRAND_HOST_BYTES",
           "STRAND_SOLVER_PARTICLE_BYTES", "STRAND_VERTEX_DEVICE_BYTES", "STRAND_VERTEX_HOST_BYTES",
           "check_hair_params", "check_hair_steps", "check_strand_memory", "dense_bytes", "dense_seconds",
           "estimate_basis", "estimate_strand_bytes", "format_bytes", "format_seconds", "frame_seconds",
           "segments_fit"]

STRAND_HOST_BYTES = 16 << 10
"""Host memory per strand while a groom is built [bytes]: its scalp lattice entries and the
polyline it is resampled from (160 samples of 3 doubles and the temporaries ``groom`` makes;
measured: 14 KiB a strand for the curly groom at its peak)."""

STRAND_VERTEX_HOST_BYTES = 1280
"""Host memory per strand vertex while a groom is built and solved sag-free [bytes]: builder
lists, spring and bending arrays, the model's host copies and the sag-free solve's unknowns;
measured: 660 B building, about 1,150 B with the sag-free solve."""

STRAND_VERTEX_DEVICE_BYTES = 160 + 2 * 48
"""Device memory per strand vertex [bytes]: the particle arrays of a model (state, masses,
initial arrays, integrator temporaries) and two springs' worth of strand data."""

STRAND_SOLVER_PARTICLE_BYTES = 3 * 128 + 32 + 2 * 12
"""Device memory per strand particle (the vertices and a ghost a strand) of the implicit strand
step's scratch [bytes] (``warpsim.strands.implicit.StrandImplicitEuler``'s arrays: three 4x4 float64
factor blocks and a float64 right-hand side a slot, two vec3 a particle; summed: 440 B a particle)."""

SAMPLE = 48
"""Strands whose dense Jacobians the stability limit takes at most (``warpsim.strands.stability.SAMPLE``)."""

DENSE_MATRICES = {"implicit": 12, "explicit": 16}
"""(S, 3 segments, 3 segments) float64 matrices alive at once while the stability limit is taken
(implicit: K, D, the assembled stiffness and its band matrix, the solve; measured peak 7.8 of them
at 32 and 64 segments; explicit: K, D and the (S, 6 segments, 6 segments) system and its eigenvalue
workspace)."""

DENSE_FLOP_SECONDS = 1.0e-8
"""Seconds per S (3 segments)^3 of the stability limit's dense solves on the CPU at the least
(measured 7.8e-9 at 48 strands x 64 segments, 2 cores); when the implicit limit's bisection runs
(the assembled stiffness misjudges the strands) it is about 25 times more (2 strands x 256
segments: 188 s)."""

STEP_SECONDS = {"implicit": (2.0e-4, 4.5e-7), "explicit": (2.0e-4, 6.0e-8)}
"""CPU seconds of one strand step: (per step, per particle) (measured on 2 cores: implicit 1.5 ms
a step at 1,632 particles, 3 ms at 3,168, 0.2 ms at 8, 16 ms at 36,000; explicit 0.30 ms at 1,632, 0.39 ms at
3,168). CUDA
steps are taken as ten times faster (an estimate for notes and refusals only)."""

POSE_BYTES_PER_STEP = 2 * 28
"""Bytes of the head's poses a strand step of a frame (``HeadPoses``: two float32 transforms),
on the device and, on CUDA, once more on the host."""

FRAME_SECONDS_LIMIT = 3600.0
"""Estimated seconds of one frame above which a groom is refused (a frame of over an hour is not
a run anyone waits for); below it, the estimate is said before the first step."""


def format_bytes(n) -> str:
    """``1.5 GiB``-style text for a byte count."""
    n = float(n)
    for unit in ("bytes", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if n < 1024 or unit == "PiB":
            return f"{n:.0f} {unit}" if unit == "bytes" else f"{n:.3g} {unit}"
        n /= 1024
    return f"{n:.3g} EiB"  # pragma: no cover


def format_seconds(s) -> str:
    """``12 s`` / ``3.5 min`` / ``2.1 h`` / ``4.2 days``."""
    s = float(s)
    if s >= 2 * 86400:
        return f"{s / 86400:.3g} days"
    if s >= 3600:
        return f"{s / 3600:.3g} h"
    if s >= 60:
        return f"{s / 60:.3g} min"
    return f"{s:.2g} s"


def _cuda(device) -> bool:
    return device is not None and str(device).startswith("cuda")


def dense_bytes(strands, segments, solver="implicit") -> int:
    """Host bytes of the dense Jacobians the stability limit takes of a sample of the strands."""
    sample = min(int(strands), SAMPLE)
    n = 3 * int(segments)
    return DENSE_MATRICES.get(solver, 16) * sample * n * n * 8


def dense_seconds(strands, segments, solver="implicit") -> float:
    """Estimated CPU seconds of the stability limit's dense solves (eigenvalues of (S, N, N), N = 3
    segments; the explicit solver's system is twice as wide: 8 times the work)."""
    n = 3.0 * int(segments)
    return DENSE_FLOP_SECONDS * min(int(strands), SAMPLE) * n ** 3 * (8.0 if solver == "explicit" else 1.0)


def estimate_strand_bytes(strands, segments, solver="implicit") -> dict:
    """Estimated memory of a groom of ``strands`` strands of ``segments`` segments:
    ``{"host", "device", "vertices", "dense"}`` (bytes, bytes, count, bytes); the host figure
    includes the stability limit's dense matrices (``dense``), the device figure the implicit
    strand step's scratch (the scene's default solver)."""
    vertices = int(strands) * (int(segments) + 1)
    dense = dense_bytes(strands, segments, solver)
    host = int(strands) * STRAND_HOST_BYTES + vertices * STRAND_VERTEX_HOST_BYTES + dense
    device = vertices * STRAND_VERTEX_DEVICE_BYTES + int(strands) * (int(segments) + 2) * STRAND_SOLVER_PARTICLE_BYTES
    return {"host": host, "device": device, "vertices": vertices, "dense": dense}


def segments_fit(strands, solver="implicit", available=None) -> int:
    """Most segments whose dense Jacobians take at most half of ``available`` bytes and a tenth
    of ``FRAME_SECONDS_LIMIT`` to solve."""
    sample = min(int(strands), SAMPLE)
    by_time = (FRAME_SECONDS_LIMIT / 10.0 / (DENSE_FLOP_SECONDS * sample * (8.0 if solver == "explicit" else 1.0))
               ) ** (1.0 / 3.0) / 3.0
    fit = by_time
    if available is not None:
        fit = min(fit, math.sqrt(available / 2 / (DENSE_MATRICES.get(solver, 16) * sample * 72)))
    return max(1, int(fit))


def check_strand_memory(strands, segments, device=None, available=None, solver="implicit") -> dict:
    """Refuse (ValueError with the figures, before anything is allocated) a groom whose memory
    estimate (``estimate_strand_bytes``, dense matrices included) exceeds the host's available
    memory (or, on CUDA, the device's free memory)."""
    need = estimate_strand_bytes(strands, segments, solver)
    available = available_host_bytes() if available is None else int(available)
    what = f"strands={strands} x segments={segments} ({need['vertices']:,} vertices)"
    host = need["host"] + (0 if _cuda(device) else need["device"])
    if host > available:
        if need["dense"] > available // 2:  # the segments' dense matrices alone: fewer strands do not help
            n = 3 * int(segments)
            raise ValueError(f"segments={segments}: {what} needs about {format_bytes(host)} of memory to build, "
                             f"{format_bytes(need['dense'])} of it the dense Jacobians of the stability limit "
                             f"({min(int(strands), SAMPLE)} x {n:,} x {n:,} float64 matrices), this machine has "
                             f"{format_bytes(available)} free; use at most about "
                             f"segments={segments_fit(strands, solver, available):,}")
        per = STRAND_HOST_BYTES + (int(segments) + 1) * STRAND_VERTEX_HOST_BYTES
        if not _cuda(device):
            per += (int(segments) + 1) * STRAND_VERTEX_DEVICE_BYTES + (int(segments) + 2) * STRAND_SOLVER_PARTICLE_BYTES
        fit = max(1, int(0.8 * (available - need["dense"])) // per)
        raise ValueError(f"{what} needs about {format_bytes(host)} of memory to build, this machine has "
                         f"{format_bytes(available)} free; use at most about strands={fit:,} at segments={segments}, "
                         "or fewer segments")
    if _cuda(device):
        import warp as wp

        free = int(getattr(wp.get_device(device), "free_memory", 0) or 0)
        if free and need["device"] > free:
            raise ValueError(f"{what} needs about {format_bytes(need['device'])} on {device}, which has "
                             f"{format_bytes(free)} free; use fewer strands or segments")
    return need


def estimate_basis(device="cpu", later=True) -> str:
    """What :func:`frame_seconds` rests on, said with every figure made from it (``later``: add
    that the run says frame 2's measured time)."""
    then = "; frame 2's time is said when the run is long" if later else ""
    if _cuda(device):
        return ("from strand steps timed on a 2-core CPU, taken as ten times faster on CUDA: an assumed ratio, not "
                f"measured here{then}")
    return f"from strand steps timed on a 2-core CPU, not on this machine{then}"


def frame_seconds(steps, particles, solver="implicit", device="cpu") -> float:
    """Estimated seconds of one frame of ``steps`` strand steps of ``particles`` particles."""
    per_step, per_particle = STEP_SECONDS.get(solver, STEP_SECONDS["implicit"])
    seconds = int(steps) * (per_step + int(particles) * per_particle)
    return seconds / 10.0 if _cuda(device) else seconds


def check_hair_steps(steps, strands, segments, solver="implicit", device="cpu", available=None,
                     name="steps") -> float:
    """Refuse (ValueError naming ``name`` = its value, the estimate and a fix) ``steps`` strand
    steps a frame whose head poses do not fit in memory or whose frame is estimated above
    ``FRAME_SECONDS_LIMIT``; returns the estimated seconds of a frame."""
    steps = int(steps)
    particles = int(strands) * (int(segments) + 2)
    available = available_host_bytes() if available is None else int(available)
    unit = POSE_BYTES_PER_STEP + (POSE_BYTES_PER_STEP if _cuda(device) else 0)
    per = frame_seconds(1, particles, solver, device)
    fit = max(1, min(int(FRAME_SECONDS_LIMIT / 10.0 / per), available // (2 * unit)))
    if steps * unit > available:
        raise ValueError(f"{name}={steps:,}: a frame's strand steps keep the head's poses, about "
                         f"{format_bytes(steps * unit)} ({POSE_BYTES_PER_STEP} bytes a step), this machine has "
                         f"{format_bytes(available)} free; use at most about {name}={fit:,} (the default is 4)")
    seconds = frame_seconds(steps, particles, solver, device)
    if seconds > FRAME_SECONDS_LIMIT:
        raise ValueError(f"{name}={steps:,}: one frame of {steps:,} strand steps of {particles:,} particles takes "
                         f"about {format_seconds(seconds)} on {device} (estimated {estimate_basis(device, False)}); "
                         f"use at most about {name}={fit:,} (a frame of about {format_seconds(fit * per)}), or fewer "
                         "strands or segments")
    return seconds


SAG_FREE_MIN_SEGMENTS = 2
"""Segments a strand needs for a sag-free rest state: one segment cannot hold its tip against
gravity within the bound (measured: 11 % of the load left at every strand count)."""


def check_hair_params(p, device="cpu", available=None) -> dict:
    """Every size of the hair scene's parameters ``p`` (strands, segments, steps, the solver's
    dense stability check, the sag-free solve) checked before anything is built: ValueError naming
    the parameter, the value, the estimate and a fix; returns the memory estimate."""
    strands, segments, solver = int(p["strands"]), int(p["segments"]), p.get("solver", "implicit")
    if p.get("sag_free", False) and segments < SAG_FREE_MIN_SEGMENTS:
        raise ValueError(f"segments={segments}: a strand of one segment cannot be made sag-free (its tip cannot be "
                         f"held against gravity within the bound max_strain=0.2); use segments>={SAG_FREE_MIN_SEGMENTS}"
                         " or sag_free=false")
    need = check_strand_memory(strands, segments, device, available, solver)
    dense = dense_seconds(strands, segments, solver)
    if dense > FRAME_SECONDS_LIMIT:
        n = 3 * segments
        raise ValueError(f"segments={segments}: the stability limit's dense Jacobians ({min(strands, SAMPLE)} x "
                         f"{n:,} x {n:,} float64 matrices) take at least {format_seconds(dense)} to solve; use at "
                         f"most about segments={segments_fit(strands, solver):,}")
    if solver == "implicit":
        check_hair_steps(p["steps"], strands, segments, solver, device, available)
    return need
