"""``warpsim pick ROOT --world N --out FILE [--flatten]`` (the parser is
:func:`warpsim.browse.pick.add_parser`): a world's stored frames, or, for a sweep run with
``--store none``, the world re-run from the sweep's manifest
(:func:`warpsim.sweeps.rerun.pick_or_rerun`)."""
from __future__ import annotations

from ..browse.pick import add_parser, report
from .rerun import pick_or_rerun

__all__ = ["add_parser", "run"]


def run(args, out, err):
    return report(args, out, lambda: pick_or_rerun(args.root, args.world, args.out, flatten=args.flatten,
                                                   allow_damaged=args.allow_damaged))
