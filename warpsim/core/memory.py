"""Host memory the system can still give, for the checks that refuse a run before it allocates
(``warpsim.sweeps.preflight``, the donuts scene)."""

from __future__ import annotations

import os

UNKNOWN = 1 << 62
"""What ``available_host_bytes`` returns by default where the figure cannot be read."""


def available_host_bytes(unknown: int = UNKNOWN) -> int:
    """Memory this process can still get [bytes]: the least of the system's (``MemAvailable``
    from /proc/meminfo, else the available pages, else ``unknown``), what an address-space limit
    leaves (``ulimit -v``: RLIMIT_AS less the process's current size) and what a cgroup's memory
    limit leaves (v2 ``memory.max`` less ``memory.current``; v1 ``memory.limit_in_bytes`` less
    its usage)."""
    return min(_system_bytes(unknown), _rlimit_bytes(), _cgroup_bytes())


def _rlimit_bytes() -> int:
    try:
        import resource

        soft = resource.getrlimit(resource.RLIMIT_AS)[0]
    except (ImportError, OSError, ValueError, AttributeError):  # pragma: no cover - no resource module
        return UNKNOWN
    if soft == resource.RLIM_INFINITY or soft < 0:
        return UNKNOWN
    used = 0
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmSize:"):
                    used = int(line.split()[1]) * 1024
                    break
    except (OSError, ValueError, IndexError):
        pass
    return max(int(soft) - used, 0)


def _read_int(path):
    try:
        with open(path) as f:
            text = f.read().strip()
    except OSError:
        return None
    return int(text) if text.isdigit() else None


def _cgroup_bytes() -> int:
    """What this process's cgroup memory limit leaves (UNKNOWN without one)."""
    try:
        with open("/proc/self/cgroup") as f:
            lines = f.read().splitlines()
    except OSError:
        return UNKNOWN
    best = UNKNOWN
    for line in lines:
        parts = line.split(":", 2)
        if len(parts) != 3:
            continue
        _, controllers, path = parts
        if controllers == "":  # v2
            limit = _read_int(f"/sys/fs/cgroup{path}/memory.max") or _read_int("/sys/fs/cgroup/memory.max")
            used = _read_int(f"/sys/fs/cgroup{path}/memory.current") or _read_int("/sys/fs/cgroup/memory.current")
        elif "memory" in controllers.split(","):
            limit = _read_int("/sys/fs/cgroup/memory/memory.limit_in_bytes")
            used = _read_int("/sys/fs/cgroup/memory/memory.usage_in_bytes")
        else:
            continue
        if limit is not None and limit < UNKNOWN:
            best = min(best, max(limit - (used or 0), 0))
    return best


def _system_bytes(unknown: int) -> int:
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):  # pragma: no cover - no sysconf
        return int(unknown)


def _format_bytes(n: float) -> str:
    for unit in ("bytes", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if n < 1024 or unit == "PiB":
            return f"{n:.0f} {unit}" if unit == "bytes" else f"{n:.3g} {unit}"
        n /= 1024
    return f"{n:.3g} EiB"  # pragma: no cover


def check_build_memory(param: str, value, count: int, what: str, bytes_each: float, fit_of,
                       available: int | None = None) -> int:
    """Refuse (ValueError naming ``param``=``value``, the estimate and a fix) a scene whose
    ``count`` ``what`` (particles, ...) need more than the memory this process can get to build
    at ``bytes_each`` [bytes] each (measured per scene); ``fit_of(n)``: the ``param`` value that
    makes about ``n`` of them. Returns the estimated bytes."""
    available = available_host_bytes() if available is None else int(available)
    need = int(count * bytes_each)
    if need > available:
        fit = fit_of(max(1, int(0.8 * available / bytes_each)))
        raise ValueError(f"{param}={value}: {int(count):,} {what} need about {_format_bytes(need)} of memory to build "
                         f"(about {bytes_each:,.0f} bytes each), this machine has {_format_bytes(available)} free; use "
                         f"at most about {param}={fit}")
    return need
