"""``warpsim query``: ask a finished sweep where its worlds went, without simulating again.

    warpsim query ROOT [--inside X0,Y0,Z0,X1,Y1,Z1@T0:T1 ...] [--outside BOX@T0:T1 ...]
                       [--rank METRIC [--top K]] [--where METRIC<VALUE ...] [--table CSV]

Reads the sweep's table (``<stem>.csv``) and occupancy record (``<stem>.occupancy.npz``, see
:mod:`warpsim.browse.occupancy`) beside ``ROOT`` and prints the picked worlds exactly as
``warpsim sweep`` does with the same options (the same worlds in the same order), then writes
``<stem>.picked<ext>`` holding only those. Exit status 2 (one line) for a bad box or window, a
root without a record, an unknown metric.
"""
from __future__ import annotations

import csv
import os

from ..cli_common import UsageError


def add_parser(sub):
    s = sub.add_parser("query", help="pick a sweep's worlds by where their particles went (IN / NOT IN a box during "
                                     "a window), from its occupancy record")
    s.add_argument("root", help="root USD written by 'warpsim sweep'")
    s.add_argument("--inside", action="append", default=[], metavar="X0,Y0,Z0,X1,Y1,Z1@T0:T1",
                   help="keep worlds with a (tracked) particle inside the box [m] at some frame of the window [s] "
                        "(repeatable; adds insideK_time, insideK_entry, insideK_share to rank by)")
    s.add_argument("--outside", action="append", default=[], metavar="X0,Y0,Z0,X1,Y1,Z1@T0:T1",
                   help="keep worlds with no (tracked) particle inside the box during the window (repeatable)")
    from ..browse.query import accept_negative_boxes

    accept_negative_boxes(s)
    s.add_argument("--rank", default=None, metavar="METRIC", help="order worlds by a metric or query column "
                   "(METRIC:desc or --rank=-METRIC: largest first)")
    s.add_argument("--top", type=int, default=None, metavar="K", help="keep the first K worlds of --rank")
    s.add_argument("--where", action="append", default=[], metavar="METRIC<VALUE",
                   help="keep worlds whose metric passes (< <= > >= == !=; repeatable)")
    s.add_argument("--table", default=None, help="the sweep's CSV table (default: beside ROOT, <stem>.csv)")
    return s


def _number(text):
    try:
        return int(text)
    except ValueError:
        try:
            return float(text)
        except ValueError:
            return text


def read_table(path):
    """Rows of a sweep table, numbers parsed (vectors stay ``"x,y,z"`` text)."""
    from ..usd.pxr_errors import DamagedFileError

    if not os.path.exists(path):
        raise FileNotFoundError(f"no sweep table {path}; give --table CSV or run the sweep again")
    if not os.path.isfile(path):  # a FIFO would block for ever
        raise ValueError(f"sweep table {path} is not a regular file (a pipe, socket or folder); give --table CSV")
    try:
        with open(path, newline="", encoding="utf-8") as f:
            rows = [{k: _number(v) for k, v in row.items()} for row in csv.DictReader(f)]
    except UnicodeDecodeError as exc:
        raise DamagedFileError(f"sweep table {path} is not text (byte 0x{exc.object[exc.start]:02x} at offset "
                               f"{exc.start} is not UTF-8): it is damaged or not a table; give the sweep's --table "
                               "CSV or run the sweep again") from None
    except csv.Error as exc:
        raise DamagedFileError(f"sweep table {path} is not a readable CSV table ({exc}); run the sweep again") \
            from None
    if not rows:
        with open(path, newline="", encoding="utf-8") as f:
            header = next(csv.reader(f), [])
        if "world" in header:
            raise ValueError(f"sweep table {path} has its header and no rows (a sweep of no worlds, or one "
                             "interrupted before its table was written); run the sweep again or give another --table")
    if not rows or "world" not in rows[0]:
        raise ValueError(f"{path} is not a sweep table (no 'world' column); give --table CSV")
    for i, row in enumerate(rows):
        if not isinstance(row.get("world"), int) or None in row or any(v is None for v in row.values()):
            raise DamagedFileError(f"sweep table {path}: row {i + 1} (field 'world' = {row.get('world')!r}) is "
                                   "damaged (not a world index, or a different number of fields than the header); "
                                   "run the sweep again")
    return rows


