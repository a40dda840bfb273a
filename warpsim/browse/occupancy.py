"""Occupancy records: where each world's particles go, kept during a sweep and asked later.

After Goel & James, *Unified Many-Worlds Browsing of Arbitrary Physics-Based Animations*
(SIGGRAPH 2022): simulate once, keep per world a compact record of which space it occupies over
time, then answer "inside this box during this window" (IN) and "never inside" (NOT IN) for
any box drawn later without simulating again (:mod:`warpsim.browse.query`).

The record (``OccupancyRecorder``, made on the device while the sweep runs; kernels in
``kernels/occupancy.py``):

- a grid of cubic cells of side ``h`` [m] over the scene's bounds (``bounds``, default: the
  worlds' frame-0 extent and the scene's static geometry (floor, walls), padded by a quarter of
  its largest side on every side), ``resolution`` cells
  along its longest side, plus one outside layer per side that catches everything beyond;
- per world and occupied cell, the frames it is occupied, bit-packed over time (32 frames a
  word): the pairs (world, cell) are sorted by world then cell (a CSR by world), so a record
  costs 4 + 4 ceil(F / 32) bytes per occupied cell and world;
- when each world records at most ``exact_max`` particles (``--track``, or a small scene), their
  exact positions per frame too (float32), so answers are exact, not only to a cell.

Written as ``<stem>.occupancy.npz`` beside the sweep's table (NumPy's zip of arrays, no
pickles): ``format`` ("warpsim-occupancy 1"), ``version`` (warpsim), ``scene``, ``lo`` [m],
``cell_size`` [m], ``dims`` (cells per axis with the outside layers), ``fps``, ``first_frame``,
``frame_count``, ``first_world``, ``world_count``, ``world_particle_count``, ``particles``
(recorded indices within a world), ``track_names``, ``world_start`` (W + 1), ``pair_cell``,
``pair_bits`` (pairs x words, uint32; bit f % 32 of word f // 32 = frame first_frame + f) and,
when exact, ``samples`` (W, F, K, 3) float32 [m]. Everything is integer OR or a copy: two runs of
the same sweep write the same record.
"""
from __future__ import annotations

import math
import os
import time

import numpy as np
import warp as wp

from ..core.safe_files import open_temporary
from ..kernels import occupancy as KO

__all__ = ["DEFAULT_RESOLUTION", "OccupancyGrid", "OccupancyRecord", "OccupancyRecorder", "occupancy_path",
           "parse_bounds"]

FORMAT = "warpsim-occupancy 1"
DEFAULT_RESOLUTION = 16
EXACT_MAX = 8
"""Recorded particles per world up to which exact positions are kept."""
SAMPLE_BYTES_MAX = 1 << 30
BLOCK_BYTES_MAX = 1 << 30
"""Device bytes of a batch's 32-frame block (world_count x cells x 4) above which the recorder
halves the resolution until it fits (the record then states the coarser cells)."""


def occupancy_path(root_or_table) -> str:
    """The record kept beside a sweep root or its table: ``<stem>.occupancy.npz``."""
    return os.path.splitext(os.path.abspath(os.fspath(root_or_table)))[0] + ".occupancy.npz"


def parse_bounds(text, what="--occupancy-bounds"):
    """(lo, hi) float64 (3,) each from ``"x0,y0,z0,x1,y1,z1"`` [m]; ValueError naming the problem."""
    parts = [p.strip() for p in str(text).split(",")]
    if len(parts) != 6:
        raise ValueError(f"{what} {text!r}: give six numbers x0,y0,z0,x1,y1,z1 [m] (two corners of a box)")
    try:
        v = np.array([float(p) for p in parts])
    except ValueError:
        raise ValueError(f"{what} {text!r}: {next(p for p in parts if not _is_float(p))!r} is not a number") \
            from None
    if not np.isfinite(v).all():
        raise ValueError(f"{what} {text!r}: the corners must be finite numbers")
    lo, hi = v[:3], v[3:]
    for a, name in enumerate("xyz"):
        if hi[a] < lo[a]:
            raise ValueError(f"{what} {text!r}: {name}1 = {hi[a]:g} < {name}0 = {lo[a]:g}; give the lower corner "
                             "first (x0,y0,z0 <= x1,y1,z1)")
    return lo, hi


