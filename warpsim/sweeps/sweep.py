"""A sweep: sample worlds, run them in batches, write the table; the functions the command line
and the Ray driver (``warpsim.distributed``) share, so both give the same worlds, samples and rows."""
from __future__ import annotations

import csv
import os

import numpy as np
import warp as wp

from ..core.safe_files import open_temporary

from ..scenes.timing import resolve_timing
from ..worlds.batch import WorldBatch
from .metrics import WorldMetrics
from .sampling import parse_vary, sample_params
from .usd import MAX_CHUNK_FRAMES, BatchLayerWriter, auto_chunk_frames, chunk_writers, world_frame_bytes

__all__ = ["make_batch", "normalise_params", "run_batch", "sample_worlds", "sweep_timing", "write_table"]


def _typed_fixed(cls, fixed):
    given = {}
    for key, value in (fixed or {}).items():
        given[key] = value
    resolved = cls.resolve_params(given)  # validates keys and parses strings
    return {k: resolved[k] for k in given}


def sample_worlds(scene_name, fixed, vary, n, sample="grid", seed=0) -> list:
    """One parameter dict per world: the ``fixed`` values (``--set``; typed values or strings)
    plus each world's sampled values of the ``vary`` specs (``"key=lo:hi[:log]"``,
    ``"key=a,b,c"``), ``n`` worlds by ``sample`` ("grid", "random", "lhs") from ``seed``.
    ValueError (one line) for an unknown key, lo > hi, a log range with a bound <= 0, n < 1."""
    from ..core import checks
    from ..scenes import get_scene
    from .preflight import check_worlds

    cls = get_scene(scene_name)
    if isinstance(vary, (str, bytes)) or not hasattr(vary, "__iter__"):
        raise TypeError(f"sample_worlds vary must be a list of specs, got {vary!r}; e.g. ['height=0.01:0.05']")
    if fixed is not None and not isinstance(fixed, dict):
        raise TypeError(f"sample_worlds fixed must be a dict {{key: value}} or None, got {checks.show(fixed)}")
    n = check_worlds(checks.integer(n, "sample_worlds n (worlds)", lo=1, fix="e.g. 64"))
    seed = checks.integer(seed, "sample_worlds seed", lo=0, hi=2**63 - 1, fix="e.g. 0")
    specs = [parse_vary(v, cls.params) for v in vary]
    fixed = _typed_fixed(cls, fixed)
    for s in specs:
        if s.key in fixed:
            raise ValueError(f"{s.key} is given both with --set and --vary; give it once")
    varied = sample_params(specs, cls.params, n, sample, seed)
    return [{**fixed, **v} for v in varied]


def sweep_timing(cls, world_params, fps=None, substeps=None):
    """The one :class:`~warpsim.scenes.timing.FrameTiming` of a sweep's worlds (``world_params``:
    one dict per world as given, or the first world's; the keys given are set by hand, a ``dt``
    among them too). ValueError (one line) for flags that disagree."""
    first = world_params if isinstance(world_params, dict) else world_params[0]
    return resolve_timing(cls, cls.resolve_params(first), fps=fps, substeps=substeps, given=tuple(first))


def timed_params(cls, world_params, timing) -> list:
    """The worlds' parameters with ``dt`` set to the step ``timing`` takes where it overrides the
    scene's dt (``--fps``, or ``--substeps N`` on a scene with a dt parameter), as run_batch does."""
    first = cls.resolve_params(world_params[0])
    if timing.scene_params(first) == first:
        return list(world_params)
    return [{**p, "dt": timing.frame_dt / timing.steps} for p in world_params]


def normalise_params(cls, params):
    """``params`` with list values of vector parameters as tuples (as the scene's defaults hold them)."""
    out = {}
    for k, v in params.items():
        default = cls.params[k].default if k in cls.params else None
        out[k] = tuple(v) if isinstance(default, (tuple, list)) and isinstance(v, list) else v
    return out


