"""Starting the local Ray cluster of ``--ray``, and saying in one line why it did not start.

``ray.init()`` without an address starts a head node (GCS server, raylet) as children of the
driver and waits for the raylet to register. When the raylet dies while starting, Ray notices
only at the end of its own 30 s wait (inside a native call that Python cannot interrupt) and
raises a bare ``Exception("The current node timed out during startup ...")``. Measured with Ray
2.60 under ``ulimit -v 4000000``: the raylet could not map its object store ("mmap failed ...
Cannot allocate memory", its fatal line 6 s after the start) and Ray raised after 36 s (41 s
through ``warpsim sweep``), a traceback.

:func:`start_local_head` refuses at once the case it can foresee (an address-space limit below
the object store Ray's default rule maps, :func:`check_address_space`) and turns any other
failure of ``ray.init`` into :class:`RayHeadError`: one line naming the cause (the last error
lines of the head's logs in this driver's session folder, ``<ray temp dir>/session_*_<pid>``) and
the fix; the processes the failed start left are ended.
"""
from __future__ import annotations

import glob
import os
import re
import resource
import sys
import time

__all__ = ["RayHeadError", "address_space_needed", "check_address_space", "head_failure_line", "object_store_bytes", "ray_temp_dir",
           "start_local_head"]

HEAD_PROCESSES = ("raylet", "gcs_server")

_LOG_LINE = re.compile(r"^\[[^\]]*? ([CEF]) \d+ \d+\] \((\w+)\) [\w./-]+:\d+:\s*(.*)$")
_BOILERPLATE = (re.compile(r"An unexpected system state has occurred\..*?fix it\.\s*"),
                re.compile(r"Check failed: \S+\s*"))


class RayHeadError(ValueError):
    """The local Ray cluster of ``--ray`` did not start (exit status 2 on the command line: the
    machine, not the sweep, is at fault, and nothing was written)."""

    exit_status = 2


def ray_temp_dir() -> str:
    """Where Ray makes its session folders (Ray's own rule: ``$RAY_TMPDIR``, else ``$TMPDIR`` on
    Linux, else ``/tmp``; then ``ray``)."""
    base = os.environ.get("RAY_TMPDIR")
    if not base:
        base = os.environ.get("TMPDIR") if sys.platform.startswith("linux") else None
    return os.path.join(base or "/tmp", "ray")


def _sessions(pid, since):
    """This driver's session folders made since ``since`` (Ray names them ``session_<date>_<pid>``)."""
    found = []
    for path in glob.glob(os.path.join(ray_temp_dir(), f"session_*_{pid}")):
        try:
            if os.path.getmtime(path) >= since - 2.0:
                found.append(path)
        except OSError:
            continue
    return sorted(found)


def _clean(text):
    for pattern in _BOILERPLATE:
        text = pattern.sub("", text)
    return text.strip().rstrip(".")


def _log_errors(session):
    """``(fatal, errors)``: the cleaned fatal (``C``/``F``) and error (``E``) lines of the head
    processes' logs in ``session``, as ``process: text``."""
    fatal, errors = [], []
    for name in HEAD_PROCESSES:
        path = os.path.join(session, "logs", f"{name}.err")
        try:
            with open(path, "rb") as f:
                f.seek(0, os.SEEK_END)
                f.seek(max(0, f.tell() - 65536))
                lines = f.read().decode("utf-8", "replace").splitlines()
        except OSError:
            continue
        for line in lines:
            m = _LOG_LINE.match(line)
            if m:
                level, process, text = m.groups()
                (fatal if level in "CF" else errors).append(f"{process}: {_clean(text)}")
    return fatal, errors


def head_failure_line(cause, session=None) -> str:
    """The one line of :class:`RayHeadError`: ``cause`` and the fix that fits it."""
    limit = resource.getrlimit(resource.RLIMIT_AS)[0]
    where = f" (logs: {os.path.join(session, 'logs')})" if session else ""
    if limit != resource.RLIM_INFINITY and re.search(r"mmap|allocat|memory|/dev/shm|timed out", cause, re.I):
        fix = (f"this process's address-space limit (ulimit -v {limit // 1024} KiB), which Ray's processes inherit, may be "
               "too small for them: raise it (ulimit -v unlimited) or run the sweep without --ray")
    elif "/dev/shm" in cause or "space" in cause.lower():
        fix = "free space in /dev/shm (df -h /dev/shm) or run the sweep without --ray"
    else:
        fix = ("run the sweep without --ray, or start a cluster with 'ray start --head' (it says why it stops) "
               "and pass the address it prints to --ray")
    cause = " ".join(str(cause).split())
    if len(cause) > 300:
        cause = cause[:297] + "..."
    return f"--ray: the local Ray cluster did not start ({cause}){where}; {fix}"