def _is_float(s):
    try:
        float(s)
    except ValueError:
        return False
    return True


def find_source_prim(frame_data, positions, particles) -> str:
    """The name of a prim in one world's ``frame_data`` ({prim: {"points": ...}}) whose points hold
    ``positions[particles]`` (one world's particle positions (P, 3)) at the same indices, bit for
    bit; ``""`` when none does (then answers cannot be refined from the cache)."""
    local = np.asarray(particles, np.int64)
    want = np.asarray(positions, np.float32)[local]
    for name in sorted(frame_data):
        points = (frame_data[name] or {}).get("points")
        if points is None:
            continue
        points = np.asarray(points.numpy() if hasattr(points, "numpy") else points, np.float32)
        if points.ndim == 2 and points.shape[1] == 3 and len(points) > int(local.max(initial=-1)) and \
                np.array_equal(points[local], want):
            return str(name)
    return ""


class OccupancyGrid:
    """Cubic cells of side ``cell_size`` [m] from ``lo`` [m]; ``dims`` cells per axis including
    one outside layer on each side (inner cells: ``dims - 2``)."""

    def __init__(self, lo, cell_size, dims):
        self.lo = np.asarray(lo, dtype=np.float64).reshape(3)
        self.cell_size = float(cell_size)
        self.dims = np.asarray(dims, dtype=np.int64).reshape(3)
        if not (self.cell_size > 0 and math.isfinite(self.cell_size)) or (self.dims < 3).any():
            raise ValueError(f"occupancy grid: cell size {cell_size} must be > 0 and dims {dims} >= 3")

    @classmethod
    def over(cls, lo, hi, resolution=DEFAULT_RESOLUTION):
        """A grid over the box lo..hi [m] with ``resolution`` cells along its longest side."""
        lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
        resolution = int(resolution)
        if resolution < 1:
            raise ValueError(f"occupancy resolution {resolution}: it must be >= 1 (cells along the longest side)")
        if resolution > 256:
            raise ValueError(f"occupancy resolution {resolution}: at most 256 cells a side (the record grows as its "
                             "cube)")
        extent = float(np.max(hi - lo))
        h = extent / resolution if extent > 0 else 1.0
        inner = np.maximum(1, np.ceil((hi - lo) / h - 1e-9)).astype(np.int64)
        return cls(lo, h, inner + 2)

    @property
    def hi(self):
        return self.lo + self.cell_size * (self.dims - 2)

    @property
    def cell_count(self) -> int:
        return int(np.prod(self.dims))

    def cells_of(self, points):
        """Cell index of each point (N, 3) [m] (NumPy reference of ``kernels/occupancy.grid_cell``)."""
        p = np.asarray(points, np.float32).reshape(-1, 3)
        s = np.floor((p - self.lo.astype(np.float32)) * np.float32(1.0 / self.cell_size)) + 1
        c = np.clip(s, 0, (self.dims - 1)).astype(np.int64)
        return (c[:, 0] * self.dims[1] + c[:, 1]) * self.dims[2] + c[:, 2]

    def box_cells(self, lo, hi):
        """Boolean (cell_count,): the cells a box lo..hi [m] may touch, widened by float32
        rounding so a point inside the box is never binned outside the range."""
        lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
        eps = 4 * float(np.finfo(np.float32).eps) * (np.abs(np.concatenate([lo, hi])).max() + np.abs(self.lo).max()
                                                     + self.cell_size)
        i0 = np.clip(np.floor((lo - eps - self.lo) / self.cell_size) + 1, 0, self.dims - 1).astype(np.int64)
        i1 = np.clip(np.floor((hi + eps - self.lo) / self.cell_size) + 1, 0, self.dims - 1).astype(np.int64)
        mask = np.zeros(tuple(self.dims), dtype=bool)
        mask[i0[0]:i1[0] + 1, i0[1]:i1[1] + 1, i0[2]:i1[2] + 1] = True
        return mask.reshape(-1)