def make_batch(cls, world_params, device=None, fused=False, reference_params=None):
    """A :class:`WorldBatch` (``fused``, ``reference_params``: see there), or for flock scenes an
    :class:`warpsim.worlds.agents.AgentWorldBatch` (its worlds never depend on their batch)."""
    from ..worlds.batch import is_agent_scene

    if is_agent_scene(cls):
        from ..worlds.agents import AgentWorldBatch

        return AgentWorldBatch(cls, world_params, device=device)
    return WorldBatch(cls, world_params, device=device, fused=fused, reference_params=reference_params)


def run_batch(scene_name, world_params, *, frames, fps=None, substeps=None, device=None, layer_path, first_world=0,
              track=None, metrics=(), use_graph=None, progress=None, fused=False, occupancy=None,
              warn=None, timing=None, chunk_size=None, resume_frame=None, frame_steps=None,
              reference_params=None, store_every=1, on_stage=None, write_workers=None) -> list:
    """Step these worlds in one batched run and return one row per world.

    Writes every frame of every world into the USD layer ``layer_path`` (world i under
    ``/Worlds/world_GGGGGG``, G = first_world + i; see :mod:`warpsim.sweeps.usd`). Rows hold
    ``"world"`` (the global index), the world's parameters as given, the metrics of
    :mod:`warpsim.sweeps.metrics` and ``"blown_up"``. ``track``: {name: particle index within a
    world} for position metrics; ``metrics``: :class:`warpsim.sweeps.metrics.UserMetric` list;
    ``use_graph``: capture each frame as a CUDA graph (None: on CUDA devices when the scene allows);
    ``fused``: step through the fused semi-implicit kernel (:class:`WorldBatch`);
    ``chunk_size``: frames per chunk file of the layer (completed chunks survive a kill; None:
    :func:`warpsim.sweeps.usd.auto_chunk_frames`, 24 or fewer so a chunk holds at most 128 MiB);
    ``resume_frame``: keep the layer's completed chunks before this frame, re-simulate the frames
    before it without writing them (the run is bit-reproducible, so they come out the same) and
    write on from there;
    ``progress(frame)``: called after each frame; ``occupancy``: None, or {"path": record file,
    "resolution": cells along the longest side, "bounds": (lo, hi) [m] or None} to keep an
    occupancy record of these worlds (:mod:`warpsim.browse.occupancy`; the tracked particles
    when ``track`` is given, else every particle); ``substeps="auto"`` (or None for scenes that
    default to it, unless ``dt`` is given): each world takes the steps a frame its own run takes
    (``WorldBatch.world_steps``), so world N equals ``warpsim run SCENE --set ...`` with its
    parameters whichever worlds share its batch;
    ``warn(line)``: called once before the first frame when a world's step is
    above its stability limit (it may raise to stop the run); ``timing``: a dict that receives
    ``frame_steps``, the most steps any world took a frame (the batch's launches per frame; a
    world re-run alone needs it only when its worlds share one count, ``WorldBatch.own_counts``
    False); ``frame_steps``: for such scenes, every world takes this many steps a frame (the
    count resolved over the whole sweep, when these worlds are one block of it; other scenes
    ignore it: each world takes its own);
    ``reference_params``: the whole sweep's parameter list when these worlds are one block of it
    (:class:`WorldBatch`: each world then gets the arrays it gets in the whole sweep, bit for bit);
    ``on_stage(name)``: called as a stage after the frames starts ("closing the layer", "saving
    the occupancy record"), for a progress bar's label;
    ``store_every``: which frames the layer holds (``--store``): 1 every frame; k > 1 every k-th
    frame and the last (a preview: the layer's extent still covers every frame); 0 only the last
    (the frame the thumbnails show; ``layer_path`` is then a scratch layer);
    ``write_workers``: processes authoring the layer's chunk files while the worlds step on (None:
    :func:`warpsim.sweeps.usd.chunk_writers` picks by the chunks' size; 0: this process; the
    same bytes either way);
    ``occupancy["agree"]``: ``agree(points (M, 3) [m], resolution) -> (bounds, resolution)``, called
    with the frame-0 points the default grid would cover, so that the blocks of one sweep on
    several devices record on one grid (:mod:`warpsim.distributed.devices`)."""
    from ..scenes import get_scene

    from ..core import checks

    cls = get_scene(scene_name)
    frames = checks.integer(frames, "run_batch frames", lo=0, fix="frames after frame 0, e.g. 120")
    first_world = checks.integer(first_world, "run_batch first_world", lo=0, hi=999_999,
                                 fix="the global index of the batch's first world")
    world_params = list(world_params)
    for w, p in enumerate(world_params):
        if not isinstance(p, dict):
            raise TypeError(f"run_batch world_params[{w}] is {checks.show(p)}; give one dict of parameters per "
                            "world (sample_worlds makes them)")
    world_params = [normalise_params(cls, p) for p in world_params]
    given = [dict(p) for p in world_params]
    if not world_params:
        raise ValueError("run_batch needs at least one world")
    store_every = int(store_every)
    if store_every < 0:
        raise ValueError(f"store_every {store_every}: give 1 (every frame), k > 1 (every k-th) or 0 (the last only)")
    if resume_frame is not None and not 0 <= int(resume_frame) <= int(frames) + 1:
        raise ValueError(f"resume_frame {resume_frame}: the run has frames 0..{frames}")
    batch, (fps, substeps, frame_dt), counts = _timed_batch(cls, world_params, fps, substeps, device, fused,
                                                            reference_params, frame_steps, timing, warn)
    stats = WorldMetrics(batch, track=track, user=metrics, frame_dt=frame_dt, step_dt=frame_dt / np.asarray(counts))
    writer = _open_layer(batch, layer_path, scene_name, first_world, fps, frames, chunk_size, store_every,
                         write_workers, resume_frame)
    recorder = _recorder(batch, occupancy, frames, track, fps, first_world, scene_name, writer)
    for i, p in enumerate(getattr(batch, "params", given)):
        writer.set_world_params(i, p)
    writer.begin()  # adopts the kept chunks of a resumed layer (ValueError when one is damaged)

    def body():
        batch.advance(frame_dt, substeps)
        stats.update()
        if recorder is not None:
            recorder.update()

    stats.update()
    if recorder is not None:
        recorder.update()
        recorder.after_frame()
    write = _FrameWriter(batch, writer, frames, store_every, int(resume_frame or 0))
    _step_frames(batch, body, frames, write, recorder, progress,
                 batch.device.is_cuda and batch.can_capture() if use_graph is None else use_graph)
    if on_stage is not None:
        on_stage("closing the layer")
    writer.close(scene_name)
    if recorder is not None:
        if on_stage is not None:
            on_stage("saving the occupancy record")
        recorder.finish().save(occupancy["path"])
    return [{"world": int(first_world) + i, **p, **m} for i, (p, m) in enumerate(zip(given, stats.rows()))]


