"""Fixed-capacity particle storage on a MAC grid with per-cell counts and compaction (shared by the
particle level set and FLIP). Arrays keep their identity; ``count`` (device int[1]) holds how many
leading entries are in use, and an ``alive`` float field marks deleted entries with 0."""

from __future__ import annotations

import numpy as np
import warp as wp

from ..kernels import grid_particles as K


class GridParticles:
    """Particles with named per-particle fields.

    Args:
        capacity: maximum particle count.
        vec3_fields / float_fields / int_fields: field names; ``alive`` names the float field whose 0
            means deleted.
        device: Warp device.
    """

    def __init__(self, capacity, vec3_fields, float_fields, alive, device, int_fields=()):
        if int(capacity) != capacity or capacity < 1:
            raise ValueError(f"particle capacity must be a positive integer, got {capacity!r}")
        if alive not in float_fields:
            raise ValueError(f"alive field {alive!r} must be one of the float fields {float_fields}")
        self.capacity, self.device, self.alive_name = int(capacity), device, alive
        n, d = self.capacity, device
        self.fields = {name: wp.zeros(n, dtype=wp.vec3, device=d) for name in vec3_fields}
        self.fields.update({name: wp.zeros(n, dtype=float, device=d) for name in float_fields})
        self.fields.update({name: wp.zeros(n, dtype=int, device=d) for name in int_fields})
        self._spare_int = wp.zeros(n, dtype=int, device=d) if int_fields else None
        self._spare_vec3 = wp.zeros(n, dtype=wp.vec3, device=d)
        self._spare_float = wp.zeros(n, dtype=float, device=d)
        self.count = wp.zeros(1, dtype=int, device=d)
        self.rank = wp.zeros(n, dtype=int, device=d)
        self._flags = wp.zeros(n, dtype=int, device=d)
        self._scan = wp.zeros(n, dtype=int, device=d)

    def __getitem__(self, name):
        return self.fields[name]

    @property
    def alive(self):
        return self.fields[self.alive_name]

    def clear(self):
        self.count.zero_()
        self.alive.zero_()

    def count_cells(self, grid, cell_count, position="x"):
        """cell_count (int, grid shape) = live particles per cell; ``rank`` = order within the cell."""
        cell_count.zero_()
        wp.launch(K.count_per_cell, self.capacity,
                  inputs=[self.count, self.fields[position], self.alive, grid._wp_origin, grid.dx],
                  outputs=[cell_count, self.rank], device=self.device)

    def cull(self, max_per_cell):
        """Delete particles ranked >= max_per_cell in their cell (call ``count_cells`` first)."""
        wp.launch(K.cull_crowded, self.capacity, inputs=[self.rank, int(max_per_cell)], outputs=[self.alive],
                  device=self.device)

    def compact(self):
        """Move live particles to the front, in order; count = live particles."""
        d, n = self.device, self.capacity
        wp.launch(K.mark_live, n, inputs=[self.count, self.alive], outputs=[self._flags], device=d)
        wp.utils.array_scan(self._flags, self._scan, inclusive=True)
        for f in self.fields.values():
            if f.dtype == wp.vec3:
                wp.launch(K.compact_vec3, n, inputs=[self._flags, self._scan, f], outputs=[self._spare_vec3], device=d)
                wp.copy(f, self._spare_vec3)
            elif f.dtype == wp.int32:
                wp.launch(K.compact_int, n, inputs=[self._flags, self._scan, f], outputs=[self._spare_int], device=d)
                wp.copy(f, self._spare_int)
            else:
                wp.launch(K.compact_float, n, inputs=[self._flags, self._scan, f], outputs=[self._spare_float],
                          device=d)
                wp.copy(f, self._spare_float)
        wp.launch(K.set_live_count, 1, inputs=[self._scan], outputs=[self.count], device=d)

    def checkpoint(self, prefix="") -> dict:
        """Host copies of every field and the count, keyed ``prefix + name``."""
        out = {prefix + name: f.numpy() for name, f in self.fields.items()}
        out[prefix + "count"] = self.count.numpy()
        return out

    def restore(self, data, prefix=""):
        """Inverse of :meth:`checkpoint`."""
        for name, f in self.fields.items():
            values = np.asarray(data[prefix + name])
            if values.shape[0] != self.capacity:
                raise ValueError(f"checkpoint field {name!r} holds {values.shape[0]} particles; capacity is "
                                 f"{self.capacity}")
            f.assign(values)
        self.count.assign(np.asarray(data[prefix + "count"]))

    def live_count(self) -> int:
        """Live particles (host read-back)."""
        n = min(int(self.count.numpy()[0]), self.capacity)
        return int(np.count_nonzero(self.alive.numpy()[:n]))

    def numpy(self, name) -> np.ndarray:
        """Host copy of a field over the live particles."""
        n = min(int(self.count.numpy()[0]), self.capacity)
        keep = self.alive.numpy()[:n] != 0.0
        return self.fields[name].numpy()[:n][keep]
