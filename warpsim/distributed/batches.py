"""Batches of a sweep on disk: split worlds, write a batch under a temporary name, publish it whole.

Layout beside the sweep's root ``sweep.usda``::

    sweep.batches/batch_0000/            one folder per finished batch: its USD layer (and any
    sweep.batches/batch_0001/            files that layer uses) plus ``rows.pkl``, its metric rows
    sweep.batches/batch_0002.tmp-.../    a batch being written (or left by a killed worker)

A batch is written into ``batch_NNNN.tmp-<host>-<pid>-<random>`` and ``os.replace``-d to
``batch_NNNN`` only once every file is closed, so a reader sees either no batch or a whole one; a
worker killed mid-batch leaves only a temporary folder that nothing references and
:func:`remove_stale` deletes. :func:`tree_checksum` (SHA-256 over relative names and contents) is
what the manifest records and what ``--resume`` checks before trusting a finished batch.
"""
from __future__ import annotations

import hashlib
import os
import pickle
import shutil
import socket
import uuid

__all__ = ["BATCH_ROWS", "batch_dir", "load_rows", "publish_batch", "remove_stale", "split_batches",
           "temp_batch_dir", "tree_checksum"]

BATCH_ROWS = "rows.pkl"
"""File in a batch folder holding its metric rows (a pickled list of dicts, exact values)."""


def split_batches(world_count, batch_size):
    """``[(first_world, count), ...]`` covering worlds ``0 .. world_count-1`` in order.

    Every batch holds ``batch_size`` worlds except possibly the last, which holds the rest.
    """
    if world_count < 1:
        raise ValueError(f"world count {world_count}: a sweep needs at least 1 world")
    if batch_size < 1:
        raise ValueError(f"--batch-size {batch_size}: it must be >= 1 (worlds per Ray task)")
    return [(first, min(batch_size, world_count - first)) for first in range(0, world_count, batch_size)]


def batches_root(out_path, name=None):
    """Folder holding the batch folders of the sweep whose root is ``out_path``: ``<stem>.batches``,
    or the folder ``name`` beside the root (a sweep re-run over a finished one writes to
    ``<stem>.batches-<token>`` until it is complete; its manifest names the folder)."""
    if name:
        return os.path.join(os.path.dirname(os.path.abspath(out_path)), os.path.basename(name))
    return os.path.splitext(os.path.abspath(out_path))[0] + ".batches"


def batch_dir(out_path, index, root=None):
    """Final folder of batch ``index`` of the sweep whose root is ``out_path`` (in ``root``, a
    folder name from :func:`batches_root`, when given)."""
    return os.path.join(batches_root(out_path, root), f"batch_{index:04d}")


def temp_batch_dir(final_dir):
    """A fresh temporary sibling of ``final_dir`` unique to this host and process (created)."""
    path = f"{final_dir}.tmp-{socket.gethostname()}-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    os.makedirs(path)
    return path


def tree_checksum(folder):
    """SHA-256 (hex) over every file below ``folder``: relative names and contents, sorted by name."""
    digest = hashlib.sha256()
    names = []
    for here, _dirs, files in os.walk(folder):
        names.extend(os.path.relpath(os.path.join(here, f), folder) for f in files)
    for name in sorted(names):
        digest.update(name.replace(os.sep, "/").encode() + b"\0")
        with open(os.path.join(folder, name), "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                digest.update(block)
        digest.update(b"\0")
    return digest.hexdigest()


def _fsync_tree(folder):
    for here, _dirs, files in os.walk(folder):
        for f in files:
            fd = os.open(os.path.join(here, f), os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)


def publish_batch(tmp_dir, final_dir, rows):
    """Write ``rows`` into ``tmp_dir``, then rename it to ``final_dir``; returns its checksum.

    An older ``final_dir`` (a batch run again because the manifest did not list it) is moved
    aside first and deleted after the rename, so ``final_dir`` is never a mixture of two runs.
    """
    with open(os.path.join(tmp_dir, BATCH_ROWS), "wb") as fh:
        pickle.dump(rows, fh, protocol=4)
    _fsync_tree(tmp_dir)
    checksum = tree_checksum(tmp_dir)
    old = None
    if os.path.exists(final_dir):
        old = f"{final_dir}.old-{uuid.uuid4().hex[:8]}"
        os.replace(final_dir, old)
    os.replace(tmp_dir, final_dir)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
    return checksum


def load_rows(final_dir):
    """The metric rows a finished batch folder holds."""
    with open(os.path.join(final_dir, BATCH_ROWS), "rb") as fh:
        return pickle.load(fh)


def remove_stale(out_path, name=None):
    """Delete temporary and moved-aside batch folders (left by killed workers); returns their count."""
    root = batches_root(out_path, name)
    if not os.path.isdir(root):
        return 0
    count = 0
    for name in os.listdir(root):
        if ".tmp-" in name or ".old-" in name:
            shutil.rmtree(os.path.join(root, name), ignore_errors=True)
            count += 1
    return count
