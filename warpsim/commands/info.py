"""``warpsim info CACHE``: a cache's prims, frame range, counts and bounds; damaged chunk files,
a sweep still being written or one interrupted before it published."""
from __future__ import annotations

import os
import sys

from ..cli_common import UsageError, one_line

READ_ONLY = True
"""Writes nothing: run outside the command's output-lock scope."""


def add_parser(sub):
    i = sub.add_parser("info", help="summarise a USD cache")
    i.add_argument("cache", help="path of a .usd/.usda/.usdc file")
    i.add_argument("--verify", action="store_true",
                   help="compare every chunk file's CRC-32 (reads them all; done anyway below 256 MiB)")


def run(args, out, err):
    return cache_summary(args.cache, out, err, args.verify)


def cache_summary(path, out, err=None, verify=False):
    """Print the summary of cache ``path`` on ``out``; the exit status (1: damaged chunk files or a
    sweep not written yet, named on ``err``)."""
    from ..usd.validate import cache_info

    if os.path.isdir(path):
        raise UsageError(f"{path!r} is a folder; give the cache file in it (.usd, .usda or .usdc)")
    if os.path.exists(path) and not os.path.isfile(path):  # reading a FIFO would wait for a writer for ever
        raise UsageError(f"{path!r} is not a regular file (a pipe, socket or device); give the cache file itself")
    staged = _staged_sweep_note(path)
    if staged is not None and not os.path.exists(path):  # a first sweep killed before it published anything
        print(staged, file=out)
        print(f"warpsim: error: {path} is not written yet: {staged.split(': ', 1)[1]}", file=err or sys.stderr)
        return 1
    try:
        info = cache_info(path, verify=True if verify else None)
    except FileNotFoundError as exc:  # checks.MissingFileError (not imported here: it would load Warp)
        raise UsageError(str(exc)) from None
    except ValueError as exc:  # the root layer itself is damaged
        print(f"warpsim: error: {one_line(exc)}", file=err or sys.stderr)
        return 1
    if info["frames"]:
        span = f"frames {info['start']}..{info['end']} ({info['frames']} frames at {info['fps']:g} fps, " \
               f"{(info['frames'] - 1) / info['fps']:.3g} s)"
    else:
        span = "no frames"
    print(f"{info['path']}: {span}", file=out)
    if staged is not None:  # a later sweep into this root was interrupted: the result above is the older one
        print(staged.replace("a sweep ", "a newer sweep ", 1), file=out)
    writing = _writer_note(path)
    if writing:
        print(writing, file=out)
    for prim in info["prims"]:
        count = prim.get("count")
        count = "" if count is None else (f"  count {count[0]}" if count[0] == count[1] else
                                          f"  count {count[0]}..{count[1]}")
        bounds = prim.get("bounds")
        bounds = "" if bounds is None else "  bounds [" + ", ".join(f"{v:.4g}" for v in bounds[0]) + "] .. [" + \
            ", ".join(f"{v:.4g}" for v in bounds[1]) + "]"
        kind = "animated" if prim["animated"] else "static"
        print(f"  {prim['path']:<28} {prim['type']:<15} {kind:<8}{count}{bounds}", file=out)
    damaged = info.get("damaged")
    if not damaged:
        return 0
    readable = ", ".join(f"{a}..{b}" for a, b in info["readable"]) or "none"
    print(f"DAMAGED: {len(damaged)} chunk file(s) (checked: {info['checked']}); counts and bounds above cover the "
          "readable frames only", file=out)
    for fname, start, end, why in damaged:
        print(f"  {fname}  frames {start}..{end}: {why}", file=out)
    print(f"readable frames: {readable}", file=out)
    print(f"warpsim: error: {path}: {len(damaged)} damaged chunk file(s) (first: {damaged[0][0]}, frames "
          f"{damaged[0][1]}..{damaged[0][2]}, {damaged[0][3]}); readable frames {readable}", file=err or sys.stderr)
    return 1


def _writer_note(path):
    """A line when a live process on this host holds the lock of ``path`` (the cache is still being
    written: the frames above are the ones completed so far), else None."""
    import socket

    from ..usd.lock import lock_info, lock_path, pid_alive

    holder = lock_info(lock_path(path)) or {}
    if holder.get("host") != socket.gethostname() or not pid_alive(holder.get("pid")) or \
            holder.get("pid") == os.getpid():
        return None
    return f"being written by pid {holder['pid']} ('{str(holder.get('command') or '')[:120]}'): the frames above are " \
        "the ones completed so far"


def _staged_sweep_note(path):
    """One line on the interrupted sweep staged for root ``path`` (its staged layer, completed
    frames, how to continue), or None when none is staged."""
    from ..sweeps.staging import staged_sweep

    staged = staged_sweep(path)
    if staged is None:
        return None
    rel = os.path.relpath
    settings = staged["settings"]
    what = f"of scene {settings['scene']!r} " if settings.get("scene") else ""
    if staged["why"]:
        return f"{rel(path)}: a sweep {what}into it was interrupted, but {staged['why']}; run the sweep again"
    frames = ", ".join(f"{a}..{b}" for a, b in staged["frames"]) or "none"
    total = settings.get("frames")
    of = f" of 0..{total}" if isinstance(total, int) else ""
    damaged = f" ({len(staged['damaged'])} damaged chunk file(s))" if staged["damaged"] else ""
    import socket

    from ..usd.lock import lock_info, lock_path, pid_alive

    holder = lock_info(lock_path(path)) or {}  # the sweep's lock file names its command (stale once killed)
    if holder.get("host") == socket.gethostname() and pid_alive(holder.get("pid")) and holder.get("pid") != os.getpid():
        return (f"{rel(path)}: a sweep {what}into it is running (pid {holder['pid']}): its staged layer "
                f"{rel(staged['layer'])} holds completed frames {frames}{of} so far")
    cmd = str(holder.get("command") or "")
    again = "the same 'warpsim sweep ...' options and --resume"
    if cmd.startswith("warpsim sweep"):
        again = f"'{cmd}{'' if ' --resume' in cmd else ' --resume'}'"
    return (f"{rel(path)}: a sweep {what}into it was interrupted: its staged layer {rel(staged['layer'])} holds "
            f"completed frames {frames}{of}{damaged}; continue it with {again}, or run it again without --resume")
