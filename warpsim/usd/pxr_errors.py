"""Library error texts in warpsim's words (shared by the readers, the writers and the command
line, one floor below all): what a ``Tf.ErrorException`` says without its internal prefix, an
``OSError`` without its bare ``[Errno N]``, and :class:`DamagedFileError` for files warpsim wrote
that are damaged (exit status 1)."""

import os

__all__ = ["DamagedFileError", "error_line", "os_reason", "pxr_reason"]


def pxr_reason(exc, limit=160) -> str:
    """What a ``pxr`` error says, without its internal prefix ("Error in 'pxrInternal_...' at line
    N in file ... : 'text'" -> "text"); the last message when there are several."""
    import re

    text = str(exc).strip()
    found = re.findall(r"Error in '[^']*' at line \d+ in file [^:]* : '(.*?)'\s*(?=\n\s*Error in|$)", text, re.S)
    reason = (found[-1] if found else text.splitlines()[-1] if text else type(exc).__name__).strip()
    reason = " ".join(reason.split())
    return reason if len(reason) <= limit else reason[: limit - 3] + "..."


class DamagedFileError(ValueError):
    """A record, manifest, table or index that warpsim wrote is damaged or was tampered with:
    the message names the file and the field. The command line exits 1 (damage), not 2 (usage)."""

    exit_status = 1


def os_reason(exc) -> str:
    """An ``OSError`` in words: "FILE: no such file or directory" instead of "[Errno 2] ..."."""
    why = (exc.strerror or "").strip() or str(exc) or type(exc).__name__
    why = why[0].lower() + why[1:] if why[:1].isupper() and why[1:2].islower() else why
    names = [n for n in (exc.filename, getattr(exc, "filename2", None)) if n is not None]
    fix = {2: "check the path", 13: "check its permissions or choose another path", 28: "free some space",
           30: "choose a writable folder", 20: "a part of the path is a file, not a folder",
           21: "give a file, not a folder", 36: "choose a shorter name"}.get(exc.errno or 0)
    where = " -> ".join(repr(os.fspath(n)) for n in names)
    text = f"{where}: {why}" if where else why
    return f"{text}; {fix}" if fix else text


def error_line(exc) -> str:
    """One line for an error reaching the command line: an ``OSError`` in words (no bare
    ``[Errno N]``), a ``pxr`` error without its internal prefix (its type when it says nothing),
    anything else its text on one line."""
    if isinstance(exc, OSError) and exc.errno is not None and str(exc).startswith("["):
        return os_reason(exc)
    text = " ".join(str(exc).split())
    if type(exc).__module__.startswith("pxr") or "pxrInternal" in text or "Tf" in type(exc).__name__:
        return f"USD could not read or write a file ({pxr_reason(exc)})" if text else \
            "USD could not read or write a file (it gave no reason): check the path is a writable folder and the " \
            "input files are intact"
    return text or type(exc).__name__