def _end_session(ray, session):
    """End what a failed start left: Ray's driver state and the session's processes."""
    try:
        ray.shutdown()
    except Exception:  # noqa: BLE001  (a half-started driver may not shut down cleanly)
        pass
    if session:
        import signal

        from .watchdog import cluster_processes

        for child in cluster_processes(session):
            try:
                os.kill(child, signal.SIGKILL)
            except OSError:
                pass


def object_store_bytes() -> int:
    """The object store Ray's raylet maps when none is given [bytes]: Ray's default rule, 30 % of
    the available memory (``MemAvailable``), at most 200 GB (0 where /proc/meminfo is missing)."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return min(int(0.3 * int(line.split()[1]) * 1024), 200 * 10 ** 9)
    except (OSError, ValueError, IndexError):
        pass
    return 0


RAYLET_EXTRA_BYTES = 1 << 30
"""Address space the raylet, and the driver, need besides the object store and what the driver
already holds [bytes] (threads, libraries, Ray's core worker)."""


def _process_bytes() -> int:
    """This process's address space now [bytes] (``VmSize``; 0 where /proc is missing)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmSize:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return 0


def address_space_needed(store=None, held=None) -> int:
    """Address space a local Ray cluster's processes need under ``ulimit -v`` [bytes]: every one
    maps the whole object store, the raylet twice (its allocator and its own client: measured with
    Ray 2.60 under ``ulimit -v 9500000``, a 6.6 GiB store, the raylet died in
    ``PlasmaClient::GetStoreFdAndMmap``), plus ``RAYLET_EXTRA_BYTES`` each and what this process
    holds already."""
    store = object_store_bytes() if store is None else int(store)
    held = _process_bytes() if held is None else int(held)
    return 2 * store + 2 * RAYLET_EXTRA_BYTES + held


def check_address_space(store=None) -> None:
    """:class:`RayHeadError` at once when this process's address-space limit (``ulimit -v``, which
    the head's processes inherit) is below :func:`address_space_needed`: Ray would find out only
    after its 30 s wait, or a process of it aborts in C++ with a stack trace and no Python
    exception to catch."""
    limit = resource.getrlimit(resource.RLIMIT_AS)[0]
    if limit == resource.RLIM_INFINITY or limit < 0:
        return
    store = object_store_bytes() if store is None else int(store)
    need = address_space_needed(store)
    if limit < need:
        raise RayHeadError(f"--ray: a local Ray cluster cannot start under this address-space limit: its processes "
                           f"map an object store of about {store / 2 ** 30:.3g} GiB each (Ray's default, 30 % of the "
                           f"available memory; the raylet twice), about {need / 2 ** 30:.3g} GiB in all, and ulimit -v "
                           f"allows {limit / 2 ** 30:.3g} GiB; raise it (ulimit -v unlimited) or run the sweep without "
                           "--ray")


def start_local_head(ray, **init_options) -> None:
    """``ray.init(**init_options)`` (a local cluster); :class:`RayHeadError` in one line naming
    the cause and the fix when its head does not start (at once for an address-space limit it
    cannot start under; otherwise when Ray gives up), after ending what the failed start left."""
    check_address_space(init_options.get("object_store_memory"))
    since = time.time()
    try:
        ray.init(**init_options)
    except Exception as exc:  # noqa: BLE001  (Ray raises bare Exception/RuntimeError when the head fails)
        sessions = _sessions(os.getpid(), since)
        session = sessions[-1] if sessions else None
        fatal, errors = _log_errors(session) if session else ([], [])
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
        cause = "; ".join(errors[-1:] + fatal[-1:]) if (errors or fatal) else f"{type(exc).__name__}: {first}"
        _end_session(ray, session)
        raise RayHeadError(head_failure_line(cause, session)) from None
