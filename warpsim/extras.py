"""The optional extras (``pip install "warpsim[EXTRA]"``) and the check every command that needs
one makes before doing any work: a missing extra is one line naming the install command (the
command line turns it into ``warpsim: error: ...`` and exit status 2), never a traceback after a
finished simulation. Checks look modules up without importing them (fast, no side effects)."""

from __future__ import annotations

import importlib.util
import os
import sys

from .cli_common import UsageError

__all__ = ["EXTRAS", "MissingExtraError", "missing_modules", "render_modules", "require_extra"]

EXTRAS = {
    "viewer": ("viser",),
    "render": ("PIL", "imageio", "imageio_ffmpeg"),
    "plot": ("matplotlib",),
    "ray": ("ray",),
}
"""Extra name -> the modules it installs (see ``[project.optional-dependencies]``)."""


class MissingExtraError(UsageError):
    """An optional extra is not installed (a usage mistake: exit status 2)."""


def missing_modules(modules) -> list:
    """The names in ``modules`` that cannot be imported here (absent, or blocked with
    ``sys.modules[name] = None``)."""
    missing = []
    for name in modules:
        if name in sys.modules:
            if sys.modules[name] is None:
                missing.append(name)
            continue
        try:
            found = importlib.util.find_spec(name) is not None
        except (ImportError, ValueError):
            found = False
        if not found:
            missing.append(name)
    return missing


def render_modules(path) -> tuple:
    """Modules the preview renderer needs to write ``path``: none for .png (``warpsim.render.png``),
    Pillow for .gif, imageio with its ffmpeg plugin for .mp4."""
    ext = os.path.splitext(str(path))[1].lower()
    return {".mp4": ("imageio", "imageio_ffmpeg"), ".png": ()}.get(ext, ("PIL",))


def require_extra(extra: str, what: str, modules=None) -> None:
    """Raise :class:`MissingExtraError` naming ``pip install "warpsim[extra]"`` unless ``modules``
    (default: all of the extra's) can be imported; ``what`` says who needs them (e.g. "warpsim plot")."""
    if extra not in EXTRAS:
        raise ValueError(f"unknown extra {extra!r}; one of {sorted(EXTRAS)}")
    missing = missing_modules(EXTRAS[extra] if modules is None else modules)
    if missing:
        names = ", ".join(_PACKAGES.get(m, m) for m in missing)
        raise MissingExtraError(f"{what} needs the optional extra '{extra}' ({names} not installed): "
                                f'pip install "warpsim[{extra}]"')


_PACKAGES = {"PIL": "pillow", "imageio_ffmpeg": "imageio-ffmpeg"}  # module -> the package that installs it
