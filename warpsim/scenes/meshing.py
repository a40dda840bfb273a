"""Scene ``metaballs``: moving blobs that merge and split, meshed every frame by marching cubes."""

from __future__ import annotations

import numpy as np

from ..meshing.metaballs import Metaballs
from . import Scene, register_scene


METABALL_NODE_BYTES = 32.0
"""Bytes a grid node of the metaballs takes (measured while building on the CPU: 26 MB at
resolution 160, with pages of zeros not yet touched; the field and marching cubes' arrays are
about 10 bytes a node once meshed)."""


@register_scene("metaballs", "moving blobs that merge and split, meshed every frame (changing topology)", params={
    "resolution": (48, "grid nodes per axis of [-1, 1]^3"),
    "blobs": (5, "number of blobs"),
    "radius": (0.7, "blob radius of influence [m]"),
    "iso": (0.5, "iso value of the summed density"),
    "seed": (3, "random seed of the blob paths"),
}, fps=30.0)
class MetaballsScene(Scene):
    """The surface is a UsdGeom.Mesh whose face counts and indices are sampled only on frames
    where they change; points, normals and extent every frame."""

    smoke_params = {"resolution": 16}

    def build(self, p):
        from ..core.memory import check_build_memory

        n = int(p["resolution"])
        if n >= 4:  # (Metaballs names a smaller one)
            # the field (4 bytes a node), marching cubes' case and vertex index (5) and its blocks, rounded up
            check_build_memory("resolution", n, float(n) ** 3, "grid nodes", METABALL_NODE_BYTES,
                               lambda k: max(4, int(k ** (1 / 3))))
        self.blobs = Metaballs(p["resolution"], p["blobs"], p["radius"], p["iso"], seed=p["seed"], device=self.device)
        self.time = 0.0
        self.mesh = self.blobs.mesh(self.time)

    def declare(self, writer):
        writer.add_mesh("blobs", topology_changes=True, velocities=False, color=(0.9, 0.45, 0.2))
        writer.add_primvar("blobs", "normals", "normal3f[]", "vertex")

    def advance(self, frame_dt, substeps):
        self.time += frame_dt
        self.mesh = self.blobs.mesh(self.time)

    def frame_data(self):
        return {"blobs": self.mesh.usd_frame(normals=True)}

    def checkpoint(self):
        return {"time": np.float64(self.time)}

    def restore(self, data):
        self.time = float(data["time"])
        self.mesh = self.blobs.mesh(self.time)