def _timed_batch(cls, world_params, fps, substeps, device, fused, reference_params, frame_steps, timing, warn):
    """(batch, (fps, substeps, frame_dt), steps each world takes a frame) of ``run_batch``: the
    one timing of every world, the batch built with it (``warn``: the stability line, if any)."""
    request = sweep_timing(cls, world_params, fps, substeps)  # the one FrameTiming of every world
    fps, substeps, frame_dt = request.fps, request.steps, request.frame_dt
    first = cls.resolve_params(world_params[0])
    if reference_params is not None:
        reference_params = [normalise_params(cls, p) for p in reference_params]
    if request.scene_params(first) != first:  # the step overrides dt (--fps, or --substeps N on a dt scene)
        world_params = [{**p, "dt": frame_dt / substeps} for p in world_params]
        if reference_params is not None:
            reference_params = [{**p, "dt": frame_dt / substeps} for p in reference_params]
    batch = make_batch(cls, world_params, device=device, fused=fused, reference_params=reference_params)
    stepped = getattr(batch, "batch_scene", None)  # flocks (AgentWorldBatch) step their own way
    if frame_steps is not None and not getattr(batch, "own_counts", False):  # worlds sharing one count: the sweep's
        request = request.with_steps(int(frame_steps))
    taken = batch.use_timing(request) if stepped is not None else request  # auto: the most any world needs
    if timing is not None:
        timing["frame_steps"] = int(taken.steps)
    counts = batch.world_steps(frame_dt, substeps) if stepped is not None else taken.steps  # each world's own
    if warn is not None and stepped is not None:
        line = batch.stability_warning(frame_dt, substeps)
        if line is not None:
            warn(line)
    return batch, (fps, substeps, frame_dt), counts