def default_bounds(points):
    """The worlds' extent (points (N, 3) [m], finite) padded by a quarter of its largest side (at
    least 5 cm) on every side."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    p = p[np.isfinite(p).all(1)]
    if not len(p):
        return np.full(3, -1.0), np.full(3, 1.0)
    lo, hi = p.min(0), p.max(0)
    pad = max(0.25 * float(np.max(hi - lo)), 0.05)
    return lo - pad, hi + pad


class OccupancyRecord:
    """A loaded or finished record (see the module docstring for the fields)."""

    def __init__(self, *, grid, fps, first_frame, frame_count, first_world, world_count, world_particle_count,
                 particles, track_names, world_start, pair_cell, pair_bits, samples=None, scene="", version="",
                 source_prim=""):
        self.grid = grid
        self.fps = float(fps)
        self.first_frame, self.frame_count = int(first_frame), int(frame_count)
        self.first_world, self.world_count = int(first_world), int(world_count)
        self.world_particle_count = int(world_particle_count)
        self.particles = np.asarray(particles, np.int64)
        self.track_names = [str(n) for n in track_names]
        self.world_start = np.asarray(world_start, np.int64)
        self.pair_cell = np.asarray(pair_cell, np.uint32)
        self.pair_bits = np.asarray(pair_bits, np.uint32).reshape(len(self.pair_cell), -1)
        self.pair_world = np.repeat(np.arange(self.world_count, dtype=np.int64), np.diff(self.world_start))
        self.samples = None if samples is None else np.asarray(samples, np.float32)
        self.scene, self.version = str(scene), str(version)
        self.source_prim = str(source_prim)
        """The animated prim of each world whose cached points hold the recorded particles at
        their indices (``""``: none found), so answers can be refined from the cache."""

    @property
    def exact(self) -> bool:
        """Whether exact positions are kept (answers exact rather than to one cell)."""
        return self.samples is not None

    @property
    def duration(self) -> float:
        """Time [s] of the last recorded frame (frame f at f / fps)."""
        return (self.first_frame + self.frame_count - 1) / self.fps

    def occupied_bounds(self):
        """(lo, hi) [m] of the grid's inner cells that some world occupies at some frame (the
        grid's own bounds when none is): where things go, for framing pictures and boxes."""
        dims = self.grid.dims
        c = np.stack(np.unravel_index(np.unique(self.pair_cell).astype(np.int64), tuple(dims)), axis=1)
        c = c[((c >= 1) & (c <= dims - 2)).all(axis=1)]
        if not len(c):
            return self.grid.lo.copy(), self.grid.hi.copy()
        return self.grid.lo + (c.min(0) - 1) * self.grid.cell_size, self.grid.lo + c.max(0) * self.grid.cell_size

    def nbytes(self) -> int:
        """Bytes of the record's arrays (what a query reads)."""
        return int(self.pair_cell.nbytes + self.pair_bits.nbytes + self.world_start.nbytes
                   + (self.samples.nbytes if self.samples is not None else 0))

    def save(self, path) -> str:
        path = os.path.abspath(os.fspath(path))
        os.makedirs(os.path.dirname(path), exist_ok=True)
        from .._version import __version__

        arrays = dict(format=np.array(FORMAT), version=np.array(__version__), scene=np.array(self.scene),
                      lo=self.grid.lo, cell_size=np.array(self.grid.cell_size), dims=self.grid.dims,
                      fps=np.array(self.fps), first_frame=np.array(self.first_frame),
                      frame_count=np.array(self.frame_count), first_world=np.array(self.first_world),
                      world_count=np.array(self.world_count),
                      world_particle_count=np.array(self.world_particle_count), particles=self.particles,
                      track_names=np.array(self.track_names, dtype=str).reshape(-1),
                      world_start=self.world_start, pair_cell=self.pair_cell, pair_bits=self.pair_bits,
                      source_prim=np.array(self.source_prim))
        if self.samples is not None:
            arrays["samples"] = self.samples
        tmp = path + ".tmp.npz"
        try:
            with open_temporary(tmp, "wb") as f:  # never through a planted link
                np.savez(f, **arrays)
        except OSError as exc:
            raise PermissionError(f"could not write the occupancy record {path}: {exc.strerror or exc}; choose a "
                                  "writable --out") from None
        os.replace(tmp, path)
        return path

    @classmethod
    def load(cls, path):
        """Read a record; FileNotFoundError / ValueError (one line) for a missing or foreign file."""
        path = os.fspath(path)
        if not os.path.exists(path):
            raise FileNotFoundError(f"no occupancy record {path}; run the sweep again with this warpsim (sweeps "
                                    "write <stem>.occupancy.npz beside their table)")
        from ..usd.pxr_errors import DamagedFileError

        if not os.path.isfile(path):  # a FIFO would block np.load for ever
            raise ValueError(f"occupancy record {path} is not a regular file (a pipe, socket or folder); give the "
                             "sweep's <stem>.occupancy.npz")
        import zipfile

        try:
            z = np.load(path, allow_pickle=False)
            if str(z["format"]) != FORMAT:
                raise ValueError(f"format {str(z['format'])!r}")
            _check_record_fields(z, path)
            grid = OccupancyGrid(z["lo"], float(z["cell_size"]), z["dims"])
            return cls(grid=grid, fps=float(z["fps"]), first_frame=int(z["first_frame"]),
                       frame_count=int(z["frame_count"]), first_world=int(z["first_world"]),
                       world_count=int(z["world_count"]), world_particle_count=int(z["world_particle_count"]),
                       particles=z["particles"], track_names=list(z["track_names"]), world_start=z["world_start"],
                       pair_cell=z["pair_cell"], pair_bits=z["pair_bits"],
                       samples=z["samples"] if "samples" in z.files else None, scene=str(z["scene"]),
                       version=str(z["version"]),
                       source_prim=str(z["source_prim"]) if "source_prim" in z.files else "")
        except DamagedFileError:
            raise
        except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile) as exc:
            size = os.path.getsize(path)
            what = "is empty (0 bytes)" if size == 0 else \
                f"is damaged or not a warpsim occupancy record ({size} bytes; {type(exc).__name__}: {str(exc)[:80]})"
            raise DamagedFileError(f"occupancy record {path} {what}; run the sweep again") from None

    def describe(self) -> str:
        inner = "x".join(str(int(d) - 2) for d in self.grid.dims)
        what = (f"tracked particles {', '.join(self.track_names)}" if self.track_names else
                f"{len(self.particles)} particle(s) per world")
        return (f"occupancy record: {self.world_count} worlds x {self.frame_count} frames at {self.fps:g} fps, "
                f"{inner} cells of {self.grid.cell_size:.4g} m over [{', '.join(f'{v:.4g}' for v in self.grid.lo)}]"
                f"..[{', '.join(f'{v:.4g}' for v in self.grid.hi)}] m, {what}, "
                f"{'exact positions kept' if self.exact else 'answers conservative to one cell'}"
                f"{f', refined from the cached {self.source_prim} points where cheap' if self.source_prim and not self.exact else ''}")


