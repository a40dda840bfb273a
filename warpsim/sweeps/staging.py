"""Where a single-process ``warpsim sweep`` writes while it runs, and the swap that publishes it.

A sweep of root ``s.usda`` streams its batch layer as ``s.batch_0000.run<T>.usdc`` (``T``: a
token of this run; a sweep over several devices one layer per block K, ``s.batch_000K.run<T>.usdc``)
with chunk files ``s.batch_0000.run<T>.chunkNNNNNN.usdc`` beside it, so a
finished sweep's files in the same folder (``s.batch_0000.usdc``, its own ``run<T'>`` chunks, the
table, the occupancy record, the root) stay untouched and readable until the new run is complete.
``s.sweep-partial.json`` names the run in progress and the settings it was started with.

When every frame is written, :meth:`SweepStaging.publish` renames the batch layer onto
``s.batch_0000.usdc`` (one ``os.replace``: the switch from the old result to the new one), moves
the occupancy record into place, and then removes the old run's chunk files and the progress
file; the caller writes the table and the root (each atomically) in between.

A run killed at any moment (SIGKILL included) leaves its completed chunks readable
(``warpsim info s.batch_0000.run<T>.usdc``); ``--resume`` finds the run from the progress file,
keeps the completed chunks, re-simulates up to them without writing (batched runs are
bit-reproducible) and writes on, so the result equals an uninterrupted run sample for sample.
"""
from __future__ import annotations

import glob
import hashlib
import json
import os
import re
import secrets

from ..core.safe_files import open_temporary

__all__ = ["SweepStaging", "settings_digest", "staged_sweep"]

VERSION = 1


def settings_digest(world_params) -> str:
    """SHA-256 of the worlds' parameters (their JSON form)."""
    text = json.dumps(list(world_params), sort_keys=True, default=lambda v: list(v) if hasattr(v, "__iter__")
                      else str(v))
    return hashlib.sha256(text.encode()).hexdigest()


def _atomic_json(path, data):
    tmp = f"{path}.tmp-{os.getpid()}"
    with open_temporary(tmp) as f:
        json.dump(data, f, indent=1)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def staged_sweep(root_path):
    """What an interrupted single-process sweep of root ``root_path`` left (None when its progress
    file is absent): ``{"progress", "layer", "settings", "frames" [(start, end)], "damaged",
    "why"}``; ``why`` says what is unreadable (the progress file or the staged layer), else None."""
    stem = os.path.splitext(os.path.abspath(os.fspath(root_path)))[0]
    progress = stem + ".sweep-partial.json"
    if not os.path.isfile(progress):
        return None
    out = {"progress": progress, "layer": None, "settings": {}, "frames": [], "damaged": [], "why": None}
    try:
        with open(progress, encoding="utf-8") as f:
            data = json.load(f)
        token, settings = str(data["token"]), data["settings"]
        if not token.isalnum() or not isinstance(settings, dict):
            raise ValueError
    except (OSError, ValueError, KeyError, TypeError):
        out["why"] = f"its progress file {os.path.basename(progress)} is damaged"
        return out
    out["settings"] = settings
    out["layer"] = layer = f"{stem}.batch_0000.run{token}.usdc"
    if not os.path.isfile(layer):
        out["why"] = "no frame was completed (its staged layer does not exist yet)"
        return out
    from ..usd.validate import chunk_health

    try:
        health = chunk_health(layer)
    except ValueError as exc:
        out["why"] = f"its staged layer does not open ({' '.join(str(exc).split())[:160]})"
        return out
    if health is not None:
        out["frames"], out["damaged"] = health["readable"], health["damaged"]
    return out


