"""Fixed-order (bit-reproducible) reductions over device arrays: ``FixedOrderReduction`` holds the
partial sums of ``kernels/reduce.py`` and folds them to one row; no float atomics, so the result
is the same run to run on every device. A reduction allocates at construction only (steps that use
it capture in CUDA graphs)."""

from __future__ import annotations

import warp as wp

from ..kernels import reduce as K

CPU_SLOTS = 4096  # threads of the first stage on the CPU (each sums every 4096-th value)
CUDA_SLOTS = 32768  # on GPUs: enough threads to keep the device busy (a 128^3 grid: 64 values each)
DEFAULT_GROUP = 64  # rows folded into one by each later stage


class FixedOrderReduction:
    """Sums (and maxima) of ``columns`` quantities in a fixed order.

    A stage's kernel writes its per-slot partials into :attr:`partials` (shape (slots, columns):
    slot s holds the values at indices s, s + slots, ... in increasing order); :meth:`finish`
    folds them and leaves the totals in :attr:`result`, shape (columns,), on the device.

    Args:
        columns: quantities reduced side by side.
        first_max_column: columns from this one on are maxima, the ones before sums (default: all sums).
        slots: rows of :attr:`partials` (threads of the first stage; default 4096 on the CPU, 32768 on
            GPUs).
        group: rows folded into one per later stage.
        device: Warp device.
    """

    def __init__(self, columns: int, first_max_column: int | None = None, slots: int | None = None,
                 group: int = DEFAULT_GROUP, device=None):
        self.device = wp.get_device(device)
        if slots is None:
            slots = CUDA_SLOTS if self.device.is_cuda else CPU_SLOTS
        if int(columns) != columns or columns < 1:
            raise ValueError(f"reduction columns must be a positive integer, got {columns!r}")
        if int(slots) != slots or slots < 1 or int(group) != group or group < 2:
            raise ValueError(f"reduction slots must be >= 1 and group >= 2 (integers), got {slots!r}, {group!r}")
        self.columns = int(columns)
        self.first_max_column = self.columns if first_max_column is None else int(first_max_column)
        self.group = int(group)
        self.partials = wp.zeros((int(slots), self.columns), dtype=float, device=self.device)
        self._levels = []
        rows = int(slots)
        while rows > 1:
            rows = (rows + self.group - 1) // self.group
            self._levels.append(wp.zeros((rows, self.columns), dtype=float, device=self.device))
        last = self._levels[-1] if self._levels else self.partials
        self.result = last.reshape((self.columns,))

    @property
    def slots(self) -> int:
        return self.partials.shape[0]

    def finish(self) -> wp.array:
        """Fold the partials into :attr:`result` (columns,) and return it."""
        src = self.partials
        for dst in self._levels:
            wp.launch(K.reduce_rows, (dst.shape[0], self.columns), inputs=[src, self.group, self.first_max_column],
                      outputs=[dst], device=self.device)
            src = dst
        return self.result

    def sum_max(self, values: wp.array, count: int) -> wp.array:
        """(sum, max) of values[:count] (a float array) in a fixed order; needs columns == 2 and
        first_max_column == 1. Returns :attr:`result` on the device."""
        if self.columns != 2 or self.first_max_column != 1:
            raise ValueError("sum_max needs a FixedOrderReduction(columns=2, first_max_column=1)")
        wp.launch(K.sum_max_strided, self.slots, inputs=[values, int(count)], outputs=[self.partials],
                  device=self.device)
        return self.finish()
