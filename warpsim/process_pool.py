"""Host work off the stepping process: a small pool of worker processes that run named functions.

A sweep's USD chunks and its thumbnails' PNG encoding are pure host work (Sdf authoring, zlib)
that would otherwise hold up the stepping loop and serialise on one core. :class:`ProcessPool`
starts ``workers`` fresh Python processes (``python -m warpsim.process_pool``: no ``fork`` of a
process holding a CUDA context, and no re-run of the caller's ``__main__`` as ``multiprocessing``'s
spawn does for a script without a ``__name__`` guard) and hands each a job at a time::

    pool = ProcessPool(4)
    future = pool.submit("warpsim.usd.chunk_author:author_chunk", job)   # a concurrent.futures.Future
    future.result()                                                      # the function's return value
    pool.close()

A job is ``(module:function, args)`` pickled down the worker's stdin; the answer (the value, or
the exception's type name, errno and text) comes back on its stdout. Large arrays travel in
shared memory (:class:`SharedBlock`), not through the pipe. A worker dies with its parent
(``PR_SET_PDEATHSIG`` on Linux; elsewhere it reads the end of its pipe and exits). This module imports nothing from warpsim: a worker starts in
about the time Python and NumPy take, and the functions it runs import what they need.
"""
from __future__ import annotations

import concurrent.futures
import importlib
import os
import pickle
import queue
import struct
import subprocess
import sys
import threading

__all__ = ["BlockPool", "ProcessPool", "RemoteError", "SharedBlock", "default_workers", "forced_workers"]

_HEADER = struct.Struct("<Q")


def default_workers(jobs=None, reserve=1, most=8) -> int:
    """Worker processes worth starting: the cores this process may use less ``reserve`` (the
    stepping process's own), at most ``most`` and at most ``jobs`` when given; 0 on a single core."""
    try:
        cores = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # pragma: no cover - not Linux
        cores = os.cpu_count() or 1
    n = min(int(most), cores - int(reserve))
    if jobs is not None:
        n = min(n, int(jobs))
    return max(0, n)


def forced_workers():
    """The worker count the environment sets (``WARPSIM_WRITE_WORKERS=N``; 0: none), or None when
    it is unset; ValueError naming the value otherwise."""
    forced = os.environ.get("WARPSIM_WRITE_WORKERS", "").strip()
    if not forced:
        return None
    if not forced.isdigit() or int(forced) > 64:
        raise ValueError(f"WARPSIM_WRITE_WORKERS={forced!r}: give a whole number of worker processes in 0..64 "
                         "(0: the stepping process writes), or unset it to let warpsim choose")
    return int(forced)


class RemoteError(RuntimeError):
    """A job raised in a worker: ``kind`` (the exception's type name), ``errno`` (an OSError's, or
    None) and the text; ``str()`` gives the text."""

    def __init__(self, kind, errno, text):
        super().__init__(text)
        self.kind, self.errno = kind, errno


def _send(stream, obj):
    data = pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
    stream.write(_HEADER.pack(len(data)))
    stream.write(data)
    stream.flush()


def _receive(stream):
    head = stream.read(_HEADER.size)
    if len(head) < _HEADER.size:
        return None
    (size,) = _HEADER.unpack(head)
    data = stream.read(size)
    if len(data) < size:
        return None
    return pickle.loads(data)


class ProcessPool:
    """``workers`` worker processes (started now, in the background) running jobs one at a time
    each; :meth:`submit` returns a ``concurrent.futures.Future``. Use as a context manager or
    call :meth:`close`."""

    def __init__(self, workers):
        self.workers = int(workers)
        if self.workers < 1:
            raise ValueError(f"ProcessPool workers {workers!r}: give at least 1 (default_workers() picks)")
        env = dict(os.environ)
        here = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))  # the warpsim package's parent
        env["PYTHONPATH"] = here + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
        self._idle: queue.Queue = queue.Queue()
        self._procs = []
        for _ in range(self.workers):
            proc = subprocess.Popen([sys.executable, "-m", "warpsim.process_pool", str(os.getpid())], stdin=subprocess.PIPE,
                                    stdout=subprocess.PIPE, env=env, close_fds=True)
            self._procs.append(proc)
            self._idle.put(proc)
        self._threads = concurrent.futures.ThreadPoolExecutor(self.workers, thread_name_prefix="warpsim-pool")
        self._closed = False

    def submit(self, target, *args) -> concurrent.futures.Future:
        """Run ``target`` (``"package.module:function"``) with ``args`` in a free worker."""
        if self._closed:
            raise ValueError("the process pool is closed")
        return self._threads.submit(self._run, target, args)

    def _run(self, target, args):
        proc = self._idle.get()
        try:
            _send(proc.stdin, (target, args))
            answer = _receive(proc.stdout)
        except (BrokenPipeError, OSError) as exc:
            raise RemoteError(type(exc).__name__, None, f"worker process {proc.pid} died: {exc}") from None
        finally:
            self._idle.put(proc)
        if answer is None:
            raise RemoteError("EOFError", None, f"worker process {proc.pid} exited (code {proc.poll()}) mid-job")
        ok, value = answer
        if ok:
            return value
        raise RemoteError(*value)

    def close(self, wait=True):
        """Finish the jobs given (``wait``) or drop those not started, then end the workers: each
        is told to exit (its input closed) and reaped by a background thread, so the caller does not
        wait for interpreters (and a CUDA context) to tear down; :meth:`join` waits for that."""
        if self._closed:
            return
        self._closed = True
        self._threads.shutdown(wait=wait, cancel_futures=not wait)
        for proc in self._procs:
            try:
                proc.stdin.close()
            except OSError:
                pass
        self._reaper = threading.Thread(target=self._reap, args=(10 if wait else 1,), daemon=True,
                                        name="warpsim-pool-reaper")
        self._reaper.start()

    def _reap(self, timeout):
        for proc in self._procs:
            try:
                proc.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
            if proc.stdout is not None:
                proc.stdout.close()

    def join(self, timeout=None) -> bool:
        """Wait until the closed pool's workers have exited; whether they have."""
        reaper = getattr(self, "_reaper", None)
        if reaper is not None:
            reaper.join(timeout)
        return reaper is not None and not reaper.is_alive()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close(wait=exc[0] is None)
        return False


