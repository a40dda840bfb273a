"""A batch's frames on their way to the host while the next frames step (CUDA devices).

:meth:`HostCopies.start` snapshots the arrays on the device (a device-to-device copy on the
stepping stream: the next step may then overwrite them) and copies the snapshot into pinned host
buffers on a stream of its own; :meth:`HostCopies.wait` waits for that copy and returns NumPy views
of the buffers. Two sets of buffers alternate (double-buffered): the views of frame f stay valid
while frame f + 1 is copied, and are reused by frame f + 2 (whose ``start`` comes after frame f's
host work, so nothing still read is overwritten). Allocates once, in the constructor.
"""
from __future__ import annotations

import warp as wp

__all__ = ["HostCopies"]


class HostCopies:
    """Double-buffered copies of ``arrays`` (``wp.array`` on one CUDA device) to pinned host memory."""

    def __init__(self, arrays, device):
        self.device = wp.get_device(device)
        if not self.device.is_cuda:
            raise ValueError(f"HostCopies is for CUDA devices; {self.device} arrays are on the host already")
        self.snapshots = [[wp.empty_like(a) for a in arrays] for _ in range(2)]
        self.host = [[wp.empty(a.shape, dtype=a.dtype, device="cpu", pinned=True) for a in arrays] for _ in range(2)]
        self.stream = wp.Stream(self.device)
        self.copied = [wp.Event(self.device) for _ in range(2)]
        self.ready = [wp.Event(self.device) for _ in range(2)]
        self._next = 0

    def start(self, arrays) -> int:
        """Begin copying ``arrays`` (the constructor's, as they are now) to the host; returns the
        ticket :meth:`wait` takes."""
        k = self._next
        self._next ^= 1
        stepping = wp.get_stream(self.device)
        for src, dst in zip(arrays, self.snapshots[k]):
            wp.copy(dst, src, stream=stepping)  # after the frame's launches, before the next frame's
        stepping.record_event(self.ready[k])
        self.stream.wait_event(self.ready[k])
        for src, dst in zip(self.snapshots[k], self.host[k]):
            wp.copy(dst, src, stream=self.stream)
        self.stream.record_event(self.copied[k])
        return k

    def wait(self, ticket) -> list:
        """NumPy views of the host buffers of ``ticket`` once its copy is done (valid until the
        ticket after next is started)."""
        wp.synchronize_event(self.copied[ticket])
        return [h.numpy() for h in self.host[ticket]]
