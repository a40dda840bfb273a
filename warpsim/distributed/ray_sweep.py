"""A many-worlds sweep on a Ray cluster: one Ray task per batch of worlds, gathered by the driver.

``warpsim sweep SCENE --worlds N --vary ... --ray [ADDRESS] --batch-size B [--resume]``

1. The driver (the process running ``warpsim sweep``) samples the worlds exactly as the
   single-process sweep does and splits them into batches of ``B`` (the last holds the rest).
2. Each batch is one Ray task: ``num_gpus=1`` when the cluster has GPUs (Ray sets
   ``CUDA_VISIBLE_DEVICES``, so the task runs on ``cuda:0``), one CPU otherwise. The task calls
   ``warpsim.sweeps.run_batch`` with a layer path inside a temporary folder, stores its metric rows
   beside it and renames the folder into place (``warpsim.distributed.batches``). A task whose
   worker dies (killed, out of memory, node lost) is run again by Ray (``max_retries``); the dead
   attempt's temporary folder is never referenced and is removed at the end.
3. As each batch finishes the driver checks its folder's checksum and records it in the manifest
   (``warpsim.distributed.manifest``); ``--resume`` runs only the batches the manifest does not
   list, whose files changed since, or whose run raised.
4. With every batch done, the driver writes the metric table (one row per world, in world order)
   and the root USD that references every batch's layer, so the variant set ``world`` spans all
   batches. A batch whose run raised (a blow-up the batch could not contain) does not stop the
   sweep: its worlds are rows with ``blown_up`` set and the error in ``batch_error``.

The output folder must be visible to every node (one machine, or a shared filesystem such as NFS):
tasks write their layers there and the driver reads them. Warp compiles kernels once per machine
and caches them (``~/.cache/warp``), so the workers of one machine share the compiled kernels.

Ray is imported only inside these functions; ``import warpsim`` does not import it.
"""
from __future__ import annotations

import logging
import os
import shutil
import signal
import socket
import sys
import time

from .batches import (
    batch_dir,
    batches_root,
    load_rows,
    publish_batch,
    remove_stale,
    split_batches,
    temp_batch_dir,
)
from .manifest import SweepManifest, manifest_path, worlds_digest

__all__ = ["RaySweepError", "add_ray_arguments", "default_batch_size", "ray_usage_error", "run_batch_task",
           "run_ray_sweep"]

DEFAULT_BATCH_SIZE = 64
LAYER_EXT = ".usdc"


class RaySweepError(RuntimeError):
    """A batch failed past its retries, or the driver cannot see a batch a worker wrote (exit 1);
    the finished batches stay listed in the manifest, so ``--resume`` continues the sweep."""


def add_ray_arguments(parser):
    """Add ``--ray [ADDRESS]``, ``--batch-size``, ``--ray-cpus`` and ``--resume`` to ``parser``."""
    g = parser.add_argument_group("Ray (run the sweep's batches on a cluster; needs warpsim[ray])")
    g.add_argument("--ray", nargs="?", const="local", default=None, metavar="ADDRESS",
                   help="run batches as Ray tasks on the cluster at ADDRESS (host:6379, ray://host:10001 or "
                        "auto); without ADDRESS start a local cluster. Put it after SCENE.")
    g.add_argument("--batch-size", type=int, default=None, metavar="B",
                   help=f"worlds per Ray task (default {DEFAULT_BATCH_SIZE}; with --device cuda on a local cluster, "
                        "one task per GPU)")
    g.add_argument("--ray-cpus", type=int, default=None, metavar="N",
                   help="CPUs of a local cluster started by --ray (default: all)")
    g.add_argument("--resume", action="store_true",
                   help="continue an interrupted sweep: with --ray run only the batches its manifest does not list "
                        "as finished; without, keep the completed chunks of the batch layer and write on")
    return g


