"""One sweep over several devices of one host: contiguous blocks of worlds, one thread per device.

    warpsim sweep SCENE ... --devices cuda:0,cuda:1      (or --devices all, or --devices cpu,cpu)

1. The worlds are split into contiguous blocks, one per device (:func:`split_blocks`): as even as
   the world count allows (sizes differ by at most one) unless a device's free memory holds
   fewer worlds, in which case its block shrinks to what fits and the devices with room take the
   rest (:func:`block_sizes`).
2. Each world takes its own automatic count (the one its own run takes,
   ``WorldBatch.world_steps``), so the split never changes a world's steps. The whole sweep's
   largest count (:func:`warpsim.sweeps.rerun.sweep_frame_steps`, on the first device) is given
   to every block for the scenes whose worlds share one count (``WorldBatch.own_counts`` False).
3. Each block runs :func:`warpsim.sweeps.run_batch` in its own thread on its own device (a CUDA
   device steps on its own stream and replays its own graphs) with the whole sweep's parameters
   as the batch's reference, so a world's arrays, and with the fixed-order sums its bits, do not
   depend on its block. Block K writes its own batch layer ``<stem>.batch_000K.usdc`` (staged and
   chunked as a one-device sweep's, :class:`warpsim.sweeps.staging.SweepStaging`). Before frame 0
   the blocks agree on one occupancy grid (the whole sweep's frame-0 extent and resolution).
4. The rows merge in world order into one table, the blocks' occupancy records into one record
   (:func:`merge_records`), the layers into one root: the table, every world's samples and the
   record equal the same sweep on one device byte for byte.

A block that fails (an error on its device) stops the other blocks at their next frame; the sweep
fails with the device named, every block's completed chunks stay, and ``--resume`` completes it
(each block re-simulates up to its own last completed chunk without writing, then writes on).
"""
from __future__ import annotations

import json
import os
import threading

import numpy as np

__all__ = ["DeviceSweepError", "block_sizes", "merge_records", "parse_devices", "run_device_sweep",
           "split_blocks", "sweep_resolution"]


class DeviceSweepError(RuntimeError):
    """A block of a sweep over several devices failed (exit 1); its message names the device."""


class _Stopped(Exception):
    """Raised inside a block's run when another block failed."""


def parse_devices(text) -> list:
    """Device names (Warp aliases, in order) from ``--devices``: ``all`` (every CUDA device) or
    names separated by commas (``cuda:0,cuda:1``; ``cpu,cpu`` splits on the CPU). ValueError with
    one line for an unknown name, an empty item, a GPU named twice, or ``all`` without GPUs."""
    import warp as wp

    text = str(text).strip()
    cuda = [str(d) for d in wp.get_cuda_devices()]
    here = ", ".join(["cpu", *cuda])
    if text == "all":
        if not cuda:
            raise ValueError("--devices all: this machine has no CUDA device; give --devices cpu,cpu to split the "
                             "sweep on the CPU, or drop --devices")
        return cuda
    names = []
    for item in (t.strip() for t in text.split(",")):
        if not item:
            raise ValueError(f"--devices {text!r}: an empty device name; give names separated by commas, e.g. "
                             f"--devices {','.join(cuda[:2]) or 'cpu,cpu'}")
        try:
            name = str(wp.get_device(item))
        except Exception:  # noqa: BLE001  (Warp raises ValueError or RuntimeError)
            raise ValueError(f"--devices {text!r}: {item!r} is not a device of this machine (it has {here}); give "
                             f"some of those, or --devices all") from None
        if name != "cpu" and name in names:
            raise ValueError(f"--devices {text!r}: {name} is named twice; each GPU takes one block of worlds")
        names.append(name)
    return names