class SweepStaging:
    """The staged files of one single-process sweep of root ``root_path``.

    ``settings``: JSON-able description that ``--resume`` must match (scene, frames, timing,
    worlds digest, ...). ``resume``: continue the run named by the progress file (ValueError
    with one line when there is none, it is damaged, or the settings differ). ``blocks``: batch
    layers of the run (one per device of a sweep over several devices: ``layers[k]``, published as
    ``final_layers[k]``; ``layer`` / ``final_layer`` are block 0's)."""

    def __init__(self, root_path, settings, resume=False, blocks=1, stored=True):
        self.root = os.path.abspath(os.fspath(root_path))
        self.stem = os.path.splitext(self.root)[0]
        self.progress_path = self.stem + ".sweep-partial.json"
        self.settings = json.loads(json.dumps(settings, sort_keys=True, default=str))
        self.resumed = bool(resume)
        if resume:
            self.token = self._load_progress()
        else:
            self.token = secrets.token_hex(4)
            self._remove_interrupted()
            os.makedirs(os.path.dirname(self.root), exist_ok=True)
            _atomic_json(self.progress_path, {"version": VERSION, "token": self.token, "settings": self.settings})
        self.layers = [f"{self.stem}.batch_{k:04d}.run{self.token}.usdc" for k in range(int(blocks))]
        self.final_layers = [f"{self.stem}.batch_{k:04d}.usdc" for k in range(int(blocks))]
        self.layer, self.final_layer = self.layers[0], self.final_layers[0]
        self.stored = bool(stored)
        """False (``--store none``): the run keeps no batch layer; :meth:`publish` moves none and
        :meth:`finish` removes an older sweep's layers of this root."""

    def _run_files(self):
        """Chunk files, indexes and staged layers of any run of this root: ``(path, token)``."""
        pattern = re.compile(re.escape(os.path.basename(self.stem)) + r"\.batch_\d{4}\.run([0-9A-Za-z]+)\.")
        for f in glob.glob(glob.escape(self.stem) + ".batch_*.run*"):
            m = pattern.match(os.path.basename(f))
            if m:
                yield f, m.group(1)

    def _load_progress(self):
        fix = "run the sweep without --resume to start it again"
        if not os.path.exists(self.progress_path):
            raise ValueError(f"--resume: no interrupted sweep at {self.root} ({os.path.basename(self.progress_path)} "
                             f"is missing: the last sweep there finished, or none ran); {fix}")
        if not os.path.isfile(self.progress_path):  # a FIFO would block for ever
            raise ValueError(f"--resume: {self.progress_path} is not a regular file; {fix}")
        try:
            with open(self.progress_path, encoding="utf-8") as f:
                data = json.load(f)
            token, saved = str(data["token"]), data["settings"]
            if data.get("version") != VERSION or not token.isalnum() or not isinstance(saved, dict):
                raise ValueError
        except (OSError, ValueError, KeyError, TypeError, AttributeError):
            raise ValueError(f"--resume: {self.progress_path} is damaged or not a warpsim sweep progress file; "
                             f"{fix}") from None
        for key in sorted(set(saved) | set(self.settings)):
            if saved.get(key) != self.settings.get(key):
                if key == "worlds":
                    raise ValueError("--resume: the sampled worlds differ from the ones the interrupted sweep started "
                                     "with (--vary, --set, --worlds, --sample or --seed changed); give its options, "
                                     f"or {fix}")
                if key == "blocks":  # the interrupted sweep ran on several devices (or on one)
                    old, new = saved.get(key), self.settings.get(key)
                    if old:
                        raise ValueError(f"--resume: the interrupted sweep ran its worlds in {len(old)} blocks "
                                         f"{old} on {len(old)} devices; give --devices with {len(old)} devices "
                                         f"again (e.g. --devices {','.join(['cpu'] * len(old))}) to resume it, "
                                         f"or {fix}")
                    raise ValueError(f"--resume: the interrupted sweep ran on one device, this one on {len(new)} "
                                     f"blocks of --devices; leave --devices out to resume it, or {fix}")
                raise ValueError(f"--resume: {key}={self.settings.get(key)!r} differs from the interrupted sweep's "
                                 f"{key}={saved.get(key)!r}; a resumed sweep keeps the settings it started with, or "
                                 f"{fix}")
        return token

    def _remove_interrupted(self):
        """Files of earlier interrupted runs (a run whose batch layer was never published)."""
        published = self._published_token()
        for f, token in self._run_files():
            if token != published:
                os.remove(f)

    def _published_token(self):
        """Token of the finished sweep's chunks (None when there is none or it predates tokens)."""
        if not os.path.exists(self.stem + ".batch_0000.usdc"):
            return None
        from pxr import Sdf

        try:
            layer = Sdf.Layer.OpenAsAnonymous(self.stem + ".batch_0000.usdc")
            named = str(dict(layer.customLayerData.get("warpsim", {})).get("chunkIndex", ""))
        except Exception:  # noqa: BLE001  (a damaged finished layer: keep nothing of it but the file itself)
            return None
        prefix = os.path.basename(self.stem) + ".batch_0000.run"
        return named[len(prefix):].split(".", 1)[0] if named.startswith(prefix) else None

    def resume_frame(self, block=0):
        """First frame to write: after the last completed chunk of block ``block``'s staged layer
        (0: none)."""
        layer = self.layers[block]
        if not self.stored or not os.path.exists(layer):
            return 0
        from pxr import Sdf

        from ..usd.validate import root_chunks, pxr_reason

        try:
            chunks = root_chunks(Sdf.Layer.OpenAsAnonymous(layer))
        except Exception as exc:  # noqa: BLE001  (Tf.ErrorException)
            raise ValueError(f"--resume: the interrupted sweep's layer {layer} does not open ("
                             f"{pxr_reason(exc, 120)}); run the sweep without --resume") from None
        return chunks[-1][1] + 1 if chunks else 0

    def abandon(self):
        """After a run that failed before writing anything: remove the progress file this run
        made (a ``--resume`` would find nothing to go on from); a run that wrote frames keeps it."""
        if self.resumed or any(token == self.token for _, token in self._run_files()):
            return
        if os.path.exists(self.progress_path):
            os.remove(self.progress_path)

    def partial(self, path):
        """A staging name for a file published whole at the end (e.g. the occupancy record)."""
        stem, ext = os.path.splitext(os.path.abspath(os.fspath(path)))
        return f"{stem}.run{self.token}{ext}"

    def publish(self, moves=()):
        """Switch to the new result: the batch layer onto its final name (every block's, in
        order), then ``moves`` [(staged path, final path)]; returns block 0's final layer path.
        Call :meth:`finish` after writing the table and root."""
        for staged, final in zip(self.layers, self.final_layers):
            if self.stored:
                os.replace(staged, final)
        for src, dst in moves:
            if os.path.exists(src):
                os.replace(src, dst)
        return self.final_layer

    def finish(self):
        """Remove the old run's chunk files, the layers of blocks an older run had beyond this
        run's, and the progress file."""
        for f, token in self._run_files():
            if token != self.token:
                os.remove(f)
        for f in glob.glob(glob.escape(self.stem) + ".batch_[0-9][0-9][0-9][0-9].usdc"):
            if f not in self.final_layers or not self.stored:
                os.remove(f)
        if os.path.exists(self.progress_path):
            os.remove(self.progress_path)
