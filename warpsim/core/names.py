"""Names in error messages: the "Did you mean ...?" hint shared by every check that rejects an
unknown name (scene parameters, prims, metrics, choices)."""

from __future__ import annotations

import difflib


def close_matches(word, choices, n: int = 3) -> str:
    """' Did you mean ...?' suffix for an error message naming up to ``n`` of ``choices`` close to
    ``word`` ('' when nothing is close)."""
    match = difflib.get_close_matches(str(word), [str(c) for c in choices], n=n, cutoff=0.5)
    return f" Did you mean {' or '.join(repr(m) for m in match)}?" if match else ""