def _open_layer(batch, layer_path, scene_name, first_world, fps, frames, chunk_size, store_every, write_workers,
                resume_frame):
    """The batch layer's writer (not begun): chunks of ``chunk_size`` frames (None: automatic,
    :func:`warpsim.sweeps.usd.auto_chunk_frames`), ``write_workers`` processes (None: by size)."""
    from ..core import checks

    writer = BatchLayerWriter(layer_path, batch.scene, first_world, batch.world_count, fps,
                              chunk_size=MAX_CHUNK_FRAMES if chunk_size is None else chunk_size,
                              resume_frame=resume_frame)
    writer.scene_name = scene_name
    frame_bytes = world_frame_bytes(writer, batch)
    if chunk_size is None:  # (set before the writer begins: its layer records it) in frames, stored or not
        writer.chunk_size = auto_chunk_frames(frame_bytes) * max(int(store_every), 1)
    if write_workers is None:
        write_workers = chunk_writers(writer, frame_bytes, frames, store_every)
    writer.workers = checks.integer(write_workers, "run_batch write_workers", lo=0, hi=64,
                                    fix="0 (this process writes) or a few processes")
    return writer


class _FrameWriter:
    """``write(frame, ticket=None)``: a frame of every world to the layer (stored frames) or to its
    extent only (frames before ``first_written``, or not kept by ``store_every``)."""

    def __init__(self, batch, writer, frames, store_every, first_written):
        self.batch, self.writer, self.frames = batch, writer, int(frames)
        self.store_every, self.first_written = store_every, first_written

    def stored(self, frame):
        return frame == self.frames or (frame % self.store_every == 0 if self.store_every else False)

    def needed(self, frame) -> bool:
        """Whether frame ``frame`` must reach the host: every frame where the layer's extent covers
        them all (all, preview), only the last with ``store_every`` 0 (``--store none``: its scratch
        layer feeds the thumbnails, nothing else reads the frames)."""
        return bool(self.store_every) or frame == self.frames

    def __call__(self, frame, ticket=None):
        batch, writer = self.batch, self.writer
        x, v = batch.world_slices() if ticket is None else batch.world_slices(ticket)
        kept = frame >= self.first_written and self.stored(frame)
        batched = batch.batch_frame_data(x, v) if hasattr(batch, "batch_frame_data") else None
        if batched is not None:  # every world's samples at once (the scene's frame_arrays)
            writer.write_batch(frame, batched) if kept else writer.observe_batch(batched)
            return
        datas = [batch.world_frame_data(x[w], v[w], w) for w in range(batch.world_count)]
        writer.write_worlds(frame, datas) if kept else writer.observe(datas)


def _step_frames(batch, body, frames, write, recorder, progress, use_graph):
    """Frames 1..``frames``: ``body()`` (captured as a CUDA graph from frame 2 with ``use_graph``),
    then ``write(frame)``. On a GPU frame f is written while frame f + 1 steps: its copy to the
    host is started (pinned, double-buffered, on a copy stream) before the next frame is
    launched, and waited for after (:meth:`WorldBatch.start_host_copy`)."""
    if write.needed(0):
        write(0)
    ahead = getattr(batch, "can_copy_ahead", lambda: False)()
    graph, pending = None, None  # pending: (frame, ticket) of the frame copied and not yet written
    for frame in range(1, int(frames) + 1):
        if use_graph and graph is None and frame > 1:  # frame 1 ran eagerly: every module is loaded
            with wp.ScopedCapture(device=batch.device) as capture:
                body()
            graph = capture.graph
            wp.capture_launch(graph)  # capturing records the frame; this runs it
        elif graph is not None:
            wp.capture_launch(graph)
        else:
            body()
        if recorder is not None:
            recorder.after_frame()
        if not write.needed(frame):  # (--store none: only the last frame goes to the host)
            if progress is not None:
                progress(frame)
            continue
        done = (frame, batch.start_host_copy()) if ahead else (frame,)
        if ahead and pending is None:
            pending = done
            continue
        if ahead:
            done, pending = pending, done
        write(*done)
        if progress is not None:
            progress(done[0])
    if pending is not None:
        write(*pending)
        if progress is not None:
            progress(pending[0])