class SharedBlock:
    """Shared memory for arrays a worker reads (created here, attached there by name).

    ``SharedBlock(nbytes)`` creates it; ``array(offset, shape, dtype)`` is a NumPy view of part of
    it; ``ref(offset, shape, dtype)`` the picklable address a worker turns back into a view with
    :func:`attach`; :meth:`release` frees it (the creator's job, once the worker is done)."""

    def __init__(self, nbytes):
        from multiprocessing import shared_memory

        self.shm = shared_memory.SharedMemory(create=True, size=max(int(nbytes), 1))
        self.name = self.shm.name
        self.nbytes = self.shm.size
        try:  # its pages made now, in one call: writing a fresh page faults it in, about 10x slower a byte
            import mmap

            self.shm._mmap.madvise(getattr(mmap, "MADV_POPULATE_WRITE", 23))  # noqa: SLF001  (Linux >= 5.14)
        except (AttributeError, OSError, ValueError):  # older kernels, other systems: pages come on first write
            pass

    def array(self, offset, shape, dtype):
        import numpy as np

        return np.ndarray(shape, dtype=dtype, buffer=self.shm.buf, offset=int(offset))

    def ref(self, offset, shape, dtype):
        import numpy as np

        return (self.name, int(offset), tuple(int(s) for s in shape), np.dtype(dtype).str)

    def release(self):
        if self.shm is not None:
            self.shm.close()
            try:
                self.shm.unlink()
            except FileNotFoundError:  # pragma: no cover - already gone
                pass
            self.shm = None


class BlockPool:
    """Shared blocks handed out again once given back (:meth:`take`, :meth:`give`): a sweep's
    chunks reuse the memory of the chunks already written instead of faulting fresh pages in.
    :meth:`close` frees them all."""

    def __init__(self):
        self._free = []

    def take(self, nbytes) -> SharedBlock:
        """A block of at least ``nbytes`` bytes (the smallest free one that fits, else a new one)."""
        fits = [b for b in self._free if b.nbytes >= nbytes]
        if fits:
            block = min(fits, key=lambda b: b.nbytes)
            self._free.remove(block)
            return block
        return SharedBlock(nbytes)

    def give(self, block):
        self._free.append(block)

    def close(self):
        for block in self._free:
            block.release()
        self._free = []


def attach(ref):
    """(array view, handle) of a :meth:`SharedBlock.ref` in a worker; close the handle when done."""
    import numpy as np
    from multiprocessing import resource_tracker, shared_memory

    name, offset, shape, dtype = ref
    shm = shared_memory.SharedMemory(name=name)
    try:  # the creator unlinks it; this process's tracker must not (nor warn at exit)
        resource_tracker.unregister(shm._name, "shared_memory")  # noqa: SLF001  (Python < 3.13 has no track=)
    except Exception:  # noqa: BLE001  # pragma: no cover
        pass
    return np.ndarray(shape, dtype=np.dtype(dtype), buffer=shm.buf, offset=offset), shm


def _die_with(parent):
    """End this worker when ``parent`` (the pool's process) dies, even by SIGKILL (Linux), so no
    orphan goes on writing a killed run's temporary files."""
    try:
        import ctypes
        import signal

        ctypes.CDLL(None).prctl(1, int(signal.SIGKILL))  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):  # pragma: no cover - not Linux: the end of stdin still stops the loop
        pass
    if os.getppid() != parent:  # the parent died before the request took effect
        os._exit(0)


def _serve():
    """The worker's loop: jobs in on stdin, answers out on stdout, until stdin ends."""
    stdin, stdout = sys.stdin.buffer, sys.stdout.buffer
    sys.stdout = sys.stderr  # a job's prints must not corrupt the answers
    while True:
        job = _receive(stdin)
        if job is None:
            return
        target, args = job
        try:
            module, name = target.split(":")
            value = getattr(importlib.import_module(module), name)(*args)
            answer = (True, value)
        except BaseException as exc:  # noqa: BLE001  (every failure goes back to the caller)
            answer = (False, (type(exc).__name__, getattr(exc, "errno", None), str(exc) or type(exc).__name__))
        _send(stdout, answer)


if __name__ == "__main__":
    if len(sys.argv) > 1:
        _die_with(int(sys.argv[1]))
    _serve()
