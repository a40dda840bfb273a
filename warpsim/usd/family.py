"""Which files belong to a cache or a sweep, so no command writes over its own inputs.

A warpsim cache ``DIR/s.usda`` and a sweep root ``DIR/s.usda`` keep their files beside them under
the same stem: ``s.manifest.usda``, ``s.chunkNNNNNN.usdc``, ``s.chunks.jsonl``,
``s.checkpoint.npz``, ``s.lock``; a sweep also ``s.batch_NNNN[.run<T>].usdc`` with their chunks,
``s.csv``, ``s.occupancy.npz``, ``s.sweep.json``, ``s.sweep-partial.json``, ``s.picked.usda``.
(A re-run world ``s.world_NNNNNN.usda`` is a cache of its own, not one of these.)

:func:`check_output` is called by every writing command (run, sweep, pick, rerun, export, render,
plot, the viewer's recorder) before it writes: an output that is one of the command's inputs (the
same file after resolving links), a file of an input's cache or sweep, or a file of another
existing cache or sweep in its folder is refused with one line naming both.
"""
from __future__ import annotations

import os
import re

__all__ = ["check_output", "family_role", "owner_of"]

_ROOT_EXT = (".usd", ".usda", ".usdc")
_MEMBERS = [  # (suffix after the stem, what it is)
    (r"\.(?:usd|usda|usdc)", "the cache itself (or its flattened copy)"),
    (r"\.manifest\.usda", "its clip manifest"),
    (r"\.chunk\d+\.usdc", "one of its chunk files"),
    (r"\.chunks\.jsonl", "its chunk index"),
    (r"\.checkpoint\.npz", "its checkpoint"),
    (r"\.lock", "its lock file"),
    (r"\.batch_\d+(?:\..*)?", "a batch layer (or a chunk of one) holding its worlds"),
    (r"\.csv", "its table"),
    (r"\.occupancy(?:\.run[0-9a-zA-Z]+)?\.npz", "its occupancy record"),
    (r"\.sweep\.json", "its sweep manifest"),
    (r"\.sweep-partial\.json", "its interrupted sweep's progress file"),
    (r"\.picked\.(?:usd|usda|usdc)", "its picked worlds"),
    (r"\.thumbs", "its thumbnails folder"),
]
_MEMBER_RE = [(re.compile(p + r"\Z", re.S), what) for p, what in _MEMBERS]


def family_role(stem_path, path) -> str | None:
    """What ``path`` is in the family of the cache or sweep whose root (without extension) is
    ``stem_path`` (e.g. "one of its chunk files"), or None when it is not one of its files."""
    folder, base = os.path.split(os.path.abspath(os.fspath(stem_path)))
    p_folder, name = os.path.split(os.path.abspath(os.fspath(path)))
    if os.path.normcase(p_folder) != os.path.normcase(folder) or not name.startswith(base + "."):
        return None
    suffix = name[len(base):]
    for rx, what in _MEMBER_RE:
        if rx.match(suffix):
            return what
    return None


def _root_of(stem) -> str | None:
    for ext in _ROOT_EXT:
        if os.path.isfile(stem + ext):
            return stem + ext
    return None


def owner_of(path) -> tuple | None:
    """(root path, role) of an existing cache or sweep in ``path``'s folder that ``path`` is a
    file of (a chunk, a batch layer, a table, ...), or None. ``path`` being a root itself does
    not count."""
    path = os.path.abspath(os.fspath(path))
    folder, name = os.path.split(path)
    parent = os.path.basename(folder)
    if parent.endswith(".thumbs"):  # a file inside a sweep's thumbnails folder
        root = _root_of(os.path.join(os.path.dirname(folder), parent[: -len(".thumbs")]))
        if root is not None:
            return root, "one of its thumbnails"
    for k in range(1, len(name)):
        if name[k] != ".":
            continue
        stem = os.path.join(folder, name[:k])
        role = family_role(stem, path)
        if role is None or role.startswith("the cache itself"):
            continue
        root = _root_of(stem)
        if root is not None and root != path:
            return root, role
    return None


def _same_file(a, b) -> bool:
    if os.path.realpath(a) == os.path.realpath(b):
        return True
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


def _input_stems(inputs):
    """Stems whose families the inputs belong to: each input's own, and its owner's."""
    out = []
    for p in inputs:
        p = os.path.abspath(os.fspath(p))
        out.append((os.path.splitext(p)[0], p))
        owner = owner_of(p)
        if owner is not None:
            out.append((os.path.splitext(owner[0])[0], owner[0]))
    return out


def check_output(out, inputs=(), flag="--out", own=None) -> None:
    """ValueError (one line) when writing ``out`` would overwrite one of ``inputs`` (same file
    after resolving links), a file of an input's cache or sweep, or a file of another existing
    cache or sweep beside it (``own``: the root this command writes, whose files it may write)."""
    shown = os.fspath(out)
    target = os.path.abspath(shown)
    if os.path.isabs(shown) and not os.path.relpath(target).startswith(".."):
        shown = os.path.relpath(target)
    fix = f"choose another {flag}" if flag else "choose another output"
    what = f"{flag} {shown!r}" if flag else repr(shown)
    for p in inputs:
        if _same_file(target, os.fspath(p)):
            raise ValueError(f"{what} is this command's input {os.fspath(p)!r}; writing it would destroy what it "
                             f"reads: {fix}")
    real = os.path.realpath(target)
    for stem, root in _input_stems(inputs):
        role = family_role(stem, target) or family_role(stem, real)
        if role is not None:
            raise ValueError(f"{what} is a file of {os.path.relpath(root)!r}, this command's input ({role}): "
                             f"writing it would destroy what it reads; {fix}")
    owner = owner_of(target) or (owner_of(real) if real != target else None)
    if owner is not None and (own is None or os.path.abspath(os.fspath(own)) != owner[0]):
        root, role = owner
        raise ValueError(f"{what} is a file of the cache or sweep {os.path.relpath(root)!r} ({role}): writing it "
                         f"would damage that result; {fix}")
