"""Checkpoints: simulation state saved atomically as ``.npz`` beside a cache, for exact resumes."""
from __future__ import annotations

import json
import os
import zipfile

import numpy as np

from ..core.safe_files import open_temporary

__all__ = ["load_checkpoint", "restore_simulator", "save_checkpoint", "simulator_checkpoint"]


def save_checkpoint(path, arrays, meta):
    """Write ``arrays`` ({name: array or scalar}) and JSON-able ``meta`` to ``path`` (.npz):
    written under a temporary name, synced, then renamed, so a kill never leaves half a file."""
    path = os.fspath(path)
    tmp = f"{path.removesuffix('.npz')}.tmp-{os.getpid()}.npz"
    payload = {f"state/{k}": np.asarray(v) for k, v in arrays.items()}
    payload["meta"] = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
    try:
        with open_temporary(tmp, "wb") as f:
            np.savez(f, **payload)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:  # a full disk, a kill signal: no half-written temporary is left
        if os.path.lexists(tmp) and not os.path.isdir(tmp):
            os.remove(tmp)
        raise


META_KEYS = ("scene", "frame", "fps", "substeps", "params")
"""Keys the command line's checkpoints carry in ``meta``."""


def load_checkpoint(path, required=()):
    """(arrays, meta) saved by :func:`save_checkpoint`. A missing file is a MissingFileError; an
    empty, truncated or foreign file, or ``meta`` lacking a ``required`` key, a ValueError naming
    the file (both are ValueErrors)."""
    from ..core.checks import existing_file

    path = existing_file(path, "checkpoint")
    fix = "delete it and run again without --resume, or restore the file"
    if not os.path.isfile(path):  # a FIFO would block np.load for ever
        raise ValueError(f"checkpoint {path!r} is not a regular file (a pipe, socket or folder); {fix}")
    try:
        with np.load(path, allow_pickle=False) as data:
            meta = json.loads(bytes(data["meta"]).decode())
            arrays = {k[len("state/"):]: data[k] for k in data.files if k.startswith("state/")}
    except (OSError, EOFError, ValueError, KeyError, UnicodeDecodeError, zipfile.BadZipFile) as exc:
        size = os.path.getsize(path)
        what = "is empty (0 bytes)" if size == 0 else f"is damaged or not a warpsim checkpoint ({size} bytes; " \
            f"{type(exc).__name__}: {str(exc)[:120]})"
        raise ValueError(f"checkpoint {path!r} {what}; {fix}") from None
    missing = [k for k in required if not isinstance(meta, dict) or k not in meta]
    if missing:
        raise ValueError(f"checkpoint {path!r} lacks {', '.join(missing)}; it is not a warpsim checkpoint: {fix}")
    return arrays, meta


def simulator_checkpoint(sim):
    """Everything a ``ws.Simulator`` needs to continue bit for bit: positions, velocities,
    forces, simulated time (host float64 and the device copy kernels read), step count and, when
    springs can break, the broken-spring mask."""
    out = {
        "positions": sim.state.positions.numpy(),
        "velocities": sim.state.velocities.numpy(),
        "forces": sim.state.forces.numpy(),
        "time": np.float64(sim.time),
        "step_count": np.int64(sim.step_count),
    }
    device_time = getattr(sim, "_time", None)
    if device_time is not None:
        out["device_time"] = device_time.numpy()
    if getattr(sim, "fracture", None) is not None:
        out["spring_broken"] = sim.model.spring_broken.numpy()
    return out


def restore_simulator(sim, data):
    """Inverse of :func:`simulator_checkpoint` (ValueError if the particle count differs)."""
    import warp as wp

    n = sim.state.positions.shape[0]
    if data["positions"].shape[0] != n:
        raise ValueError(f"checkpoint holds {data['positions'].shape[0]} particles but the scene has {n}; "
                         "resume with the parameters the checkpoint was made with")
    for name in ("positions", "velocities", "forces"):
        arr = getattr(sim.state, name)
        wp.copy(arr, wp.array(data[name], dtype=arr.dtype, device=arr.device))
    sim.time = float(data["time"])
    sim.step_count = int(data["step_count"])
    device_time = getattr(sim, "_time", None)
    if getattr(sim, "fracture", None) is not None and "spring_broken" in data:
        sim.fracture.restore(data["spring_broken"])
    if device_time is not None and "device_time" in data:
        wp.copy(device_time, wp.array(data["device_time"], dtype=device_time.dtype, device=device_time.device))
