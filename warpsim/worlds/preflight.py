"""Checks of a sweep request made before any simulation time is spent (``warpsim sweep``).

Everything knowable up front is refused here with one line that names the option, the value and
a fix: the seed, the world count against the memory it needs (estimated from one world of the
scene; the figure is in the message), the output paths, ``--rank`` / ``--where`` on parameters
that are not numbers and the syntax of a ``--ray`` address.
"""
from __future__ import annotations

import os
import re

__all__ = ["HOST_BYTES_PER_WORLD", "available_host_bytes", "check_ray_address", "check_seed", "check_worlds",
           "estimate_sweep_bytes", "format_bytes", "numeric_columns"]

HOST_BYTES_PER_WORLD = 4096
"""Host memory a world costs besides its particles [bytes]: its parameter dict, its table row,
its prim specs in the batch layer and the root's variant (a conservative round figure)."""

DEVICE_BYTES_PER_PARTICLE = 160
"""Device memory per particle of a batch [bytes]: state (positions, velocities, forces), the
last good positions, mass, inverse mass, radius, world index, initial arrays and integrator
temporaries (RK4 keeps four stages) (an upper estimate)."""

DEVICE_BYTES_PER_SPRING = 48
"""Device memory per spring [bytes]: two indices, rest length, stiffness, damping, CSR entries."""

HOST_BYTES_PER_PARTICLE = 96
"""Host memory per particle while frames are written [bytes]: the (N, P, 3) position and
velocity copies of a frame and the samples held until a chunk is saved."""


def format_bytes(n) -> str:
    """``1.5 GiB``-style text for a byte count."""
    n = float(n)
    for unit in ("bytes", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if n < 1024 or unit == "PiB":
            return f"{n:.0f} {unit}" if unit == "bytes" else f"{n:.3g} {unit}"
        n /= 1024
    return f"{n:.3g} EiB"  # pragma: no cover


def available_host_bytes() -> int:
    """Memory the system can still give [bytes] (``MemAvailable``; 1/2 of the pages elsewhere)."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):  # pragma: no cover - no sysconf
        return 1 << 62


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
