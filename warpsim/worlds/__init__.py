"""Many worlds: N variants of one scene stepped together in one model, browsed as USD variants and
picked by their outcome (``warpsim sweep``).

Modules:
  sampling  ``--vary`` specs and the grid / random / Latin-hypercube plans (seeded)
  plan      how a varied parameter enters one world's arrays, found by building the scene a few times
  batch     :class:`WorldBatch`: world 0 tiled on the device into N worlds (``kernels/worlds.py``:
            tile_*, per-world gravity, blow-up flags and freezing), stepped by the scene's own
            simulator class, one launch per stage for all worlds (``fused=True``: the cloth
            solver's fused semi-implicit kernel); particle-pair and agent neighbour grids are
            keyed by world (``kernels/worlds.py: world_key``)
  agents    :class:`AgentWorldBatch`: flocks (``flock``, ``school``) as one Flock with world-keyed
            neighbours and per-world food
  forces    :class:`WorldGravity`, :class:`WorldPlanes` (per-world gravity, wall restitution and
            friction; ``kernels/collide.py: collide_planes_worlds``)
  metrics   per-world metrics on the device (centre of mass, peak speed, kinetic energy, tracked
            particles, user ``@wp.func`` metrics), ``--rank`` / ``--where`` picking
  usd       batch layers (``/Worlds/world_GGGGGG``) and the root: a ``world`` variant set or a grid
  occupancy per-world occupancy records made on the device during a sweep (``kernels/occupancy.py``:
            grid cells per frame as bits, bit-packed over time; exact positions of few particles)
  query     IN / NOT IN a box during a window over a record (``--inside`` / ``--outside``)
  roots     reading a sweep root back: its worlds, batch layers, table and record
  sweep     :func:`sample_worlds`, :func:`run_batch`, :func:`write_table`
  shared    the shared-topology path of a batch (the default for mass-spring scenes): springs stored
            once, one fused kernel per sub-step (``kernels/world_step.py``)
  rerun     one world of a sweep re-run alone, bit for bit (``--from-sweep``, ``--rerun``,
            :func:`rerun_world`); the sweep's manifest ``<stem>.sweep.json``
  command   ``warpsim sweep``
  query_command  ``warpsim query``: ask a finished sweep's record
  pick      ``warpsim pick``: one world as a file any USD tool opens
  gallery   ``warpsim view SWEEP.usda``: the worlds side by side in the browser, click one to
            isolate it (imports the viewer; not imported by this package)

Entry points (the command line and the Ray driver ``warpsim.distributed`` both use them, so a
Ray sweep and a single-process sweep give the same table and samples): :func:`sample_worlds`,
:func:`run_batch`, :func:`write_sweep_root`, :func:`write_table`; classes :class:`WorldBatch`,
:class:`UserMetric`.
"""
from .batch import WorldBatch
from .metrics import UserMetric, WorldMetrics
from .occupancy import OccupancyRecord, OccupancyRecorder
from .pick import pick_world
from .query import Region, answer_region, parse_region
from .rerun import rerun_world
from .sweep import run_batch, sample_worlds, write_table
from .usd import write_sweep_root

__all__ = ["OccupancyRecord", "OccupancyRecorder", "Region", "UserMetric", "WorldBatch", "WorldMetrics",
           "answer_region", "parse_region", "pick_world", "rerun_world", "run_batch", "sample_worlds",
           "write_sweep_root", "write_table"]
