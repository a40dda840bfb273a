"""USD output: the crash-safe streaming cache writer (``writer``), the prim declarations a scene
makes once for every sink (``prims``), reading caches back and validating them (``validate``),
exact-resume checkpoints (``checkpoint``) and chunk files authored in worker processes
(``chunk_author``). ``pxr`` is imported lazily, and so are this package's modules: a worker
process importing ``warpsim.usd.chunk_author`` loads neither Warp nor the solvers.

Drives no kernels. Entry classes: UsdCacheWriter, validate_cache, cache_info.
"""

__all__ = ["UsdCacheWriter", "validate_cache", "cache_info"]

_HOMES = {"UsdCacheWriter": "writer", "validate_cache": "validate", "cache_info": "validate"}


def __getattr__(name):
    home = _HOMES.get(name)
    if home is None:
        raise AttributeError(f"module 'warpsim.usd' has no attribute {name!r}")
    import importlib

    return getattr(importlib.import_module(f".{home}", __name__), name)


def __dir__():
    return sorted(set(globals()) | set(__all__))
