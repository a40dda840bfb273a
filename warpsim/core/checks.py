"""Shared input validation: every check returns the cleaned value or raises an error that names
the item, shows the value and says how to fix it.

Used wherever user input enters warpsim (builders, forces, colliders, solvers, loaders, the
command line) so that bad input fails early, before any kernel runs, with one kind of message::

    checks.positive(max_speed, "Simulator max_speed", unit="m/s")
    -> ValueError: Simulator max_speed must be a finite number > 0 [m/s], got -1.0; give e.g. 1e4

Errors are ``ValueError`` (bad values) or :class:`MissingFileError` / :class:`UnreadableFileError`
for files (subclasses of both ``FileNotFoundError``/``PermissionError`` and ``ValueError``, so
``except ValueError`` keeps catching them).
"""

from __future__ import annotations

import errno
import math
import numbers
import os

import numpy as np

__all__ = [
    "MissingFileError",
    "UnreadableFileError",
    "choice",
    "count",
    "existing_file",
    "finite",
    "flag",
    "in_range",
    "index_array",
    "integer",
    "mesh_vertices",
    "nonnegative",
    "number",
    "numbers_array",
    "positive",
    "same_length",
    "sequence_of",
    "show",
    "vec3",
    "vectors",
]


class MissingFileError(FileNotFoundError, ValueError):
    """A named input file does not exist (``.filename`` holds the path)."""

    def __str__(self):
        return str(self.strerror)


class UnreadableFileError(PermissionError, ValueError):
    """A named input file exists but cannot be read (``.filename`` holds the path)."""

    def __str__(self):
        return str(self.strerror)


def _file_error(cls, message, path):
    return cls(errno.ENOENT if cls is MissingFileError else errno.EACCES, message, path)


def show(value, limit: int = 60) -> str:
    """Short repr of ``value`` for messages (type added for non-numbers, long reprs cut)."""
    if isinstance(value, (str, bytes)):
        text = repr(value)
    elif isinstance(value, (bool, numbers.Number)) or value is None:
        return repr(value)
    else:
        text = repr(value)
        if not isinstance(value, (list, tuple, np.ndarray)):
            text = f"{text} ({type(value).__name__})"
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _unit(unit):
    return f" [{unit}]" if unit else ""


def _fix(fix):
    return f"; {fix}" if fix else ""


def _to_float(value, what, requirement, fix):
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (numbers.Real, np.ndarray, np.generic)):
        raise ValueError(f"{what} must be {requirement}, got {show(value)}{_fix(fix)}")
    try:
        return float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be {requirement}, got {show(value)}{_fix(fix)}") from None


def number(value, what: str, unit: str = "", fix: str = "") -> float:
    """``value`` as a float (it may be NaN or infinite); ValueError naming ``what`` for strings,
    None and other non-numbers instead of ``could not convert string to float``."""
    return _to_float(value, what, f"a number{_unit(unit)}", fix)


def finite(value, what: str, unit: str = "", fix: str = "") -> float:
    """``value`` as a float; ValueError unless it is a finite real number (strings and None are
    rejected, not parsed)."""
    req = f"a finite number{_unit(unit)}"
    v = _to_float(value, what, req, fix)
    if not math.isfinite(v):
        raise ValueError(f"{what} must be {req}, got {v}{_fix(fix)}")
    return v


def in_range(
    value, what: str, lo=None, hi=None, *, lo_open=False, hi_open=False, unit: str = "", fix: str = ""
) -> float:
    """A finite float with ``lo <= value <= hi`` (``<`` where ``lo_open``/``hi_open``)."""
    parts = []
    if lo is not None:
        parts.append(f"{'>' if lo_open else '>='} {lo:g}")
    if hi is not None:
        parts.append(f"{'<' if hi_open else '<='} {hi:g}")
    req = "a finite number" + (" " + " and ".join(parts) if parts else "") + _unit(unit)
    v = _to_float(value, what, req, fix)
    ok = math.isfinite(v)
    if ok and lo is not None:
        ok = v > lo if lo_open else v >= lo
    if ok and hi is not None:
        ok = v < hi if hi_open else v <= hi
    if not ok:
        raise ValueError(f"{what} must be {req}, got {show(value)}{_fix(fix)}")
    return v


