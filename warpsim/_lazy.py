"""Names of a package loaded on first use (PEP 562): a package's ``__getattr__`` made by :func:`lazy_attributes`."""

from __future__ import annotations

import importlib


def lazy_attributes(package: str, homes: dict, namespace: dict):
    """A module ``__getattr__`` for ``package`` (its ``__name__``): name ``n`` in ``homes`` is imported on first use
    from the module ``homes[n]`` (relative to the package, e.g. ``".vbd"``) and bound in ``namespace`` (the package's
    ``globals()``, as an import in its file would bind it); any other name raises AttributeError."""

    def __getattr__(name: str):
        if name in homes:
            value = namespace[name] = getattr(importlib.import_module(homes[name], package), name)
            return value
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    return __getattr__