def block_sizes(world_count, capacities) -> list:
    """Worlds per block: as even as possible (the first ``world_count % K`` blocks one more),
    then no block above its ``capacities[k]`` (worlds its device holds; None: no limit), the
    excess going to the blocks with room, one world at a time to the least loaded. ValueError
    when the devices together hold fewer than ``world_count`` worlds."""
    k = len(capacities)
    if k < 1:
        raise ValueError("a sweep over several devices needs at least one device")
    if world_count < 1:
        raise ValueError(f"world count {world_count}: a sweep needs at least 1 world")
    cap = [world_count if c is None else max(0, int(c)) for c in capacities]
    if sum(cap) < world_count:
        raise ValueError(f"{world_count} worlds do not fit: the devices hold about {sum(cap)} together "
                         f"({', '.join(str(c) for c in cap)} each, from their free memory); use fewer --worlds or "
                         "more devices")
    sizes = [world_count // k + (1 if i < world_count % k else 0) for i in range(k)]
    excess = 0
    for i in range(k):
        if sizes[i] > cap[i]:
            excess += sizes[i] - cap[i]
            sizes[i] = cap[i]
    while excess:
        i = min((i for i in range(k) if sizes[i] < cap[i]), key=lambda i: (sizes[i], i))
        sizes[i] += 1
        excess -= 1
    return sizes


def split_blocks(world_count, capacities) -> list:
    """``[(first_world, count), ...]``: contiguous blocks in world order, sized by
    :func:`block_sizes` (a device left with no world gets no block)."""
    out, first = [], 0
    for n in block_sizes(world_count, capacities):
        out.append((first, n))
        first += n
    return out


def device_capacity(device, bytes_per_world, share=0.9):
    """Worlds of ``bytes_per_world`` [bytes] that ``share`` of a CUDA device's free memory holds
    (None on the CPU: the host check of :mod:`warpsim.sweeps.preflight` covers it)."""
    import warp as wp

    dev = wp.get_device(device)
    free = int(getattr(dev, "free_memory", 0) or 0) if dev.is_cuda else 0
    if not dev.is_cuda or not free or bytes_per_world <= 0:
        return None
    return int(share * free // bytes_per_world)


def merge_records(records):
    """One :class:`warpsim.browse.occupancy.OccupancyRecord` from the records of consecutive
    blocks of worlds on one grid (their pairs are sorted by world, so the merge is their
    concatenation); ValueError when the grids or frames differ."""
    from ..browse.occupancy import OccupancyRecord

    first = records[0]
    for r in records[1:]:
        same = (np.array_equal(r.grid.lo, first.grid.lo) and r.grid.cell_size == first.grid.cell_size
                and np.array_equal(r.grid.dims, first.grid.dims) and r.frame_count == first.frame_count
                and np.array_equal(r.particles, first.particles))
        if not same:
            raise ValueError("the blocks' occupancy records differ in grid, frames or particles; they cannot merge")
    starts, offset = [np.zeros(1, np.int64)], 0
    for r in records:
        starts.append(r.world_start[1:] + offset)
        offset += int(r.world_start[-1])
    samples = None if first.samples is None else np.concatenate([r.samples for r in records])
    return OccupancyRecord(grid=first.grid, fps=first.fps, first_frame=first.first_frame,
                           frame_count=first.frame_count, first_world=first.first_world,
                           world_count=sum(r.world_count for r in records),
                           world_particle_count=first.world_particle_count, particles=first.particles,
                           track_names=first.track_names, world_start=np.concatenate(starts),
                           pair_cell=np.concatenate([r.pair_cell for r in records]),
                           pair_bits=np.concatenate([r.pair_bits for r in records]), samples=samples,
                           scene=first.scene, source_prim=first.source_prim)


def sweep_resolution(bounds, resolution, world_count):
    """The resolution a one-device recorder of ``world_count`` worlds settles on (it halves while
    a 32-frame block of bits would pass ``BLOCK_BYTES_MAX``)."""
    from ..browse.occupancy import BLOCK_BYTES_MAX, OccupancyGrid

    resolution = int(resolution)
    grid = OccupancyGrid.over(bounds[0], bounds[1], resolution)
    while world_count * grid.cell_count * 4 > BLOCK_BYTES_MAX and resolution > 2:
        resolution //= 2
        grid = OccupancyGrid.over(bounds[0], bounds[1], resolution)
    return resolution


class _Agreement:
    """The blocks' meeting before frame 0: each hands in its frame-0 extent, all get the whole
    sweep's occupancy grid (bounds as :func:`warpsim.browse.occupancy.default_bounds` of every
    world's points, resolution as one recorder of every world would take)."""

    def __init__(self, blocks, world_count):
        self.barrier = threading.Barrier(blocks)
        self.corners = [None] * blocks
        self.world_count = world_count

    def agree(self, block, points, resolution):
        from ..browse.occupancy import default_bounds

        p = np.asarray(points, np.float64).reshape(-1, 3)
        p = p[np.isfinite(p).all(1)]
        self.corners[block] = np.stack([p.min(0), p.max(0)]) if len(p) else np.zeros((0, 3))
        try:
            self.barrier.wait()
        except threading.BrokenBarrierError:
            raise _Stopped() from None
        bounds = default_bounds(np.concatenate(self.corners))
        return bounds, sweep_resolution(bounds, resolution, self.world_count)


def _world_counts(cls, base):
    """(particles, springs) of one world (built on the CPU), None for scenes without a model."""
    scene = cls(base, device="cpu")
    model = getattr(getattr(scene, "sim", None), "model", None)
    return None if model is None else (int(model.particle_count), int(model.spring_count))


def _saved_blocks(root):
    """The block split an interrupted sweep of ``root`` started with (None: none readable)."""
    path = os.path.splitext(os.path.abspath(os.fspath(root)))[0] + ".sweep-partial.json"
    try:
        with open(path) as f:
            blocks = json.load(f)["settings"]["blocks"]
        return [(int(a), int(b)) for a, b in blocks]
    except (OSError, ValueError, KeyError, TypeError):
        return None


def plan_blocks(scene_name, world_params, devices, resume_root=None):
    """``[(first_world, count), ...]`` for ``devices``: from their free memory (see
    :func:`split_blocks`), or, resuming the sweep of root ``resume_root``, the split it started
    with when it has as many blocks. Checks each device's share against its memory
    (:func:`warpsim.sweeps.preflight.check_sweep_memory`; ValueError with the figures)."""
    from ..scenes import get_scene
    from ..sweeps import preflight

    cls = get_scene(scene_name)
    counts = _world_counts(cls, cls.resolve_params(world_params[0]))
    n = len(world_params)
    saved = _saved_blocks(resume_root) if resume_root is not None else None
    if saved is not None and len(saved) == len(devices) and sum(c for _, c in saved) == n:
        blocks = saved
    else:
        per_world = preflight.estimate_sweep_bytes(*counts, 1)["device"] if counts else 0
        blocks = split_blocks(n, [device_capacity(d, per_world) for d in devices])
    if counts:
        on = {}
        for d, (_, count) in zip(devices, blocks):
            on[d] = on.get(d, 0) + count
        for d, count in on.items():
            preflight.check_sweep_memory(scene_name, *counts, count, d)
    return blocks


def run_device_sweep(scene_name, world_params, *, devices, frames, out_path, table_path, settings, fps=None,
                     substeps=None, layout="variants", track=None, fused=False, occupancy=None, chunk_size=None,
                     resume=False, warn=None, progress=None, log=None, store_every=1) -> dict:
    """Run a sweep split over ``devices`` in this process; write its layers, table, occupancy
    record and root (module docstring). ``settings``: what ``--resume`` must match (the one-device
    sweep's staging settings; the split is added). ``occupancy``: None, or the options of
    :func:`warpsim.sweeps.run_batch` without ``path`` (the record goes beside the root).
    ``progress(frames)``: called with the frames every block has finished, as that grows;
    ``log``: a file told of a resume; ``store_every``: the frames kept, as ``run_batch`` takes it
    (``--store``: 1 all, k preview, 0 none: each block's last frame goes to a scratch layer, the
    ``"layers"`` returned, for the thumbnails; the caller removes them, and the root is
    :func:`warpsim.browse.roots.write_unstored_root`'s). Returns ``{"rows", "root", "layers",
    "record", "blocks", "frame_steps"}``. DeviceSweepError naming the device when a block fails after frame 0; a
    ValueError a block raises before it (a bad parameter) is raised as it is."""
    from ..cli_common import UsageError
    from ..browse.occupancy import OccupancyRecord, occupancy_path
    from ..sweeps.rerun import sweep_frame_steps
    from ..sweeps.staging import SweepStaging
    from ..sweeps.sweep import run_batch, write_table
    from ..browse.roots import write_sweep_root

    world_params = list(world_params)
    n = len(world_params)
    blocks = plan_blocks(scene_name, world_params, devices, out_path if resume else None)
    blocks = [(b, d) for b, d in zip(blocks, devices) if b[1] > 0]
    staging = SweepStaging(out_path, {**settings, "blocks": [list(b) for b, _ in blocks]}, resume=resume,
                           blocks=len(blocks), stored=int(store_every) != 0)
    scratch: list = [None] * len(blocks)  # --store none: each block's last frame, for the thumbnails
    if int(store_every) == 0:
        import tempfile

        scratch = [os.path.join(tempfile.mkdtemp(prefix="warpsim_sweep_last_"), "last.usdc") for _ in blocks]
    # automatic sub-steps: resolved over the whole sweep before the split, on the first device
    steps = sweep_frame_steps(scene_name, world_params, fps=fps, substeps=substeps, device=blocks[0][1], fused=fused)
    firsts = [staging.resume_frame(k) for k in range(len(blocks))]
    if any(firsts) and log is not None:
        kept = [f"block {k} on {blocks[k][1]}: frames 0..{f - 1}" for k, f in enumerate(firsts) if f]
        print(f"resuming: {'; '.join(kept)} are kept; re-simulating them without writing, then writing on", file=log)
    record = occupancy_path(out_path)
    agreement = _Agreement(len(blocks), n)
    options = None
    if occupancy is not None:
        options = dict(occupancy)
        if options.get("bounds") is not None:  # given bounds: only the resolution depends on the count
            options["resolution"] = sweep_resolution(options["bounds"], options.get("resolution") or 16, n)
    stop = threading.Event()
    lock = threading.Lock()
    # one block at a time until its first frame is done: Warp loads (and compiles) a module on first
    # use, and two threads loading the same module at once once hung a two-block CPU sweep
    setup = threading.Lock()
    holding = [False] * len(blocks)

    def acquire(k):
        setup.acquire()
        holding[k] = True

    def release(k):
        if holding[k]:
            holding[k] = False
            setup.release()

    reached = [0] * len(blocks)
    shown = [0]
    results: list = [None] * len(blocks)
    errors: list = [None] * len(blocks)

    def tick(k, frame):
        release(k)  # its modules are loaded
        if stop.is_set():
            raise _Stopped()
        with lock:
            reached[k] = frame
            low = min(reached)
            if progress is not None and low > shown[0]:
                progress(low)
                shown[0] = low

    def block(k):
        (first, count), device = blocks[k]
        opts = None
        if options is not None:
            opts = {**options, "path": staging.partial(f"{os.path.splitext(record)[0]}.block{k}.npz")}
            if opts.get("bounds") is None:
                opts["agree"] = lambda points, resolution, k=k: meet(k, points, resolution)
        acquire(k)
        try:
            results[k] = run_batch(scene_name, world_params[first:first + count], frames=frames, fps=fps,
                                   substeps=substeps, device=device, layer_path=scratch[k] or staging.layers[k],
                                   first_world=first, store_every=store_every,
                                   track=track, progress=lambda f: tick(k, f), fused=fused, occupancy=opts,
                                   warn=warn, chunk_size=chunk_size, resume_frame=firsts[k], frame_steps=steps,
                                   reference_params=world_params)
        except BaseException as exc:  # noqa: BLE001  (recorded; the caller raises it with the device named)
            errors[k] = exc.with_traceback(None)  # frees the run's frames: its writer's open chunk layer too
            stop.set()
            agreement.barrier.abort()
        finally:
            release(k)

    def meet(k, points, resolution):
        release(k)  # the other blocks come to the meeting too
        agreed = agreement.agree(k, points, resolution)
        acquire(k)
        return agreed

    threads = [threading.Thread(target=block, args=(k,), name=f"warpsim-block-{k}", daemon=True)
               for k in range(len(blocks))]
    for t in threads:
        t.start()
    try:
        for t in threads:
            while t.is_alive():
                t.join(0.2)
    except BaseException:  # Ctrl-C: the blocks stop at their next frame, their chunks stay
        stop.set()
        agreement.barrier.abort()
        for t in threads:
            t.join()
        raise
    failed = [(k, e) for k, e in enumerate(errors) if e is not None and not isinstance(e, _Stopped)]
    if failed:
        k, exc = failed[0]
        (first, count), device = blocks[k]
        if isinstance(exc, (ValueError, UsageError)) and not any(reached):
            raise exc  # a request refused before any step (a parameter, --strict): as on one device
        if not isinstance(exc, Exception):
            raise exc
        text = " ".join(str(exc).split()) or type(exc).__name__
        raise DeviceSweepError(f"device {device} (block {k}, worlds {first}..{first + count - 1}) failed after frame "
                               f"{reached[k]}: {type(exc).__name__}: {text}; the other blocks stopped and every "
                               "completed chunk is kept: run the sweep again with --resume to complete it") from None
    rows = [row for r in results for row in r]
    parts = [staging.partial(f"{os.path.splitext(record)[0]}.block{k}.npz") for k in range(len(blocks))]
    moves = []
    if options is not None:
        merge_records([OccupancyRecord.load(p) for p in parts]).save(staging.partial(record))
        moves = [(staging.partial(record), record)]
    staging.publish(moves)  # the old sweep stays whole until here
    for p in parts:
        if os.path.exists(p):
            os.remove(p)
    write_table(table_path, rows)
    if int(store_every) == 0:
        from ..browse.roots import write_unstored_root
        from ..scenes import get_scene
        from ..sweeps.sweep import sweep_timing

        root = write_unstored_root(out_path, n, scene=scene_name, frames=frames,
                                   fps=sweep_timing(get_scene(scene_name), world_params, fps, substeps).fps)
    else:
        root = write_sweep_root(out_path, staging.final_layers, n, layout=layout)
    staging.finish()
    return {"rows": rows, "root": root, "layers": scratch if int(store_every) == 0 else list(staging.final_layers),
            "record": record if moves else None,
            "blocks": [(first, count, device) for (first, count), device in blocks], "frame_steps": steps}