def _recorder(batch, occupancy, frames, track, fps, first_world, scene_name, writer):
    """An :class:`warpsim.browse.occupancy.OccupancyRecorder` for ``run_batch`` (None: no record);
    its default grid also covers the static geometry the writer has seen (floor, walls)."""
    if not occupancy:
        return None
    from ..browse.occupancy import DEFAULT_RESOLUTION, OccupancyRecorder, find_source_prim

    static = np.array([writer.lo, writer.hi]) if np.isfinite(writer.hi - writer.lo).all() else None
    bounds, resolution = occupancy.get("bounds"), occupancy.get("resolution") or DEFAULT_RESOLUTION
    if bounds is None and occupancy.get("agree") is not None:  # one grid for every block of the sweep
        n, P = batch.world_count, batch.model.world_particle_count
        x = batch.sim.state.positions.numpy().reshape(n, P, 3)[:, list(track.values()) if track else slice(None)]
        x = x.reshape(-1, 3) if static is None else np.concatenate([x.reshape(-1, 3), static])
        bounds, resolution = occupancy["agree"](x, resolution)
    recorder = OccupancyRecorder(batch, frames, particles=list(track.values()) if track else None,
                                 track_names=list(track) if track else (), bounds=bounds,
                                 resolution=resolution, fps=fps,
                                 first_world=first_world, scene=scene_name, include=static)
    x, v = batch.world_slices()  # world 0's frame data names the prim holding the recorded particles
    recorder.source_prim = find_source_prim(batch.world_frame_data(x[0], v[0], 0), x[0], recorder.particles)
    return recorder


def _cell(value):
    if value is None:  # a column this solver does not have (energy_gain of agents): an empty cell, not 0
        return ""
    if isinstance(value, (tuple, list, np.ndarray)):
        return ",".join(f"{float(v):.9g}" for v in value)
    if isinstance(value, float):
        return f"{value:.9g}"
    return str(value)


def write_table(csv_path, rows) -> str:
    """A CSV table with one row per world (columns in first-seen order: world, parameters,
    metrics); vector values are written ``x,y,z`` in one quoted cell. Returns the path."""
    rows = list(rows) if rows is not None and not isinstance(rows, (str, bytes, dict)) else rows
    if rows is None or isinstance(rows, (str, bytes, dict)) or not all(isinstance(r, dict) for r in rows):
        raise TypeError(f"write_table rows must be a list of dicts (one per world, as run_batch returns), got "
                        f"{type(rows).__name__}")
    csv_path = os.path.abspath(os.fspath(csv_path))
    os.makedirs(os.path.dirname(csv_path), exist_ok=True)
    columns = []
    for row in rows:
        for k in row:
            if k not in columns:
                columns.append(k)
    tmp = csv_path + ".tmp"
    try:
        with open_temporary(tmp, newline="") as f:
            out = csv.writer(f)
            out.writerow(columns)
            for row in rows:
                out.writerow([_cell(row[k]) if k in row else "" for k in columns])
    except OSError as exc:  # in words, never a bare "[Errno N]"; no temporary is left (open_temporary)
        from ..core.safe_files import disk_full, disk_reason

        code = disk_full(exc)
        why = disk_reason(code) if code is not None else \
            f"{(exc.strerror or str(exc)).lower()}; choose a writable --out"
        raise OSError(f"could not write the table {csv_path}: {why}") from None
    os.replace(tmp, csv_path)
    return csv_path