def positive(value, what: str, unit: str = "", fix: str = "") -> float:
    """A finite float > 0."""
    return in_range(value, what, 0.0, lo_open=True, unit=unit, fix=fix)


def nonnegative(value, what: str, unit: str = "", fix: str = "") -> float:
    """A finite float >= 0."""
    return in_range(value, what, 0.0, unit=unit, fix=fix)


def integer(value, what: str, lo=None, hi=None, fix: str = "") -> int:
    """An int (Python or NumPy integer, or a float with an integral value) within [lo, hi]."""
    bounds = []
    if lo is not None:
        bounds.append(f">= {lo}")
    if hi is not None:
        bounds.append(f"<= {hi}")
    req = "an integer" + (" " + " and ".join(bounds) if bounds else "")
    if isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{what} must be {req}, got {show(value)}{_fix(fix)}")
    if isinstance(value, (numbers.Integral, np.integer)):
        v = int(value)
    elif (
        isinstance(value, (numbers.Real, np.floating))
        and math.isfinite(float(value))
        and float(value).is_integer()
    ):
        v = int(float(value))
    else:
        raise ValueError(f"{what} must be {req}, got {show(value)}{_fix(fix)}")
    if (lo is not None and v < lo) or (hi is not None and v > hi):
        raise ValueError(f"{what} must be {req}, got {v}{_fix(fix)}")
    return v


def count(value, what: str, minimum: int = 1, fix: str = "") -> int:
    """A count: an integer >= ``minimum`` (default 1)."""
    return integer(value, what, lo=minimum, fix=fix)


def choice(value, what: str, choices, fix: str = ""):
    """``value`` if it is one of ``choices``; else ValueError listing them (and a close match)."""
    try:
        ok = value in choices
    except TypeError:  # unhashable value
        ok = False
    if not ok:
        import difflib

        close = (
            difflib.get_close_matches(str(value), [str(c) for c in choices], n=1)
            if isinstance(value, str)
            else []
        )
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise ValueError(
            f"{what} {show(value)} is unknown; use one of {', '.join(map(repr, choices))}{hint}{_fix(fix)}"
        )
    return value


def index_array(values, what: str, fix: str = "") -> np.ndarray:
    """``values`` (vertex or particle indices, any shape) as int64; a non-integer index (2.5) is
    refused naming ``what`` and the first such entry, never truncated. ValueError for values that
    are not numbers."""
    try:
        a = np.asarray(values)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be an array of integer indices, got {show(values)}{_fix(fix)}") from None
    if a.dtype.kind in "iu":
        return a.astype(np.int64)
    if a.dtype.kind == "b" or a.dtype.kind not in "f" and a.size:
        raise ValueError(f"{what} must be integer indices, got dtype {a.dtype}{_fix(fix)}")
    a = a.astype(np.float64)
    bad = np.flatnonzero(~np.isfinite(a.reshape(-1)) | (a.reshape(-1) != np.round(a.reshape(-1))))
    if len(bad):
        k = int(bad[0])
        raise ValueError(f"{what} holds the non-integer index {float(a.reshape(-1)[k])!r} (entry {k}); indices are "
                         f"counted in whole vertices and are not rounded: give integers{_fix(fix)}")
    return a.astype(np.int64)


class FlagError(TypeError, ValueError):
    """A True/False option given something else (``'no'`` is truthy in Python: never a mode turned
    on by accident). Both a TypeError and a ValueError, so either ``except`` catches it."""


