"""USD output: the crash-safe streaming cache writer (``writer``), the prim declarations a scene
makes once for every sink (``prims``), reading caches back and validating them (``validate``),
and exact-resume checkpoints (``checkpoint``). ``pxr`` is imported lazily, so importing this
package works without usd-core.

Drives no kernels. Entry classes: UsdCacheWriter, validate_cache, cache_info.
"""

from .validate import cache_info, validate_cache
from .writer import UsdCacheWriter

__all__ = ["UsdCacheWriter", "validate_cache", "cache_info"]
