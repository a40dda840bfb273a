"""pxr's error texts in warpsim's words: what a ``Tf.ErrorException`` says without its internal
prefix (shared by the readers and the chunk index, one floor below both)."""

__all__ = ["pxr_reason"]


def pxr_reason(exc, limit=160) -> str:
    """What a ``pxr`` error says, without its internal prefix ("Error in 'pxrInternal_...' at line
    N in file ... : 'text'" -> "text"); the last message when there are several."""
    import re

    text = str(exc).strip()
    found = re.findall(r"Error in '[^']*' at line \d+ in file [^:]* : '(.*?)'\s*(?=\n\s*Error in|$)", text, re.S)
    reason = (found[-1] if found else text.splitlines()[-1] if text else type(exc).__name__).strip()
    reason = " ".join(reason.split())
    return reason if len(reason) <= limit else reason[: limit - 3] + "..."
