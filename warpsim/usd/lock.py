"""One writer per output: an advisory lock file beside every file a warpsim command writes.

``warpsim run/sweep/pick/rerun/export/render/plot`` and the viewer's recorder (through
:class:`warpsim.usd.writer.UsdCacheWriter`) take the lock of their output before anything is
written. The lock of a USD cache ``DIR/s.usda`` is ``DIR/s.lock`` (one per stem: ``s.usda`` and
``s.usdc`` share their chunk files ``s.chunkNNNNNN.usdc``, so they share the lock); of any other
output ``DIR/x.gif`` it is ``DIR/x.gif.lock``. The file holds JSON naming the holder::

    {"pid": 4711, "host": "node3", "start": "2026-11-27T07:50:01Z", "command": "warpsim run springs ..."}

Exclusion is ``fcntl.flock`` on the open lock file: the kernel drops it when its process ends in
any way (SIGKILL included), so a lock file left by a killed process is stale and the next writer
takes it over; a normal exit also removes the file (context manager, command scope, ``atexit``).
Where ``flock`` is unsupported (some network file systems) the recorded pid decides: a lock whose
pid is alive on this host is held, any other is stale. Within one process the lock is re-entrant
(the command line and the cache writer it drives take the same lock).

A second writer gets :class:`OutputLockedError` (a ValueError; the command line prints one line
and exits 2) naming the holder and the lock file.
"""
from __future__ import annotations

import atexit
import contextlib
import datetime
import errno
import json
import os
import socket
import sys
import threading

from ..core.safe_files import UnsafePathError, check_regular, open_fd

try:
    import fcntl
except ImportError:  # pragma: no cover - Windows: the pid decides
    fcntl = None  # type: ignore[assignment]

__all__ = ["OutputLock", "OutputLockedError", "command_scope", "hold", "lock_info", "lock_path", "pid_alive"]

USD_EXTENSIONS = (".usd", ".usda", ".usdc")

_held: dict = {}  # lock path -> {"fd": int or None, "count": int, "pid": int}
_mutex = threading.RLock()
_scopes: list = []  # stack of lists: locks taken while a command scope is open


class OutputLockedError(ValueError):
    """The output is being written by another process (exit status 2 on the command line)."""


def lock_path(out) -> str:
    """The lock file of output ``out``: ``<stem>.lock`` for a USD cache, ``<out>.lock`` else."""
    out = os.path.abspath(os.fspath(out))
    stem, ext = os.path.splitext(out)
    return stem + ".lock" if ext.lower() in USD_EXTENSIONS else out + ".lock"


def lock_info(path) -> dict | None:
    """The holder recorded in lock file ``path`` (None when it is missing, unreadable or not a
    regular file: a planted link or FIFO is never followed)."""
    try:
        if not check_regular(path, "lock file"):
            return None
    except UnsafePathError:
        return None
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            data = json.loads(f.read() or "null")
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def pid_alive(pid) -> bool:
    """Whether process ``pid`` exists on this host."""
    try:
        os.kill(int(pid), 0)
    except PermissionError:  # it exists, owned by another user
        return True
    except (ProcessLookupError, OverflowError, ValueError, TypeError):  # gone, or not a pid
        return False
    return True


def _holder_text(info) -> str:
    if not info:
        return "another process (its lock file names no holder yet)"
    what = f"pid {info.get('pid', '?')} on {info.get('host', '?')}"
    cmd = str(info.get("command") or "").strip()
    if cmd:
        what += f", '{cmd[:120]}'"
    if info.get("start"):
        what += f", since {info['start']}"
    return what


def _refuse(out, path, info, flag):
    shown = os.path.relpath(os.fspath(out)) if flag else os.fspath(out)
    raise OutputLockedError(f"{flag + ' ' if flag else ''}{shown} is being written by another warpsim process "
                            f"({_holder_text(info)}); wait for it to finish or choose another output (lock file "
                            f"{os.path.basename(path)}; delete it only if that process is gone)")


def _record(command) -> bytes:
    start = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
    cmd = command if command is not None else " ".join(["warpsim" if i == 0 else a for i, a in enumerate(sys.argv)])
    return json.dumps({"pid": os.getpid(), "host": socket.gethostname(), "start": start,
                       "command": cmd}).encode()


