"""Files warpsim creates beside an output, written without following links, and the disk errors
of writing in words.

Anyone who can create a name in a shared output folder could plant ``NAME.lock`` (or a chunk's
temporary name, a progress file, a table) as a symbolic link to another file; a writer that
follows it overwrites that file. Every such file is therefore opened here with ``O_NOFOLLOW``
(and ``O_NONBLOCK``, so a FIFO planted there cannot hang the run), and a name that exists and is
not a regular file is refused with :class:`UnsafePathError` naming it and how to clear it.
Temporary names are cleared first (removing a link removes the link, never its target) and then
created exclusively; ``os.replace`` onto a final name replaces the name itself, so a link planted
at the final name is replaced, not followed.

:func:`disk_full` recognises a full, read-only or over-quota disk (``ENOSPC``/``EROFS``/``EDQUOT``,
also inside a ``pxr`` ``Tf.ErrorException``'s text) so that writers can remove their temporaries
and the command line can say it in one line.
"""

from __future__ import annotations

import contextlib
import errno
import os
import stat

__all__ = ["DISK_ERRNOS", "UnsafePathError", "check_regular", "check_replaceable", "clear_temporary", "disk_full", "disk_reason", "open_fd",
           "open_for_write", "open_temporary", "temporary_name", "write_replacing"]

DISK_ERRNOS = tuple(e for e in (errno.ENOSPC, errno.EROFS, getattr(errno, "EDQUOT", None), errno.EFBIG)
                    if e is not None)
"""errno values meaning the disk cannot take what is being written."""

_DISK_TEXTS = {"no space left on device": errno.ENOSPC, "read-only file system": errno.EROFS,
               "disk quota exceeded": getattr(errno, "EDQUOT", errno.ENOSPC), "file too large": errno.EFBIG}


class UnsafePathError(ValueError):
    """A file warpsim would create exists and is not a regular file (a symbolic link, a folder, a
    FIFO, a device): warpsim does not write through it (exit status 2 on the command line)."""


def _kind(mode) -> str:
    if stat.S_ISLNK(mode):
        return "a symbolic link"
    if stat.S_ISDIR(mode):
        return "a folder"
    if stat.S_ISFIFO(mode):
        return "a FIFO (named pipe)"
    if stat.S_ISSOCK(mode):
        return "a socket"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "a device"
    return "not a regular file"


def _refusal(path, what, mode) -> UnsafePathError:
    target = ""
    if stat.S_ISLNK(mode):
        try:
            target = f" to {os.readlink(path)!r}"
        except OSError:
            pass
    rm = "rm -r" if stat.S_ISDIR(mode) else "rm"
    return UnsafePathError(f"{what} {os.fspath(path)!r} is {_kind(mode)}{target}, not a regular file; warpsim does "
                           f"not write through it: remove it ({rm} '{os.fspath(path)}') and run again")


def check_regular(path, what: str = "file") -> bool:
    """Whether ``path`` exists; :class:`UnsafePathError` (naming ``what`` and the path) when it
    exists and is not a regular file. Links are not followed."""
    try:
        mode = os.lstat(path).st_mode
    except FileNotFoundError:
        return False
    except NotADirectoryError:
        return False
    if not stat.S_ISREG(mode):
        raise _refusal(path, what, mode)
    return True


def check_replaceable(path, flag: str = "--out") -> bool:
    """Whether ``path`` exists; :class:`UnsafePathError` naming ``flag`` when it is a folder, a
    FIFO, a socket or a device (an output is written under a temporary name and renamed onto
    ``path``: a regular file or a symbolic link there is replaced, never written through)."""
    try:
        mode = os.lstat(path).st_mode
    except (FileNotFoundError, NotADirectoryError):
        return False
    if stat.S_ISREG(mode) or stat.S_ISLNK(mode):
        return True
    fix = f"name a file in it, e.g. {os.path.join(os.fspath(path), 'out' + os.path.splitext(os.fspath(path))[1])!r}" if stat.S_ISDIR(mode) else \
        f"remove it (rm '{os.fspath(path)}') or choose another {flag}"
    raise UnsafePathError(f"{flag} {os.fspath(path)!r} is {_kind(mode)}, not a file warpsim can replace; {fix}")


def clear_temporary(path, what: str = "temporary file") -> None:
    """Remove whatever is at the temporary name ``path`` (a file or a planted link: the link, not
    its target); a folder there is refused (:class:`UnsafePathError`)."""
    try:
        mode = os.lstat(path).st_mode
    except (FileNotFoundError, NotADirectoryError):
        return
    if stat.S_ISDIR(mode):
        raise _refusal(path, what, mode)
    try:
        os.remove(path)
    except FileNotFoundError:
        pass