def flag(value, what: str, fix: str = "") -> bool:
    """``value`` as a bool when it is ``True``/``False`` (NumPy's too, or the integers 0 and 1);
    anything else, strings such as ``'no'`` included, is refused naming ``what``.
    The one parser of True/False options in the API (the command line parses ``--set`` text with
    :func:`warpsim.scenes.parse_value`: true/false, yes/no, on/off, 1/0)."""
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, numbers.Integral) and value in (0, 1):
        return bool(value)
    name = what.split()[-1]
    hint = ""
    if isinstance(value, str) and value.strip().lower() in ("1", "0", "true", "false", "yes", "no", "on", "off"):
        hint = f" (the text {value!r} is not a bool in Python: 'no' would count as True)"
    raise FlagError(f"{what} must be True or False, got {show(value)}{hint}; e.g. {name}=False{_fix(fix)}")


def vec3(value, what: str, *, nonzero: bool = False, unit: str = "", fix: str = "") -> tuple:
    """A tuple of 3 finite floats (a sequence of numbers; strings are rejected)."""
    if isinstance(value, (str, bytes)) or value is None or isinstance(value, numbers.Number):
        raise ValueError(
            f"{what} must be a sequence of 3 numbers{_unit(unit)}, got {show(value)}"
            f"{_fix(fix or 'e.g. (0.0, 1.0, 0.0)')}"
        )
    try:
        items = list(value)
    except TypeError:
        raise ValueError(
            f"{what} must be a sequence of 3 numbers{_unit(unit)}, got {show(value)}"
            f"{_fix(fix or 'e.g. (0.0, 1.0, 0.0)')}"
        ) from None
    if len(items) != 3:
        raise ValueError(
            f"{what} must have 3 components, got {len(items)}: {show(value)}{_fix(fix or 'give (x, y, z)')}"
        )
    out = []
    for k, c in enumerate(items):
        out.append(_to_float(c, f"{what} component {k}", "a number", fix or "give 3 numbers (x, y, z)"))
    v = tuple(out)
    if not all(math.isfinite(c) for c in v):
        raise ValueError(f"{what} is not finite: {v}{_fix(fix or 'give finite coordinates')}")
    if nonzero and not any(v):
        raise ValueError(f"{what} is the zero vector{_fix(fix or 'give a non-zero direction')}")
    return v


def _as_float_array(values, what, fix):
    if isinstance(values, (str, bytes)) or values is None:
        raise ValueError(f"{what} must be an array of numbers, got {show(values)}{_fix(fix)}")
    try:
        arr = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(
            f"{what} must be an array of numbers ({exc}), got {show(values)}{_fix(fix)}"
        ) from None
    return arr


def float_array(values, what: str, fix: str = "") -> np.ndarray:
    """``values`` as a float64 array (any shape; NaN allowed); ValueError naming ``what`` for
    strings, None and ragged or non-numeric input."""
    return np.asarray(_as_float_array(values, what, fix), dtype=np.float64)


def vectors(
    values, what: str, width: int = 3, *, item: str = "row", min_count: int = 0, unit: str = "", fix: str = ""
) -> np.ndarray:
    """(N, width) float64 array of finite values; a flat list of ``N * width`` numbers or a
    single vector (N = 1) is accepted. Errors name the first bad row: ``{what} {item} 4``."""
    arr = _as_float_array(values, what, fix)
    if arr.ndim == 1 and arr.size == width:
        arr = arr.reshape(1, width)
    if arr.ndim != 2 or arr.shape[1] != width:
        raise ValueError(
            f"{what} must have shape (N, {width}){_unit(unit)}, got shape {arr.shape}"
            f"{_fix(fix or f'give one row of {width} numbers per {item}')}"
        )
    bad = np.flatnonzero(~np.isfinite(arr).all(axis=1))
    if len(bad):
        k = int(bad[0])
        raise ValueError(
            f"{what}: {item} {k} is not finite: {arr[k].tolist()}"
            f"{_fix(fix or f'give finite values (or remove {item} {k})')}"
        )
    if len(arr) < min_count:
        raise ValueError(f"{what} needs at least {min_count} {item}(s), got {len(arr)}{_fix(fix)}")
    return arr