def _check_record_fields(z, path) -> None:
    """DamagedFileError naming ``path`` and the field when a record's arrays do not fit together
    (a zero frame rate, a cell outside the grid, pairs that do not match the CSR, ...)."""
    from ..usd.pxr_errors import DamagedFileError

    def bad(field, why):
        raise DamagedFileError(f"occupancy record {path}: field {field!r} {why}; the record is damaged: run the "
                               "sweep again")

    def scalar(field, low, kind=int):
        a = np.asarray(z[field])
        if a.ndim != 0 or not np.issubdtype(a.dtype, np.number) or not math.isfinite(float(a)):
            bad(field, f"is {a.tolist()!r}, not one finite number")
        value = kind(a)
        if value < low or (kind is int and value != float(a)):
            bad(field, f"is {a.tolist()!r}, not {'a whole number' if kind is int else 'a number'} >= {low}")
        return value

    fps = scalar("fps", 0.0, float)
    if fps <= 0.0:
        bad("fps", f"is {fps!r}, not a rate > 0 [frames/s]")
    cell = scalar("cell_size", 0.0, float)
    if cell <= 0.0:
        bad("cell_size", f"is {cell!r}, not a length > 0 [m]")
    scalar("first_frame", 0)
    frames = scalar("frame_count", 1)
    scalar("first_world", 0)
    worlds = scalar("world_count", 1)
    per_world = scalar("world_particle_count", 0)
    lo = np.asarray(z["lo"])
    if lo.shape != (3,) or not np.isfinite(lo.astype(np.float64)).all():
        bad("lo", f"is {lo.tolist()!r}, not 3 finite coordinates [m]")
    dims = np.asarray(z["dims"])
    if dims.shape != (3,) or not np.issubdtype(dims.dtype, np.integer) or (dims < 3).any():
        bad("dims", f"is {dims.tolist()!r}, not 3 whole numbers >= 3")
    cells = int(np.prod(dims.astype(np.int64)))
    start = np.asarray(z["world_start"])
    pairs = np.asarray(z["pair_cell"])
    if start.shape != (worlds + 1,) or not np.issubdtype(start.dtype, np.integer) or start[0] != 0 \
            or (np.diff(start) < 0).any():
        bad("world_start", f"does not hold {worlds + 1} rising offsets from 0 (world_count {worlds})")
    if pairs.ndim != 1 or not np.issubdtype(pairs.dtype, np.integer) or len(pairs) != int(start[-1]):
        bad("pair_cell", f"holds {pairs.size} entries, world_start ends at {int(start[-1])}")
    if len(pairs) and int(pairs.max()) >= cells:
        bad("pair_cell", f"names cell {int(pairs.max())}, outside the grid's {cells} cells")
    bits = np.asarray(z["pair_bits"])
    words = max(1, (frames + 31) // 32)
    if bits.size != len(pairs) * words:
        bad("pair_bits", f"holds {bits.size} words, {len(pairs)} pairs x {words} words for {frames} frames expected")
    particles = np.asarray(z["particles"])
    if particles.ndim != 1 or len(particles) and (not np.issubdtype(particles.dtype, np.integer) or
                                                  particles.min() < 0 or particles.max() >= max(per_world, 1)):
        bad("particles", f"are not indices within a world of {per_world} particles")
    if "samples" in z.files:
        samples = np.asarray(z["samples"])
        if samples.shape != (worlds, frames, len(particles), 3):
            bad("samples", f"has shape {samples.shape}, ({worlds}, {frames}, {len(particles)}, 3) expected")


class OccupancyRecorder:
    """Records a batch's occupancy on its device, frame by frame.

    ``batch``: a :class:`warpsim.worlds.batch.WorldBatch` (``sim.state.positions``,
    ``model.world_particle_count``, ``world_count``, ``device``); ``frames``: frames after frame 0;
    ``particles``: indices within a world to record (None: all); ``bounds``: (lo, hi) [m] (None:
    :func:`default_bounds` of frame 0 and of the corners ``include`` (lo, hi) [m], e.g. the
    scene's static geometry: floor, walls); ``resolution``: cells along the longest side;
    ``exact_max``: keep exact positions when at most this many particles per world are recorded.
    :meth:`update` launches kernels only (capture-safe); call it for frame 0 and after every
    frame, then :meth:`after_frame` on the host, then :meth:`finish`.

    ``in_step`` (default): when the batch steps on the shared-topology path and every particle is
    recorded without exact positions, the stepping kernel itself marks the cells at each frame's
    last sub-step (``kernels/occupancy.py: CellMarks``) from frame 1 on, so :meth:`update` reads
    no positions; the record is the same bit for bit. Every 32 frames the block's occupied words
    are compacted on the device and only those move to the host, where a thread merges them into
    the record's pairs while the next frames step. ``host_seconds`` sums the host time of the
    flushes (``flush``) and of :meth:`finish` (``finish``, which waits for the last merge)."""

    def __init__(self, batch, frames, *, particles=None, track_names=(), bounds=None,
                 resolution=DEFAULT_RESOLUTION, exact_max=EXACT_MAX, fps=60.0, first_world=0, scene="",
                 include=None, in_step=True):
        self.device = batch.device
        n, P = batch.world_count, batch.model.world_particle_count
        self.batch = batch
        local = np.arange(P) if particles is None else np.asarray(particles, np.int64).reshape(-1)
        if len(local) and (local.min() < 0 or local.max() >= P):
            raise ValueError(f"recorded particle {int(local.max())} is out of range [0, {P}) for one world")
        if bounds is None:
            x = batch.sim.state.positions.numpy().reshape(n, P, 3)[:, local].reshape(-1, 3)
            if include is not None:
                x = np.concatenate([x, np.asarray(include, np.float64).reshape(-1, 3)])
            bounds = default_bounds(x)
        resolution = int(resolution)
        self.grid = OccupancyGrid.over(bounds[0], bounds[1], resolution)
        while n * self.grid.cell_count * 4 > BLOCK_BYTES_MAX and resolution > 2:
            resolution //= 2
            self.grid = OccupancyGrid.over(bounds[0], bounds[1], resolution)
        self.resolution = resolution
        self.frame_count = int(frames) + 1
        self.world_count, self.world_particle_count = n, P
        self.local = wp.array(local.astype(np.int32), dtype=int, device=self.device)
        self.block = wp.zeros(n * self.grid.cell_count, dtype=wp.uint32, device=self.device)
        self.cell_hit = wp.zeros(n * self.grid.cell_count, dtype=wp.uint8, device=self.device)
        self.frame = wp.zeros(1, dtype=int, device=self.device)
        exact = len(local) <= int(exact_max) and n * self.frame_count * len(local) * 12 <= SAMPLE_BYTES_MAX
        self.samples = wp.zeros(n * self.frame_count * len(local) if exact else 0, dtype=wp.vec3, device=self.device)
        self.fps, self.first_world, self.scene = float(fps), int(first_world), str(scene)
        self.particles, self.track_names = local, list(track_names)
        self.source_prim = ""
        """Set by the sweep (:func:`find_source_prim`): the prim whose cached points hold the
        recorded particles."""
        self._keys = np.zeros(0, np.int64)  # the sorted keys world * cell_count + cell flushed so far
        self._bits = np.zeros((0, max(1, (self.frame_count + 31) // 32)), np.uint32)  # their words
        self._merging: list = []  # the flushes' merges, run one after another beside the stepping
        self._merger = None
        self._seen = 0
        g = self.grid
        self._args = (wp.vec3(*g.lo.astype(np.float32)), float(np.float32(1.0 / g.cell_size)),
                      wp.vec3i(*(int(d) for d in g.dims)))
        self.stepper = getattr(batch, "stepper", None)
        self.in_step = bool(in_step) and self.stepper is not None and not exact and len(local) == P and \
            np.array_equal(local, np.arange(P)) and hasattr(batch, "world_blown_frame")
        """Whether the stepping kernel marks the cells (see the class docstring)."""
        self._marking = False  # the stepper marks (set after frame 0's update)
        self.marks = KO.CellMarks()
        self.marks.lo, self.marks.inv_h, self.marks.dims = self._args
        self.marks.cell_hit, self.marks.bits, self.marks.frame = self.cell_hit, self.block, self.frame
        self._counts = wp.zeros(n + 1, dtype=int, device=self.device)
        self._start = wp.zeros(n + 1, dtype=int, device=self.device)
        self._cells_out = wp.zeros(0, dtype=wp.uint32, device=self.device)
        self._words_out = wp.zeros(0, dtype=wp.uint32, device=self.device)
        self.host_seconds = {"flush": 0.0, "finish": 0.0, "merge_wait": 0.0}
        self.flushed_bytes = 0
        """Bytes moved from the device to the host by the flushes so far."""

    def update(self):
        """Mark the current frame's cells (kernels only). In-step (after frame 0): fold the marks
        the step made (the block-per-world kernel folded them itself) and redo worlds frozen at
        this frame."""
        lo, inv_h, dims = self._args
        K = int(self.local.shape[0])
        if self._marking:
            if not self.stepper.block_per_world:
                wp.launch(KO.fold_cell_hits, self.cell_hit.shape[0], inputs=[self.cell_hit, self.frame, self.block],
                          device=self.device)
            b = self.batch
            wp.launch(KO.redo_blown_worlds, self.world_count,
                      inputs=[b.sim.state.positions, self.world_particle_count, b.world_blown_frame, b.frame_counter,
                              lo, inv_h, dims, self.frame, self.block], device=self.device)
        elif K:
            wp.launch(KO.record_cells, (self.world_count, K),
                      inputs=[self.batch.sim.state.positions, self.world_particle_count, self.local, lo, inv_h, dims,
                              self.frame, self.frame_count, self.cell_hit, self.samples], device=self.device)
            wp.launch(KO.fold_cell_hits, self.cell_hit.shape[0], inputs=[self.cell_hit, self.frame, self.block],
                      device=self.device)
        wp.launch(KO.next_record_frame, 1, inputs=[self.frame], device=self.device)
        if self.in_step and not self._marking:  # from the next frame on, the step marks the cells
            self.stepper.marks = self.marks
            self._marking = True

    def after_frame(self):
        """Host side after each :meth:`update`: every 32 frames the block's bits move to the host."""
        self._seen += 1
        if self._seen % 32 == 0:
            self._flush()

    def _flush(self):
        """The block's nonzero words, compacted on the device (world by world, in cell order), move
        to the host as sorted keys (world * cell_count + cell) and words; the block is cleared."""
        t0 = time.perf_counter()
        n, cells, d = self.world_count, self.grid.cell_count, self.device
        wp.launch(KO.count_world_words, n, inputs=[self.block, cells, self._counts], device=d)
        wp.utils.array_scan(self._counts, self._start, inclusive=True)
        start = self._start.numpy()
        total = int(start[n])
        if total > self._cells_out.shape[0]:
            size = max(total, 2 * self._cells_out.shape[0])
            self._cells_out = wp.empty(size, dtype=wp.uint32, device=d)
            self._words_out = wp.empty(size, dtype=wp.uint32, device=d)
        wp.launch(KO.take_world_words, n, inputs=[self.block, cells, self._start, self._cells_out, self._words_out],
                  device=d)
        # copies (on the CPU device numpy() is a view of buffers the next flush overwrites)
        cell = np.array(self._cells_out[:total].numpy()) if total else np.zeros(0, np.uint32)
        words = np.array(self._words_out[:total].numpy()) if total else np.zeros(0, np.uint32)
        world = np.repeat(np.arange(n, dtype=np.int64), np.diff(start))
        if self._merger is None:
            from concurrent.futures import ThreadPoolExecutor

            self._merger = ThreadPoolExecutor(max_workers=1, thread_name_prefix="warpsim-occupancy")
        self._merging.append(self._merger.submit(self._merge, (self._seen - 1) // 32, world * cells + cell, words))
        self.flushed_bytes += start.nbytes + 8 * total
        self.host_seconds["flush"] += time.perf_counter() - t0

    def _merge(self, block, keys, words):
        """Add one flush's sorted ``keys`` and their ``words`` (32-frame block ``block``) to the
        record's pairs (a host thread: it runs while the next frames step)."""
        old = self._keys
        at = np.searchsorted(old, keys)
        known = at < len(old)
        known[known] = old[at[known]] == keys[known]
        width = max(self._bits.shape[1], block + 1)
        if width != self._bits.shape[1]:
            self._bits = np.pad(self._bits, ((0, 0), (0, width - self._bits.shape[1])))
        if not known.all():  # insert the new keys in order (both arrays are sorted: no sort needed)
            new = keys[~known]
            where = np.searchsorted(old, new)
            self._keys = np.insert(old, where, new)
            self._bits = np.insert(self._bits, where, 0, axis=0)
        self._bits[np.searchsorted(self._keys, keys), block] = words

    def finish(self) -> OccupancyRecord:
        if self._seen % 32:
            self._flush()
        if self.stepper is not None and self.stepper.marks is self.marks:
            self.stepper.marks = None
        t0 = time.perf_counter()
        frame_count = self._seen
        nwords = max(1, (frame_count + 31) // 32)
        for merge in self._merging:  # the last flush's merge, the others long done
            merge.result()
        if self._merger is not None:
            self._merger.shutdown()
            self._merger = None
        self._merging = []
        self.host_seconds["merge_wait"] = time.perf_counter() - t0
        keys, bits = self._keys, np.ascontiguousarray(self._bits[:, :nwords])
        if bits.shape[1] < nwords:
            bits = np.pad(bits, ((0, 0), (0, nwords - bits.shape[1])))
        cells = self.grid.cell_count
        world = keys // cells
        start = np.searchsorted(world, np.arange(self.world_count + 1)).astype(np.int64)
        samples = None
        K = len(self.particles)
        if self.samples.shape[0]:
            samples = self.samples.numpy().reshape(self.world_count, self.frame_count, K, 3)[:, :frame_count]
        record = OccupancyRecord(grid=self.grid, fps=self.fps, first_frame=0, frame_count=frame_count,
                                 first_world=self.first_world, world_count=self.world_count,
                                 world_particle_count=self.world_particle_count, particles=self.particles,
                                 track_names=self.track_names, world_start=start,
                                 pair_cell=(keys % cells).astype(np.uint32), pair_bits=bits, samples=samples,
                                 scene=self.scene, source_prim=self.source_prim)
        self.host_seconds["finish"] += time.perf_counter() - t0
        return record