def run(args, out, err):
    from ..browse.occupancy import OccupancyRecord
    from ..browse.query import answer_region, answers_note, apply_regions, cached_positions, parse_region, region_columns
    from ..browse.roots import sweep_root_files, unstored_root_files, write_sweep_root
    from .metrics import parse_rank, parse_where, print_picked, select

    usage = UsageError
    if args.top is not None and args.top < 1:
        raise usage(f"--top {args.top}: it must be >= 1")
    if args.top is not None and args.rank is None:
        raise usage("--top needs --rank METRIC (the order to take the top worlds from)")
    try:
        unstored = unstored_root_files(args.root, args.table)  # --store none: the record and table alone
        files = unstored or sweep_root_files(args.root, args.table)
        regions = [parse_region(t, True) for t in args.inside] + [parse_region(t, False) for t in args.outside]
        record = OccupancyRecord.load(files["record"])
        rows = read_table(files["table"])
        names = list(rows[0]) + region_columns(regions)
        rank = parse_rank(args.rank, names) if args.rank else None
        where = [parse_where(w, names) for w in args.where]
        positions = cached_positions(args.root, record) if regions and not unstored else None
        answers = [answer_region(record, r, positions) for r in regions]  # windows checked here
        candidates = apply_regions(rows, record, regions, answers=answers)
    except (OSError, ValueError) as exc:
        if getattr(exc, "exit_status", 2) != 2:
            raise  # a damaged table or record: exit 1, naming the file and the field
        from ..usd.pxr_errors import error_line

        raise usage(error_line(exc)) from None
    params = [k for k in rows[0] if k != "world" and k not in _metric_columns(rows[0])]
    print(record.describe(), file=out)
    if regions:
        print(answers_note(record, regions, answers), file=out)
    picked = select(candidates, rank=rank, top=args.top, where=where)
    print_picked(picked, len(rows), params, rank=rank, where=where, extra=region_columns(regions), out=out)
    if picked and unstored:
        print(f"picked worlds: none written ({args.root} stored no frames, --store none); warpsim pick "
              f"{args.root} --world N --out FILE re-runs one", file=out)
    elif picked:
        root = os.path.abspath(args.root)
        stem, ext = os.path.splitext(root)
        layers = sorted({layer for _, layer in files["worlds"]})
        from ..usd.lock import hold

        hold(stem + ".picked" + ext, "")  # one writer of the picked worlds (released when the command ends)
        try:
            pick_path = write_sweep_root(stem + ".picked" + ext, layers, len(rows), layout=files["layout"],
                                         worlds=[r["world"] for r in picked])
        except Exception as exc:  # noqa: BLE001  (Tf.ErrorException: a batch layer that does not open)
            from ..usd.pxr_errors import DamagedFileError, error_line

            if isinstance(exc, (ValueError, OSError)) and not type(exc).__module__.startswith("pxr"):
                raise
            raise DamagedFileError(f"could not write the picked worlds: a batch layer of {args.root} does not open "
                                   f"({error_line(exc)}); run the sweep again") from None
        print(f"picked worlds: {os.path.relpath(pick_path)}", file=out)
    return 0


def _metric_columns(row):
    """The metric columns of a table row (built-in and tracked), as ``warpsim sweep`` writes them
    after the parameters."""
    from .metrics import BUILTIN

    keys = list(row)
    first = next((i for i, k in enumerate(keys) if k in BUILTIN), len(keys))
    return set(keys[first:])
