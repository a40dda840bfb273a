"""The manifest of a distributed sweep: which batches finished, with a checksum each.

``sweep.ray-manifest.json`` beside the sweep's root ``sweep.usda``::

    {"version": 1,
     "sweep": {"scene": "springs", "world_count": 64, "batch_size": 16, "frames": 24, ...,
               "worlds_sha256": "..."},           # what --resume must match
     "batches": {"0": {"first_world": 0, "world_count": 16, "dir": "sweep.batches/batch_0000",
                       "sha256": "...", "seconds": 3.1, "host": "node-a", "attempt_pid": 1234,
                       "blown_up": 0, "error": null}, ...}}

Only the driver writes it, after a batch's folder has been published whole (see
:mod:`warpsim.distributed.batches`), by writing a temporary file and ``os.replace``-ing it, so a
driver killed at any moment leaves the previous complete manifest. ``--resume`` trusts a listed
batch only when its folder still has the recorded checksum.
"""
from __future__ import annotations

import hashlib
import json
import os

from ..core.safe_files import open_temporary

from .batches import tree_checksum

__all__ = ["SweepManifest", "manifest_path", "worlds_digest"]

VERSION = 1


def manifest_path(out_path):
    """``<root stem>.ray-manifest.json`` beside the sweep's root ``out_path``."""
    return os.path.splitext(os.path.abspath(out_path))[0] + ".ray-manifest.json"


def _plain(value):
    """JSON-ready copy: tuples to lists, NumPy scalars and arrays to Python values."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if hasattr(value, "tolist"):  # numpy scalar or array
        return value.tolist()
    return value


def worlds_digest(world_params):
    """SHA-256 of the per-world parameters (their JSON form), so a resume sees the same worlds."""
    text = json.dumps(_plain(list(world_params)), sort_keys=True, allow_nan=True)
    return hashlib.sha256(text.encode()).hexdigest()


class SweepManifest:
    """Finished batches of one sweep; ``load`` an existing one or start ``new``.

    Attributes:
        path: the manifest file.
        sweep: the sweep's description (dict of JSON values) that a resume must match.
        batches: ``{batch index: record}`` of the finished batches.
    """

    def __init__(self, path, sweep, batches=None, batches_root=None):
        self.path = os.path.abspath(path)
        self.sweep = _plain(sweep)
        self.batches = dict(batches or {})
        self.batches_root = batches_root
        """Name of the folder beside the root holding the batches (None: ``<stem>.batches``)."""

    @classmethod
    def new(cls, path, sweep):
        return cls(path, sweep)

    @classmethod
    def load(cls, path):
        """Read ``path``; FileNotFoundError naming it and the fix when there is none."""
        from ..usd.pxr_errors import DamagedFileError

        if not os.path.exists(path):
            raise FileNotFoundError(f"--resume: no manifest {path}; start the sweep without --resume first")
        if not os.path.isfile(path):  # a FIFO would block for ever
            raise ValueError(f"--resume: manifest {path} is not a regular file (a pipe, socket or folder); remove it "
                             "to start the sweep again")
        with open(path, encoding="utf-8") as fh:
            try:
                data = json.load(fh)
            except (json.JSONDecodeError, UnicodeDecodeError) as exc:
                raise DamagedFileError(f"--resume: manifest {path} is not valid JSON text ({type(exc).__name__}: "
                                       f"{str(exc)[:80]}); remove it to start the sweep again") from None
        if not isinstance(data, dict):
            raise ValueError(f"--resume: manifest {path} holds a JSON {type(data).__name__}, not a warpsim sweep "
                             "manifest; remove it to start the sweep again without --resume")
        if data.get("version") != VERSION:
            raise ValueError(f"--resume: manifest {path} has version {data.get('version')!r}, "
                             f"this warpsim writes {VERSION}; start the sweep again without --resume")
        fix = "remove it to start the sweep again without --resume"
        if not isinstance(data, dict) or not isinstance(data.get("sweep"), dict):
            raise ValueError(f"--resume: manifest {path} lacks its \"sweep\" settings (not a warpsim sweep "
                             f"manifest, or edited); {fix}")
        batches = data.get("batches")
        if not isinstance(batches, dict):
            raise ValueError(f"--resume: manifest {path} has no \"batches\" table (found "
                             f"{type(batches).__name__}); {fix}")
        out = {}
        for key, rec in batches.items():
            if not str(key).isdigit() or not isinstance(rec, dict) or not {"dir", "sha256"} <= set(rec) \
                    or not all(isinstance(rec[k], str) for k in ("dir", "sha256")):
                raise ValueError(f"--resume: manifest {path}: batch entry {key!r} is not a batch record (a batch "
                                 f"index with \"dir\" and \"sha256\"); {fix}")
            rec.setdefault("error", None)
            out[int(key)] = rec
        root = data.get("batches_root")
        return cls(path, data["sweep"], out, os.path.basename(root) if isinstance(root, str) and root else None)

    def mismatch(self, sweep):
        """A sentence naming the first setting where ``sweep`` differs from the recorded one, or None."""
        given = _plain(sweep)
        for key in sorted(set(given) | set(self.sweep)):
            if given.get(key) != self.sweep.get(key) and key == "worlds_sha256":
                return ("the sampled worlds differ from the ones the sweep started with (--vary, --set, --worlds, "
                        "--sample or --seed changed); give the options it started with, or run without --resume")
            if given.get(key) != self.sweep.get(key):
                return (f"{key}={given.get(key)!r} differs from the manifest's {key}={self.sweep.get(key)!r}; "
                        "a resumed sweep keeps the settings it started with")
        return None

    def record(self, index, record):
        """Add batch ``index`` (a dict of JSON values) and rewrite the manifest atomically."""
        self.batches[int(index)] = _plain(record)
        self.save()

    def save(self):
        data = {"version": VERSION, "sweep": self.sweep,
                "batches": {str(k): self.batches[k] for k in sorted(self.batches)}}
        if self.batches_root:
            data["batches_root"] = self.batches_root
        tmp = f"{self.path}.tmp-{os.getpid()}"
        with open_temporary(tmp) as fh:
            json.dump(data, fh, indent=1, allow_nan=True)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, self.path)

    def finished(self, index):
        """True when batch ``index`` is listed and its folder still has the recorded checksum."""
        rec = self.batches.get(int(index))
        if rec is None:
            return False
        folder = os.path.join(os.path.dirname(self.path), rec["dir"])
        return os.path.isdir(folder) and tree_checksum(folder) == rec["sha256"]
