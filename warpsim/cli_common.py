"""What every ``warpsim`` command module shares with ``warpsim.cli``, one floor below both (so a
command module imports this, not the command line that loads it): the usage-mistake exception and
the ``--device`` check."""

from __future__ import annotations

__all__ = ["UsageError", "device_arg", "one_line"]


class UsageError(Exception):
    """A mistake in the command line: reported with exit status 2."""


def device_arg(name) -> str:
    """The Warp device named by ``--device`` (``None``: ``cuda:0`` when CUDA is available, else
    ``cpu``) as a string; UsageError listing the available devices when it does not exist."""
    import warp as wp

    if name is None:
        return "cuda:0" if wp.is_cuda_available() else "cpu"
    try:
        return str(wp.get_device(name))
    except Exception as exc:  # noqa: BLE001  (Warp raises plain Exception/RuntimeError/ValueError)
        choices = [str(d) for d in wp.get_devices()]
        raise UsageError(f"--device {name!r} is not available ({exc}); available: {', '.join(choices)}") from None


def one_line(exc) -> str:
    """An exception's text on one line (its type name when it has none)."""
    return " ".join(str(exc).split("\n")).strip() or type(exc).__name__
