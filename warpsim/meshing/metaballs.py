"""Moving metaballs meshed by marching cubes: the blobs merge and split, so the mesh's topology
changes from frame to frame (used by the ``metaballs`` scene and ``examples/metaballs.py``)."""

from __future__ import annotations

import numpy as np
import warp as wp

from ..kernels.implicit_fields import metaball_density
from .marching_cubes import MarchingCubes


class Metaballs:
    """``blob_count`` Wyvill blobs of radius ``radius`` [m] circling through [-1, 1]^3 m on
    Lissajous paths; ``mesh(t)`` samples their summed density on a ``resolution``^3 grid and
    returns the iso-``iso`` surface (one reusable MarchingCubes, no reallocation per frame)."""

    def __init__(self, resolution=64, blob_count=5, radius=0.7, iso=0.5, seed=3, device=None):
        if int(resolution) < 4:
            raise ValueError(f"metaballs resolution {resolution} must be >= 4 grid nodes per axis")
        if int(blob_count) < 1:
            raise ValueError(f"metaballs blob_count {blob_count} must be >= 1")
        if not radius > 0.0:
            raise ValueError(f"metaballs radius {radius} must be > 0 [m]")
        self.device = wp.get_device(device)
        self.iso = float(iso)
        self.lower = (-1.0, -1.0, -1.0)
        h = 2.0 / (int(resolution) - 1)
        self.spacing = (h, h, h)
        shape = (int(resolution),) * 3
        rng = np.random.default_rng(seed)
        self.phase = rng.uniform(0.0, 2.0 * np.pi, (blob_count, 3))
        self.omega = rng.uniform(0.6, 1.4, (blob_count, 1)) * np.array([1.0, 1.3, 0.7])  # [rad/s]
        self.field = wp.zeros(shape, dtype=wp.float32, device=self.device)
        self.centers = wp.zeros(blob_count, dtype=wp.vec3, device=self.device)
        self.radii = wp.full(blob_count, float(radius), dtype=wp.float32, device=self.device)
        # inside="above": the blobs are where the density exceeds iso; close_boundary caps any
        # blob that pokes out of the box.
        self.mesher = MarchingCubes(shape, self.spacing, self.lower, self.device, inside="above", close_boundary=True)

    def blob_centers(self, t: float) -> np.ndarray:
        """Blob centres [m] at time t [s], shape (blob_count, 3)."""
        return 0.55 * np.sin(self.omega * t + self.phase)

    def mesh(self, t: float):
        """Move the blobs to time t [s] and re-mesh; returns a MarchingCubesResult."""
        self.centers.assign(self.blob_centers(t).astype(np.float32))
        metaball_density(self.centers, self.radii, self.field, self.lower, self.spacing)
        return self.mesher.mesh(self.field, self.iso)