def ray_usage_error(args):
    """A one-line complaint about the Ray options of parsed ``args``, or None when they are fine."""
    if getattr(args, "ray", None) is None:
        given = [flag for flag, value in (("--batch-size", getattr(args, "batch_size", None)),
                                          ("--ray-cpus", getattr(args, "ray_cpus", None))) if value]
        if given:
            return f"{', '.join(given)} go{'es' if len(given) == 1 else ''} with --ray (a sweep on a Ray cluster)"
        return None
    if args.batch_size is not None and args.batch_size < 1:
        return f"--batch-size {args.batch_size}: it must be >= 1 (worlds per Ray task)"
    if args.ray_cpus is not None and args.ray_cpus < 1:
        return f"--ray-cpus {args.ray_cpus}: it must be >= 1"
    if args.ray_cpus is not None and args.ray != "local":
        return "--ray-cpus sizes a local cluster; a running cluster at --ray ADDRESS has its own CPUs"
    if args.ray == "local":  # a head that cannot start under ulimit -v: said before any world is sampled
        from .ray_head import RayHeadError, check_address_space

        try:
            check_address_space()
        except RayHeadError as exc:
            return str(exc)
    return None


def default_batch_size(world_count, device=None, address=None):
    """Worlds per Ray task when ``--batch-size`` is not given: with ``--device cuda...`` on a local
    cluster, one task per local GPU (``ceil(world_count / GPUs)``: each task holds one GPU and steps
    its worlds in one batch); otherwise ``DEFAULT_BATCH_SIZE``."""
    if str(device or "").startswith("cuda") and address in (None, "local"):
        import warp as wp

        gpus = wp.get_cuda_device_count()
        if gpus:
            return max(1, -(-int(world_count) // gpus))
    return DEFAULT_BATCH_SIZE


def _layer_name(out_path, index):
    return f"{os.path.splitext(os.path.basename(out_path))[0]}.batch_{index:04d}{LAYER_EXT}"


def _blown_rows(world_params, first_world, error):
    return [{"world": first_world + i, **params, "blown_up": 1, "batch_error": error}
            for i, params in enumerate(world_params)]


def run_batch_task(spec):
    """Body of one Ray task: run one batch into a temporary folder and publish it whole.

    ``spec`` keys: ``scene``, ``worlds`` (list of parameter dicts), ``first_world``, ``index``,
    ``frames``, ``fps``, ``substeps``, ``device``, ``final_dir``, ``layer_name``, ``runner`` (None:
    ``warpsim.sweeps.run_batch``), ``options`` (more keyword arguments for it) and ``kill_once``
    (tests only: a marker path; the first attempt that finds no marker creates it and SIGKILLs its
    own worker after the layer is written but before it is published); ``reference``: an ObjectRef
    of the whole sweep's parameter list (None or absent: none; ``run_batch``'s ``reference_params``). Returns ``{"index", "rows", "sha256", "seconds", "host", "pid", "error"}``.
    """
    import warp as wp

    wp.config.quiet = True
    if hasattr(wp, "LOG_WARNING"):
        wp.config.log_level = wp.LOG_WARNING
    runner = spec.get("runner")
    if runner is None:
        from ..sweeps import run_batch as runner
    t0 = time.perf_counter()
    final_dir = spec["final_dir"]
    tmp = temp_batch_dir(final_dir)
    error = None
    options = dict(spec.get("options") or {})
    if spec.get("reference") is not None:  # the whole sweep's parameters (an ObjectRef)
        import ray

        options["reference_params"] = ray.get(spec["reference"])
    if spec.get("occupancy"):  # the batch's occupancy record, on the whole sweep's grid, in its folder
        options["occupancy"] = {**spec["occupancy"], "path": os.path.join(tmp, spec["record_name"])}
    try:
        rows = runner(spec["scene"], spec["worlds"], frames=spec["frames"], fps=spec["fps"],
                      substeps=spec["substeps"], device=spec["device"],
                      layer_path=os.path.join(tmp, spec["layer_name"]), first_world=spec["first_world"],
                      **options)
    except Exception as exc:  # noqa: BLE001  (a batch that blows up is flagged, not fatal)
        error = f"{type(exc).__name__}: {exc}".splitlines()[0]
        rows = _blown_rows(spec["worlds"], spec["first_world"], error)
        for name in os.listdir(tmp):  # no partial layer in a published batch
            path = os.path.join(tmp, name)
            shutil.rmtree(path) if os.path.isdir(path) else os.remove(path)
    marker = spec.get("kill_once")
    if marker and not os.path.exists(marker):
        with open(marker, "w") as fh:
            fh.write(f"{spec['index']} {os.getpid()}\n")
        os.kill(os.getpid(), signal.SIGKILL)
    checksum = publish_batch(tmp, final_dir, rows)
    return {"index": spec["index"], "rows": rows, "sha256": checksum, "seconds": time.perf_counter() - t0,
            "host": socket.gethostname(), "pid": os.getpid(), "error": error}


def _connect(address, num_cpus):
    """``(ray, started)``: connect to ``address`` or start a local cluster (reuse an open connection)."""
    remote = address not in (None, "local")
    if remote and "RAY_AUTH_MODE" not in os.environ and "ray" not in sys.modules and _token_available():
        # Ray >= 2.59 starts clusters with token authentication, and a driver that connects by address
        # sends its token only in token mode, read when ray is imported (a cluster without
        # authentication ignores the token)
        os.environ["RAY_AUTH_MODE"] = "token"
    try:
        import ray
    except ImportError:
        raise ValueError("--ray needs Ray: pip install 'warpsim[ray]'") from None
    if ray.is_initialized():
        return ray, False
    if remote:
        _probe_address(address)
    quiet = {"logging_level": logging.ERROR, "log_to_driver": False}
    if not remote:
        from .ray_head import start_local_head

        start_local_head(ray, num_cpus=num_cpus, include_dashboard=False, **quiet)  # one line when it fails
        _watch_local_cluster(ray)
    else:
        try:
            ray.init(address=address, **quiet)
        except ConnectionError as exc:
            raise ValueError(f"--ray {address}: no Ray cluster there, or its authentication token is not this "
                             f"machine's ({exc}); start one with 'ray start --head' and pass the address it "
                             "prints; with token authentication set RAY_AUTH_MODE=token and the cluster's token "
                             "(ray get-auth-token) in ~/.ray/auth_token") from None
    return ray, True


def _watch_local_cluster(ray):
    """A killed driver must not leave the cluster it started running: see ``watchdog``."""
    from .watchdog import start_watchdog

    session = None
    try:  # ray has no public accessor for the session folder
        session = ray._private.worker.global_worker.node.get_session_dir_path()
    except Exception:  # noqa: BLE001
        latest = os.path.join("/tmp", "ray", "session_latest")
        session = os.path.realpath(latest) if os.path.exists(latest) else None
    start_watchdog(session)


CONNECT_TIMEOUT_S = 10.0
"""How long the driver waits for a cluster address to accept a TCP connection [s] (Ray itself
retries an address that does not answer for minutes)."""


def _probe_address(address, timeout=None):
    """ValueError naming ``address`` when nothing accepts a connection there within ``timeout``
    seconds (``auto`` is left to Ray: it reads the address of the cluster on this machine)."""
    from ..sweeps.preflight import check_ray_address

    timeout = CONNECT_TIMEOUT_S if timeout is None else float(timeout)
    target = check_ray_address(address)
    if target is None:
        return
    host, port = target
    deadline = time.monotonic() + timeout
    last = None
    while True:
        try:
            socket.create_connection((host, port), timeout=max(0.1, min(2.0, deadline - time.monotonic()))).close()
            return
        except socket.gaierror as exc:
            raise ValueError(f"--ray {address}: host {host!r} is unknown ({exc.strerror}); give the head node's "
                             "address as 'ray start --head' prints it") from None
        except OSError as exc:
            last = exc.strerror or str(exc) or type(exc).__name__
        if time.monotonic() >= deadline:
            raise ValueError(f"--ray {address}: nothing answers at {host}:{port} ({last}; gave up after {timeout:g} s); "
                             "start a cluster with 'ray start --head' and pass the address it prints, or use --ray "
                             "alone for a local cluster")
        time.sleep(0.25)


def _token_available():
    """Whether a Ray authentication token is configured (RAY_AUTH_TOKEN[_PATH] or ~/.ray/auth_token)."""
    return bool(os.environ.get("RAY_AUTH_TOKEN") or os.environ.get("RAY_AUTH_TOKEN_PATH")
                or os.path.exists(os.path.join(os.path.expanduser("~"), ".ray", "auth_token")))


def _task_resources(ray, device):
    """``(ray options, device name inside the task)`` for the cluster and the requested device."""
    gpus = ray.cluster_resources().get("GPU", 0)
    if device is None:
        device = "cuda" if gpus > 0 else "cpu"
    if str(device).startswith("cuda"):
        if gpus < 1:
            raise ValueError(f"--device {device}: the Ray cluster has no GPUs; use --device cpu")
        return {"num_gpus": 1, "num_cpus": 1}, "cuda:0"  # Ray picks the GPU via CUDA_VISIBLE_DEVICES
    if device != "cpu":
        raise ValueError(f"--device {device!r}: Ray tasks run on 'cpu' or 'cuda'")
    return {"num_cpus": 1}, "cpu"


def _driver_device(device):
    """Where the driver resolves a sweep-wide setting: the sweep's kind of device when it has one."""
    import warp as wp

    if device == "cpu" or not wp.is_cuda_available():
        return "cpu"
    return "cuda:0"


def run_ray_sweep(scene_name, world_params, *, frames, out_path, table_path, fps=None, substeps=None,
                  device=None, batch_size=DEFAULT_BATCH_SIZE, address=None, num_cpus=None, resume=False,
                  layout="variants", max_retries=3, runner=None, batch_options=None, log=None, _kill_once=None,
                  occupancy=None):
    """Run a sweep's worlds as Ray tasks, one per batch; write the table and the root USD.

    Args:
        scene_name: a registered scene that ``warpsim.sweeps.run_batch`` supports.
        world_params: one parameter dict per world (``warpsim.sweeps.sample_worlds``).
        frames, fps, substeps: as for ``warpsim sweep`` (None: the scene's defaults).
        out_path: the root USD (``.usd``/``.usda``/``.usdc``); batches live in ``<stem>.batches/``,
            the manifest in ``<stem>.ray-manifest.json``.
        table_path: the CSV of one row per world.
        device: None (GPUs when the cluster has them), ``"cpu"`` or ``"cuda"``.
        batch_size: worlds per Ray task.
        address: a running cluster's address, or None / ``"local"`` to start a local one with
            ``num_cpus`` CPUs (an open ``ray.init`` connection is reused either way).
        resume: skip the batches the manifest lists with an unchanged checksum and no error.
        max_retries: Ray task retries after a worker dies.
        runner: the batch function (default ``warpsim.sweeps.run_batch``); it must be picklable.
        batch_options: more keyword arguments for every ``runner`` call (e.g. ``track``).
        log: a file for one line per finished batch (None: silent).
        occupancy: None, or {"resolution", "bounds"} as for ``run_batch``: every batch records its
            worlds on the grid one process would take for the whole sweep (:func:`sweep_record_options`)
            and the driver merges the records into ``<stem>.occupancy.npz``, the same bytes as a
            one-process sweep's (none when a batch failed).

    Returns:
        ``{"rows", "root", "table", "ran", "skipped", "batches": {index: record}, "record", "seconds"}``
        (``record``: the merged occupancy record's path, or None);
        ``ran``/``skipped`` are batch indices run now / taken from the manifest.
    """
    t_start = time.perf_counter()
    world_params = list(world_params)
    if "frame_steps" not in (batch_options or {}):
        # automatic sub-steps resolve over the whole sweep (its stiffest world), as in one process,
        # not per batch: every batch is told the count (warpsim.sweeps.rerun.sweep_frame_steps)
        from ..sweeps.rerun import sweep_frame_steps

        steps = sweep_frame_steps(scene_name, world_params, fps=fps, substeps=substeps, device=_driver_device(device),
                                  fused=bool((batch_options or {}).get("fused")))
        if steps is not None:
            batch_options = {**(batch_options or {}), "frame_steps": steps}
    batches = split_batches(len(world_params), batch_size)
    out_path = os.path.abspath(out_path)
    sweep = {"scene": scene_name, "world_count": len(world_params), "batch_size": batch_size,
             "frames": frames, "fps": fps, "substeps": substeps, "layout": layout,
             "worlds_sha256": worlds_digest(world_params), "options": _describe(batch_options or {})}
    if occupancy is not None:  # a resumed sweep's batches must record on the same grid
        sweep["occupancy"] = _describe({"resolution": occupancy.get("resolution"), "bounds": (
            None if occupancy.get("bounds") is None else [list(map(float, c)) for c in occupancy["bounds"]])})
    from ..browse.roots import LAYOUTS

    if layout not in LAYOUTS:
        raise ValueError(f"layout {layout!r} is unknown; use one of {', '.join(LAYOUTS)}")
    if num_cpus is not None and num_cpus < 1:
        raise ValueError(f"--ray-cpus {num_cpus}: it must be >= 1")
    mpath = manifest_path(out_path)
    manifest = None
    if resume:
        try:
            manifest = SweepManifest.load(mpath)
        except FileNotFoundError as exc:  # a usage mistake on the command line (exit 2)
            raise ValueError(str(exc)) from None
        problem = manifest.mismatch(sweep)
        if problem:
            raise ValueError(f"--resume: {problem}")

    record_options = None
    if occupancy is not None:
        record_options = sweep_record_options(scene_name, world_params, occupancy,
                                              track=(batch_options or {}).get("track"),
                                              fused=bool((batch_options or {}).get("fused")))
    ray, started = _connect(address, num_cpus)
    try:
        options, task_device = _task_resources(ray, device)  # refuses a device before touching any file
        os.makedirs(os.path.dirname(out_path), exist_ok=True)
        if manifest is None:
            broot = None
            if os.path.exists(out_path) and os.path.isdir(batches_root(out_path)):
                # a finished sweep of this name stays whole (its root references these batches) until
                # this one is complete: write beside it, remove it at the end
                import secrets

                broot = os.path.basename(batches_root(out_path)) + "-" + secrets.token_hex(4)
            else:
                shutil.rmtree(batches_root(out_path), ignore_errors=True)  # an interrupted sweep of this name
            manifest = SweepManifest.new(mpath, sweep)
            manifest.batches_root = broot
            manifest.save()
        broot = manifest.batches_root
        os.makedirs(batches_root(out_path, broot), exist_ok=True)
        # a resume runs again what is not listed, what changed on disk and what raised (maybe out of memory)
        skipped = [i for i in range(len(batches)) if resume and manifest.finished(i) and not manifest.batches[i]["error"]]
        todo = [i for i in range(len(batches)) if i not in skipped]
        task = ray.remote(run_batch_task).options(max_retries=max_retries, retry_exceptions=False, **options)
        # every batch builds its worlds against the whole sweep (run_batch reference_params): a world's
        # arrays, and so its samples, do not depend on its batch; stored once in Ray's object store
        reference = ray.put(list(world_params)) if runner is None else None
        pending = {}
        for i in todo:
            first, count = batches[i]
            spec = {"scene": scene_name, "worlds": world_params[first:first + count], "first_world": first,
                    "index": i, "frames": frames, "fps": fps, "substeps": substeps, "device": task_device,
                    "final_dir": batch_dir(out_path, i, broot), "layer_name": _layer_name(out_path, i),
                    "runner": runner, "options": batch_options, "kill_once": _kill_once,
                    "occupancy": record_options, "record_name": _record_name(out_path, i),
                    "reference": reference}
            pending[task.remote(spec)] = i
        fresh = {}
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            i = pending.pop(done[0])
            try:
                result = ray.get(done[0])
            except Exception as exc:  # noqa: BLE001  (Ray wraps worker deaths past max_retries)
                for ref in pending:  # the sweep stops here; its other tasks need not run on
                    ray.cancel(ref, force=True)
                raise RaySweepError(f"batch {i} (worlds {batches[i][0]}..{sum(batches[i]) - 1}) failed after "
                                   f"{max_retries} retries: {str(exc).splitlines()[0]}; the finished batches are "
                                   "in the manifest: run again with --resume") from None
            _record(manifest, out_path, batches, i, result)
            fresh[i] = result["rows"]
            if log is not None:
                rec = manifest.batches[i]
                state = f", failed: {rec['error']}" if rec["error"] else ""
                print(f"batch {i + 1}/{len(batches)} (worlds {batches[i][0]}..{sum(batches[i]) - 1}) "
                      f"{rec['seconds']:.2f} s on {rec['host']}{state}", file=log, flush=True)
    finally:
        if started:
            ray.shutdown()

    rows = []
    for i in range(len(batches)):
        rows.extend(fresh[i] if i in fresh else load_rows(batch_dir(out_path, i, broot)))
    rows.sort(key=lambda r: r["world"])
    from ..sweeps import write_sweep_root, write_table

    write_table(table_path, rows)
    ok = [i for i in range(len(batches)) if not manifest.batches[i]["error"]]
    layers = [os.path.join(batch_dir(out_path, i, broot), _layer_name(out_path, i)) for i in ok]
    worlds = None  # every world; only the worlds of batches with a layer when a batch failed
    if len(ok) < len(batches):
        worlds = [w for i in ok for w in range(batches[i][0], sum(batches[i]))]
    if not layers:
        raise RaySweepError(f"every batch failed, e.g. batch 0: {manifest.batches[0]['error']}; the table "
                            f"{table_path} lists the errors")
    root = write_sweep_root(out_path, layers, len(world_params), layout=layout, worlds=worlds)
    record = None
    if record_options is not None:
        record = _merge_records(out_path, batches, manifest, broot, log)
    remove_stale(out_path, broot)
    import glob

    current = batches_root(out_path, broot)
    for folder in glob.glob(glob.escape(batches_root(out_path)) + "*"):  # the replaced sweep's batches
        if os.path.isdir(folder) and os.path.abspath(folder) != current:
            shutil.rmtree(folder, ignore_errors=True)
    return {"rows": rows, "root": root, "table": table_path, "layers": layers, "ran": sorted(fresh),
            "skipped": skipped,
            "batches": {i: manifest.batches[i] for i in range(len(batches))}, "record": record,
            "seconds": time.perf_counter() - t_start}


def _record_name(out_path, index):
    return f"{os.path.splitext(os.path.basename(out_path))[0]}.batch_{index:04d}.occupancy.npz"


def sweep_record_options(scene_name, world_params, occupancy, *, track=None, fused=False, chunk=256):
    """``occupancy`` ({"resolution", "bounds"}) with the grid one process's recorder of every
    world takes: bounds (when not given) as :func:`warpsim.browse.occupancy.default_bounds` of
    every world's frame-0 points (the tracked particles when ``track``) and the scene's static
    geometry, and the resolution that recorder settles on for the whole world count. The worlds
    are built on the CPU, ``chunk`` at a time, not run."""
    import tempfile

    import numpy as np

    from ..scenes import get_scene
    from ..browse.occupancy import DEFAULT_RESOLUTION, default_bounds
    from ..sweeps.sweep import normalise_params, make_batch
    from ..sweeps.usd import BatchLayerWriter
    from .devices import sweep_resolution

    options = {"resolution": occupancy.get("resolution") or DEFAULT_RESOLUTION, "bounds": occupancy.get("bounds")}
    n = len(world_params)
    if options["bounds"] is None:
        cls = get_scene(scene_name)
        corners = []
        for first in range(0, n, int(chunk)):
            batch = make_batch(cls, [normalise_params(cls, p) for p in world_params[first:first + int(chunk)]],
                               device="cpu", fused=fused)
            if not corners:  # the static geometry (floor, walls) the batch layers declare
                with tempfile.TemporaryDirectory() as folder:
                    writer = BatchLayerWriter(os.path.join(folder, "grid.usdc"), batch.scene, 0, batch.world_count,
                                              60.0)
                if np.isfinite(writer.hi - writer.lo).all():
                    corners.append(np.array([writer.lo, writer.hi]))
            P = batch.model.world_particle_count
            x = batch.sim.state.positions.numpy().reshape(batch.world_count, P, 3)
            x = x[:, list(track.values()) if track else slice(None)].reshape(-1, 3).astype(np.float64)
            x = x[np.isfinite(x).all(1)]
            if len(x):
                corners.append(np.stack([x.min(0), x.max(0)]))
        options["bounds"] = default_bounds(np.concatenate(corners) if corners else np.zeros((0, 3)))
    options["resolution"] = sweep_resolution(options["bounds"], options["resolution"], n)
    return options


def _merge_records(out_path, batches, manifest, broot, log):
    """Merge the batches' occupancy records into ``<stem>.occupancy.npz`` (its path), or remove a
    stale one and return None when a batch failed (its worlds have no record)."""
    from ..browse.occupancy import OccupancyRecord, occupancy_path
    from .devices import merge_records

    path = occupancy_path(out_path)
    failed = [i for i in range(len(batches)) if manifest.batches[i]["error"]]
    if failed:
        if os.path.exists(path):
            os.remove(path)
        if log is not None:
            print(f"no occupancy record: batch {failed[0]} failed ({manifest.batches[failed[0]]['error']}); "
                  "run the sweep again with --resume", file=log, flush=True)
        return None
    parts = [OccupancyRecord.load(os.path.join(batch_dir(out_path, i, broot), _record_name(out_path, i)))
             for i in range(len(batches))]
    return merge_records(parts).save(path)


def _describe(options):
    """JSON form of ``batch_options`` for the manifest (objects by their ``name`` or type)."""
    import json

    return json.loads(json.dumps(options, sort_keys=True,
                                 default=lambda o: getattr(o, "name", type(o).__name__)))


def _record(manifest, out_path, batches, i, result):
    """Check batch ``i``'s published folder as the driver sees it, then list it in the manifest."""
    from .batches import tree_checksum

    folder = batch_dir(out_path, i, manifest.batches_root)
    if not os.path.isdir(folder) or tree_checksum(folder) != result["sha256"]:
        raise RaySweepError(f"batch {i} was written on host {result['host']} to {folder}, which this driver "
                           "does not see (or sees changed): --out must be on a filesystem every Ray node shares")
    first, count = batches[i]
    manifest.record(i, {"first_world": first, "world_count": count,
                        "dir": os.path.relpath(folder, os.path.dirname(manifest.path)),
                        "sha256": result["sha256"], "seconds": result["seconds"], "host": result["host"],
                        "pid": result["pid"], "error": result["error"],
                        "blown_up": sum(bool(r.get("blown_up")) for r in result["rows"])})
