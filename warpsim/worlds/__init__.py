"""Many worlds stepped together: N variants of one scene in one model, one launch per stage for
all worlds. The sweeps that drive them are :mod:`warpsim.sweeps`; browsing a finished sweep is
:mod:`warpsim.browse`.

Modules:
  batch     :class:`WorldBatch`: world 0 tiled on the device into N worlds (``kernels/worlds.py``:
            tile_*, per-world gravity, blow-up flags and freezing), stepped by the scene's own
            simulator class, one launch per stage for all worlds (``fused=True``: the cloth
            solver's fused semi-implicit kernel); particle-pair and agent neighbour grids are
            keyed by world (``kernels/worlds.py: world_key``)
  shared    the shared-topology path of a batch (the default for mass-spring scenes): springs stored
            once, one fused kernel per sub-step (``kernels/world_step.py``)
  passes    per-world step counts on the paths without a masked kernel (tiled, cloth): one pass per
            distinct count, each world keeping the pass of its own count
  plan      how a varied parameter enters one world's arrays, found by building the scene a few times
  agents    :class:`AgentWorldBatch`: flocks (``flock``, ``school``) as one Flock with world-keyed
            neighbours and per-world food
  forces    :class:`WorldGravity`, :class:`WorldPlanes` (per-world gravity, wall restitution and
            friction; ``kernels/collide.py: collide_planes_worlds``)

The sweep and browsing names this package exported before the split (``run_batch``,
``sample_worlds``, ``write_sweep_root``, ``write_table``, ``UserMetric``, ``WorldMetrics``,
``rerun_world``, ``OccupancyRecord``, ``OccupancyRecorder``, ``Region``, ``answer_region``,
``parse_region``, ``pick_world``) still resolve here, looked up on first use from their new
packages (so importing this package imports nothing above it).
"""
from .batch import WorldBatch

__all__ = ["WorldBatch"]

_MOVED = {
    "run_batch": "warpsim.sweeps", "sample_worlds": "warpsim.sweeps", "write_table": "warpsim.sweeps",
    "write_sweep_root": "warpsim.sweeps", "UserMetric": "warpsim.sweeps", "WorldMetrics": "warpsim.sweeps",
    "rerun_world": "warpsim.sweeps", "OccupancyRecord": "warpsim.browse", "OccupancyRecorder": "warpsim.browse",
    "Region": "warpsim.browse", "answer_region": "warpsim.browse", "parse_region": "warpsim.browse",
    "pick_world": "warpsim.browse",
}
"""Names that moved to :mod:`warpsim.sweeps` / :mod:`warpsim.browse` in the split: name -> package."""


def __getattr__(name):
    """``warpsim.worlds.run_batch`` and the other moved names, from their new package."""
    if name in _MOVED:
        import importlib

        return getattr(importlib.import_module(_MOVED[name]), name)
    raise AttributeError(f"module 'warpsim.worlds' has no attribute {name!r}")