def open_fd(path, *, what: str = "file", append: bool = False, exclusive: bool = False,
            read: bool = False, mode: int = 0o644) -> int:
    """A file descriptor of ``path`` opened for writing without following a link (see the module
    docstring): created if missing, truncated unless ``append`` (``exclusive``: it must not
    exist; ``read``: read and write, not truncated). :class:`UnsafePathError` when ``path`` is not
    a regular file."""
    check_regular(path, what)
    flags = (os.O_RDWR if read else os.O_WRONLY) | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0) \
        | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0)
    if exclusive:
        flags |= os.O_EXCL
    if append:
        flags |= os.O_APPEND
    elif not read:
        flags |= os.O_TRUNC
    try:
        fd = os.open(path, flags, mode)
    except OSError as exc:
        if exc.errno in (errno.ELOOP, errno.ENXIO, errno.EISDIR, getattr(errno, "EMLINK", -1)):
            try:
                st_mode = os.lstat(path).st_mode
            except OSError:
                raise exc from None
            if not stat.S_ISREG(st_mode):
                raise _refusal(path, what, st_mode) from None
        raise
    try:
        st_mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(st_mode):
            raise _refusal(path, what, st_mode)
        if hasattr(os, "set_blocking"):
            os.set_blocking(fd, True)
    except BaseException:
        os.close(fd)
        raise
    return fd


def open_for_write(path, mode: str = "w", *, what: str = "file", exclusive: bool = False,
                   encoding: str | None = None, newline: str | None = None):
    """``open(path, mode)`` for writing (``"w"``, ``"wb"``, ``"a"``, ``"ab"``) that never follows a
    link planted at ``path`` nor writes into a FIFO or device there (:class:`UnsafePathError`
    naming ``what`` and the path and how to clear it)."""
    if mode not in ("w", "wb", "a", "ab"):
        raise ValueError(f"open_for_write mode must be 'w', 'wb', 'a' or 'ab', got {mode!r}")
    fd = open_fd(path, what=what, append=mode.startswith("a"), exclusive=exclusive)
    if "b" in mode:
        return os.fdopen(fd, mode)
    return os.fdopen(fd, mode, encoding=encoding or "utf-8", newline=newline)


def disk_full(exc) -> int | None:
    """The errno (``ENOSPC``, ``EROFS``, ``EDQUOT``, ``EFBIG``) when ``exc`` says the disk cannot
    take what is being written (an ``OSError``, or a library error such as ``pxr``'s
    ``Tf.ErrorException`` whose text says so); None otherwise."""
    if isinstance(exc, OSError) and exc.errno in DISK_ERRNOS:
        return exc.errno
    text = str(exc).lower()
    for words, code in _DISK_TEXTS.items():
        if words in text:
            return code
    return None


def disk_reason(code) -> str:
    """The words of a disk errno, with what to do."""
    return {errno.ENOSPC: "no space left on device; free some space or choose another folder",
            errno.EROFS: "the file system is read-only; choose a writable folder",
            errno.EFBIG: "the file is too large for this file system; choose another folder or smaller --chunk",
            }.get(code, "the disk quota is exceeded; free some space or choose another folder")


@contextlib.contextmanager
def open_temporary(path, mode: str = "w", *, what: str = "temporary file", encoding: str | None = None,
                   newline: str | None = None):
    """``with open_temporary(tmp) as f:`` a fresh temporary file at ``path`` (whatever a previous
    run or another user left there is removed first, a planted link as a link), created
    exclusively without following links; removed again when the block fails (a full disk leaves
    no temporary behind)."""
    clear_temporary(path, what)
    f = open_for_write(path, mode, what=what, exclusive=True, encoding=encoding, newline=newline)
    try:
        with f:
            yield f
    except BaseException:
        try:
            os.remove(path)
        except OSError:
            pass
        raise


def temporary_name(path) -> str:
    """The temporary name beside ``path`` that :func:`write_replacing` writes first
    (``stem.tmp-PID.suffix``: the suffix kept for libraries that read it)."""
    stem, ext = os.path.splitext(os.fspath(path))
    return f"{stem}.tmp-{os.getpid()}{ext}"


def write_replacing(path, write, *, what: str = "file", mode: str = "wb"):
    """``write(f)`` into a fresh temporary name beside ``path`` (:func:`open_temporary`: a link
    planted there is removed, never followed), then rename it onto ``path`` (a link or file
    planted at ``path`` is replaced, not written through). A failure leaves no temporary file
    behind and ``path`` as it was. Returns ``path``."""
    tmp = temporary_name(path)
    with open_temporary(tmp, mode, what=f"temporary file of {what}") as f:
        write(f)
    try:
        os.replace(tmp, path)
    except BaseException:
        try:
            os.remove(tmp)
        except OSError:
            pass
        raise
    return path