def _acquire_flock(out, path, command, flag):
    """The fd of ``path`` locked by this process (or None where flock is unsupported: pid rule)."""
    for _ in range(20):
        fd = open_fd(path, what="lock file", read=True)  # never through a planted link, FIFO or folder
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            _refuse(out, path, lock_info(path), flag)
        except OSError as exc:
            os.close(fd)
            if exc.errno in (errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS, errno.EINVAL):
                return _acquire_pid(out, path, command, flag)
            raise
        try:  # the file we locked must still be the one at ``path`` (a holder may have removed it)
            same = os.path.samestat(os.fstat(fd), os.lstat(path))
        except FileNotFoundError:
            same = False
        if not same:
            os.close(fd)
            continue
        data = _record(command)
        os.ftruncate(fd, 0)
        os.pwrite(fd, data, 0)
        return fd
    raise OutputLockedError(f"could not take the lock {path} (it kept being replaced); try again")


def _acquire_pid(out, path, command, flag):
    """Lock without flock: create the file exclusively; take over one whose pid is dead here."""
    for _ in range(5):
        try:
            fd = open_fd(path, what="lock file", exclusive=True)
        except FileExistsError:
            check_regular(path, "lock file")  # a planted link or folder is named, never followed or removed
            info = lock_info(path)
            if info and info.get("host") == socket.gethostname() and pid_alive(info.get("pid")) \
                    and int(info.get("pid")) != os.getpid():
                _refuse(out, path, info, flag)
            if info and info.get("host") not in (None, socket.gethostname()):
                _refuse(out, path, info, flag)  # another host's process: its liveness cannot be checked here
            with contextlib.suppress(FileNotFoundError):
                os.remove(path)  # stale: its process is gone
            continue
        os.write(fd, _record(command))
        os.close(fd)
        return None
    raise OutputLockedError(f"could not take the lock {path}; try again")


def hold(out, flag="--out", command=None) -> str:
    """Take the lock of output ``out`` for this process (re-entrant) and return the lock path;
    released when the enclosing :func:`command_scope` ends (or at exit). ``flag`` names the
    option in the refusal. OutputLockedError when another process holds it."""
    path = lock_path(out)
    with _mutex:
        entry = _held.get(path)
        if entry is not None and entry["pid"] == os.getpid():
            entry["count"] += 1
        else:
            try:
                os.makedirs(os.path.dirname(path), exist_ok=True)
                fd = _acquire_flock(out, path, command, flag) if fcntl is not None else \
                    _acquire_pid(out, path, command, flag)
            except OSError as exc:  # the folder cannot hold the lock file, so not the output either
                what = f"{flag} {os.fspath(out)!r}" if flag else repr(os.fspath(out))
                raise ValueError(f"{what}: cannot write in folder {os.path.dirname(path)!r} "
                                 f"({(exc.strerror or str(exc)).lower()}); choose a writable folder") from None
            _held[path] = {"fd": fd, "count": 1, "pid": os.getpid()}
        if _scopes:
            _scopes[-1].append(path)
    return path


def release(path) -> None:
    """Undo one :func:`hold` of lock file ``path``; the last one removes the file and unlocks."""
    with _mutex:
        entry = _held.get(path)
        if entry is None or entry["pid"] != os.getpid():
            return
        entry["count"] -= 1
        if entry["count"] > 0:
            return
        del _held[path]
        fd = entry["fd"]
        try:
            if fd is None or os.path.samestat(os.fstat(fd), os.lstat(path)):
                os.remove(path)  # before unlocking: a waiter then finds the file gone and retries
        except OSError:
            pass
        if fd is not None:
            os.close(fd)


@contextlib.contextmanager
def command_scope():
    """Locks taken (by :func:`hold`) inside the block are released when it ends, however."""
    with _mutex:
        _scopes.append([])
    try:
        yield
    finally:
        with _mutex:
            taken = _scopes.pop()
        for path in reversed(taken):
            release(path)


class OutputLock:
    """``with OutputLock(out):`` holds the lock of ``out`` for the block (see :func:`hold`)."""

    def __init__(self, out, flag="", command=None):
        self.out = out
        self.flag = flag
        self.command = command
        self.path = None

    def acquire(self):
        if self.path is None:
            with _mutex:  # not tied to an enclosing command scope: released by release()
                scopes = _scopes[:]
                _scopes.clear()
                try:
                    self.path = hold(self.out, self.flag, self.command)
                finally:
                    _scopes.extend(scopes)
        return self

    def release(self):
        if self.path is not None:
            release(self.path)
            self.path = None

    def __enter__(self):
        return self.acquire()

    def __exit__(self, *exc):
        self.release()
        return False


@atexit.register
def _release_all():  # a normal exit removes the lock files (a kill leaves them stale)
    for path in list(_held):
        entry = _held.get(path)
        if entry is not None and entry["pid"] == os.getpid():
            entry["count"] = 1
            release(path)
