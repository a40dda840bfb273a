"""Sweeps: many worlds of one scene sampled, run in batches (:mod:`warpsim.worlds`), measured and
picked (``warpsim sweep``, ``warpsim query``), a picked world re-run alone bit for bit.

Modules:
  sampling  ``--vary`` specs and the grid / random / Latin-hypercube plans (seeded)
  sweep     :func:`sample_worlds`, :func:`run_batch`, :func:`write_table`: the sweep driver
  metrics   per-world metrics on the device (centre of mass, peak speed, kinetic energy, tracked
            particles, user ``@wp.func`` metrics), ``--rank`` / ``--where`` picking
  usd       batch layers (``/Worlds/world_GGGGGG``, each prim declared once in ``/WorldShared``,
            springs stored as their particles' points); the root over them is
            :mod:`warpsim.browse.roots`
  staging   where a sweep writes while it runs (temporary names, chunks, ``--resume``) and the swap
            that publishes it
  preflight checks of a sweep request (seed, memory, disk, paths, picking options) before any simulation
  rerun     one world of a sweep re-run alone, bit for bit (``--from-sweep``, ``--rerun``,
            :func:`rerun_world`); the sweep's manifest ``<stem>.sweep.json``
  command   ``warpsim sweep``
  query_command  ``warpsim query``: pick a finished sweep's worlds from its table and occupancy
            record (:mod:`warpsim.browse.query`)

Entry points (the command line and the Ray driver ``warpsim.distributed`` both use them, so a
Ray sweep and a single-process sweep give the same table and samples): :func:`sample_worlds`,
:func:`run_batch`, :func:`write_sweep_root` (from :mod:`warpsim.browse.roots`),
:func:`write_table`; :class:`UserMetric`.
"""
from ..browse.roots import write_sweep_root
from .metrics import UserMetric, WorldMetrics
from .rerun import rerun_world
from .sweep import run_batch, sample_worlds, write_table

__all__ = ["UserMetric", "WorldMetrics", "rerun_world", "run_batch", "sample_worlds", "write_sweep_root",
           "write_table"]
