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
        # (cell, particle) pairs; the stable radix sort needs room for 2n of each
        self._keys = wp.zeros(2 * n, dtype=int, device=d)
        self._ids = wp.zeros(2 * n, dtype=int, device=d)
        self.sorted_ids = self._ids[:n]  # particle indices by cell octant, then index (``count_cells``)
        self.octant_start = self.octant_count = None  # per octant: first entry in sorted_ids, length
        self._emitted = self._emit_offsets = None  # per-cell counts of an append and their prefix sums
        self._no_ids = wp.zeros(1, dtype=int, device=d)
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
        """cell_count (int, grid shape) = live particles per cell; ``sorted_ids`` = the live particles
        ordered by cell octant (flat cell index * 8 + x + 2 y + 4 z of the cell halves they lie in),
        then by index; ``octant_start`` / ``octant_count`` (cells * 8) = where each octant's run
        begins and its length; ``rank`` = a particle's order by index among its cell's live
        particles (-1 when dead). A stable sort, not an atomic counter, orders them, so the lists
        are the same on every run and device."""
        d, n = self.device, self.capacity
        octants = 8 * cell_count.size
        if self.octant_start is None or self.octant_start.shape[0] != octants:
            self.octant_start = wp.zeros(octants, dtype=int, device=d)
            self.octant_count = wp.zeros(octants, dtype=int, device=d)
        cell_count.zero_()
        self.octant_count.zero_()
        wp.launch(K.count_per_cell, n, inputs=[self.count, self.fields[position], self.alive, grid.wp_origin, grid.dx],
                  outputs=[cell_count, self.octant_count, self._keys, self._ids], device=d)
        wp.utils.radix_sort_pairs(self._keys, self._ids, n)
        wp.utils.array_scan(self.octant_count, self.octant_start, inclusive=False)
        wp.launch(K.rank_in_cell, n, inputs=[self._keys, self._ids, self.octant_start, self.octant_count],
                  outputs=[self.rank], device=d)

    def begin_append(self, cells: int):
        """Zeroed per-cell counts (int, (cells,)) for the counting pass of an append in cell order,
        and the array that receives their exclusive prefix sums (``scan_append``)."""
        if self._emitted is None or self._emitted.shape[0] != cells:
            self._emitted = wp.zeros(cells, dtype=int, device=self.device)
            self._emit_offsets = wp.zeros(cells, dtype=int, device=self.device)
        self._emitted.zero_()
        return self._emitted, self._emit_offsets

    def scan_append(self):
        """Offsets of each cell's new particles: exclusive prefix sum of the counting pass."""
        wp.utils.array_scan(self._emitted, self._emit_offsets, inclusive=False)

    def finish_append(self, next_id=None):
        """count += the appended particles; ``next_id`` (device int[1]) += those that fitted."""
        wp.launch(K.advance_count, 1, inputs=[self._emitted, self._emit_offsets, self.capacity],
                  outputs=[self.count, next_id if next_id is not None else self._no_ids], device=self.device)

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
