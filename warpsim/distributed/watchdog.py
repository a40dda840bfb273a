"""Ends the local Ray cluster a sweep driver started when that driver dies, even by SIGKILL.

``ray.init()`` without an address starts a head node (GCS server, raylet, dashboard and runtime
environment agents, workers) as children of the driver; ``ray.shutdown()`` ends them, but a
driver killed outright never calls it and Ray leaves some of them running (measured with Ray
2.60: the dashboard and runtime-env agents stayed up, re-parented to init). :func:`start_watchdog`
spawns a small process in its own session that waits for the driver to exit and then kills
every process holding a file open under that cluster's session folder (its log files), which
identifies the cluster's processes and nothing else. After a normal ``ray.shutdown()`` there is
nothing left to kill and the watchdog exits with the driver.

    python -m warpsim.distributed.watchdog DRIVER_PID SESSION_DIR
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

__all__ = ["cluster_processes", "start_watchdog"]


def _alive(pid) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # pragma: no cover - someone else's process with that pid
        return True
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"  # a zombie has exited
    except OSError:
        return True


def cluster_processes(session_dir) -> list:
    """Pids of the processes holding a file open under ``session_dir`` (Linux ``/proc``)."""
    session_dir = os.path.realpath(session_dir)
    me = os.getpid()
    out = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit() or int(entry) == me:
            continue
        try:
            fds = os.listdir(f"/proc/{entry}/fd")
        except OSError:
            continue
        for fd in fds:
            try:
                target = os.readlink(f"/proc/{entry}/fd/{fd}")
            except OSError:
                continue
            if target.startswith(session_dir + os.sep):
                out.append(int(entry))
                break
    return out


def start_watchdog(session_dir, driver_pid=None):
    """Spawn the watchdog for the cluster whose session folder is ``session_dir`` (None where
    ``/proc`` is missing: nothing to watch with)."""
    if not os.path.isdir("/proc") or not session_dir:
        return None
    return subprocess.Popen([sys.executable, "-m", "warpsim.distributed.watchdog", str(driver_pid or os.getpid()),
                             os.fspath(session_dir)], stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=True, close_fds=True)


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    driver, session_dir = int(argv[0]), argv[1]
    while _alive(driver):
        time.sleep(0.5)
    for _ in range(3):  # processes starting while the first ones die
        pids = cluster_processes(session_dir)
        for pid in pids:
            try:
                os.kill(pid, signal.SIGKILL)
            except OSError:
                pass
        if not pids:
            break
        time.sleep(1.0)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