def numbers_array(
    values,
    what: str,
    length=None,
    *,
    lo=None,
    lo_open=False,
    item: str = "entry",
    unit: str = "",
    fix: str = "",
) -> np.ndarray:
    """1-D float64 array of finite numbers (a scalar is broadcast to ``length``), optionally
    ``>= lo`` (``> lo`` with ``lo_open``)."""
    arr = _as_float_array(values, what, fix)
    if arr.ndim == 0 and length is not None:
        arr = np.full(int(length), float(arr))
    if arr.ndim != 1:
        raise ValueError(
            f"{what} must be a 1-D sequence of numbers{_unit(unit)}, got shape {arr.shape}{_fix(fix)}"
        )
    if length is not None and len(arr) != length:
        raise ValueError(f"{what} has {len(arr)} entries but {length} are needed{_fix(fix)}")
    bad = np.flatnonzero(~np.isfinite(arr))
    if lo is not None:
        bad = np.flatnonzero(~np.isfinite(arr) | ((arr <= lo) if lo_open else (arr < lo)))
    if len(bad):
        k = int(bad[0])
        need = "finite" if lo is None else f"finite and {'>' if lo_open else '>='} {lo:g}"
        raise ValueError(f"{what}: {item} {k} is {arr[k]}; it must be {need}{_unit(unit)}{_fix(fix)}")
    return arr


def same_length(**arrays) -> int:
    """The common length of the keyword arrays; ValueError naming both when two differ."""
    items = [(name, len(a)) for name, a in arrays.items() if a is not None]
    for name, n in items[1:]:
        if n != items[0][1]:
            raise ValueError(
                f"{items[0][0]} has {items[0][1]} entries but {name} has {n}; give one {name} "
                f"per {items[0][0]} entry"
            )
    return items[0][1] if items else 0


def sequence_of(items, what: str, cls, example: str) -> list:
    """``items`` as a list of ``cls`` instances. A single instance (``forces=ws.Gravity()``) or
    a non-sequence gets a message showing the list form ``example``."""
    if isinstance(items, cls):
        raise ValueError(
            f"{what} must be a list, got a single {type(items).__name__}; write {what}=[...] (e.g. {example})"
        )
    if isinstance(items, (str, bytes, dict)):
        raise ValueError(
            f"{what} must be a list of {cls.__name__} objects, got {show(items)}; e.g. {example}"
        )
    try:
        out = list(items)
    except TypeError:
        raise ValueError(
            f"{what} must be a list of {cls.__name__} objects, got {show(items)}; e.g. {example}"
        ) from None
    for k, obj in enumerate(out):
        if not isinstance(obj, cls):
            raise ValueError(
                f"{what}[{k}] is {type(obj).__name__}, not a warpsim {cls.__name__}; e.g. {example}"
            )
    return out


def mesh_vertices(points, what: str = "mesh", *, fix: str = "") -> np.ndarray:
    """(V, 3) float64 vertices, every one finite; the error names the first bad vertex."""
    return vectors(
        points,
        f"{what} vertices",
        3,
        item="vertex",
        fix=fix or "fix or remove that vertex (NaN/inf coordinates cannot be meshed)",
    )


def existing_file(path, what: str = "file") -> str:
    """``path`` as a str if it names a readable regular file; :class:`MissingFileError`,
    :class:`UnreadableFileError` or ValueError (a folder) naming it otherwise."""
    path = os.fspath(path)
    if not os.path.exists(path):
        raise _file_error(MissingFileError, f"{what} {path!r} does not exist; check the path", path)
    if os.path.isdir(path):
        raise ValueError(f"{what} {path!r} is a folder, not a file; name the file inside it")
    if not os.access(path, os.R_OK):
        raise _file_error(
            UnreadableFileError,
            f"{what} {path!r} cannot be read (permission denied); fix its permissions",
            path,
        )
    return path
