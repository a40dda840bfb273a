"""Browsing a sweep's worlds: the files a sweep leaves (its root, occupancy record) read back and
asked, one world picked as a file, the worlds side by side in the browser.

Modules:
  roots     the sweep root: written over the batch layers (:func:`write_sweep_root`, a ``world``
            variant set or a grid) and read back (its worlds, batch layers, table and record)
  occupancy per-world occupancy records made on the device during a sweep (``kernels/occupancy.py``:
            grid cells per frame as bits, bit-packed over time; exact positions of few particles)
  query     IN / NOT IN a box during a window over a record (``--inside`` / ``--outside``)
  pick      ``warpsim pick``: one world as a file any USD tool opens (:func:`pick_world`)
  panel     thumbnails and the spacetime query panel of the gallery
  gallery   ``warpsim view SWEEP.usda``: the worlds side by side in the browser, click one to
            isolate it (imports the viewer; not imported by this package)

This package imports nothing from :mod:`warpsim.sweeps` (the sweeps write what it reads).
"""
from .occupancy import OccupancyRecord, OccupancyRecorder
from .pick import pick_world
from .query import Region, answer_region, parse_region
from .roots import write_sweep_root

__all__ = ["OccupancyRecord", "OccupancyRecorder", "Region", "answer_region", "parse_region", "pick_world",
           "write_sweep_root"]
