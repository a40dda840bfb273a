"""What a :class:`warpsim.particle_fluids.pbf.ParticleFluid` reports about itself: checkpoints to
continue bit for bit, and diagnostics (largest speed, density, compression, volume, momentum).

A mixin of ``ParticleFluid`` (its arrays: ``_x``, ``_v``, ``_ids``, ``_density``, ...); one job of the
fluid's, kept apart from its stepping.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np
import warp as wp

from ..core.errors import SimulationError
from ..kernels import sph as K

__all__ = ["FluidRecords"]


class FluidRecords:
    """Checkpoints and diagnostics of a ``ParticleFluid`` (see the module docstring)."""

    # the fluid's own, read and set here
    _x: Any
    _v: Any
    _ids: Any
    _density: Any
    _compression: Any
    _reduce: Any
    _stat_reduction: Any
    capacity: int
    device: Any
    emitters: list
    sinks: list
    max_speed: float
    particle_mass: float
    rest_density: float
    active_count: int
    time: float
    step_count: int
    frame_count: int
    next_id: int
    dropped: int

    def _build_neighbors(self, x, n: int, with_stats: int = 0) -> None:  # pragma: no cover - the fluid's own
        raise NotImplementedError

    # ----------------------------------------------------------------------------- checkpoints
    def checkpoint(self) -> dict:
        """Everything needed to continue bit for bit: NumPy arrays and scalars."""
        n = self.active_count
        out = {"positions": self._x.numpy()[:n].copy(), "velocities": self._v.numpy()[:n].copy(),
               "ids": self._ids.numpy()[:n].copy(), "time": self.time, "step_count": self.step_count,
               "frame_count": self.frame_count, "next_id": self.next_id, "dropped": self.dropped}
        out["emitters"] = np.array([[e.travel, e.emitted] for e in self.emitters], np.float64).reshape(-1, 2)
        out["sinks"] = np.array([s.removed for s in self.sinks], np.int64)
        return out

    def restore(self, data: dict) -> None:
        """Inverse of :meth:`checkpoint` (same fluid settings)."""
        x = np.asarray(data["positions"], np.float32).reshape(-1, 3)
        n = len(x)
        if n > self.capacity:
            raise ValueError(f"checkpoint holds {n} particles but the capacity is {self.capacity}")
        if len(data["emitters"]) != len(self.emitters) or len(data["sinks"]) != len(self.sinks):
            raise ValueError("checkpoint was made with a different number of emitters or sinks")
        self._x.assign(np.concatenate([x, self._x.numpy()[n:]]))
        self._v.assign(np.concatenate([np.asarray(data["velocities"], np.float32).reshape(-1, 3), self._v.numpy()[n:]]))
        self._ids.assign(np.concatenate([np.asarray(data["ids"], np.int32).reshape(-1), self._ids.numpy()[n:]]))
        self.active_count = n
        self.time = float(data["time"])
        self.step_count, self.frame_count = int(data["step_count"]), int(data["frame_count"])
        self.next_id, self.dropped = int(data["next_id"]), int(data["dropped"])
        for e, (travel, emitted) in zip(self.emitters, np.asarray(data["emitters"]).reshape(-1, 2)):
            e.travel, e.emitted = float(travel), int(emitted)
        for s, removed in zip(self.sinks, np.asarray(data["sinks"]).reshape(-1)):
            s.removed = int(removed)

    # ----------------------------------------------------------------------------- diagnostics
    def max_speed_now(self) -> float:
        """Largest particle speed [m/s] (one read-back); SimulationError when not finite or too fast."""
        n = self.active_count
        if n == 0:
            return 0.0
        self._reduce.assign(np.array([0.0, 3.0e38], np.float32))
        wp.launch(K.reduce_speed, n, inputs=[self._v[:n], self._x[:n]], outputs=[self._reduce], device=self.device)
        vmax, bad = (float(a) for a in self._reduce.numpy())
        if not math.isfinite(vmax) or vmax > self.max_speed:
            if vmax >= 1.0e30:
                k = int(bad)
                what = "a non-finite state"
            else:
                k = int(np.argmax(np.linalg.norm(self._v[: self.active_count].numpy(), axis=1)))
                what = f"speed {vmax:.4g} m/s > max_speed {self.max_speed:g}"
            raise SimulationError(
                f"fluid blew up at step {self.step_count} (t = {self.time:.6g} s): particle {k} has {what}. "
                "Remedy: lower cfl or max_dt, raise iterations, or check the boundaries.",
                step=self.step_count, time=self.time, particle=k, frame=self.frame_count + 1)
        return vmax

    def measure_density(self) -> np.ndarray:
        """Density [kg/m^3] of every active particle at the current positions, (active_count,)."""
        n = self.active_count
        if n == 0:
            return np.zeros(0, np.float32)
        self._build_neighbors(self._x[:n], n)
        return self._density[:n].numpy()

    def density_error(self) -> tuple:
        """(mean, max) relative compression max(rho/rho0 - 1, 0) at the current positions."""
        n = self.active_count
        if n == 0:
            return 0.0, 0.0
        self.measure_density()
        wp.launch(K.compression, n, inputs=[self._density, self.rest_density], outputs=[self._compression],
                  device=self.device)
        total, peak = self._stat_reduction.sum_max(self._compression, n).numpy()
        return float(total) / n, float(peak)

    def volume(self) -> float:
        """Density-based fluid volume sum_i m / max(rho_i, rho0) [m^3] at the current positions
        (shrinks exactly as the fluid compresses; surface particles count their rest volume)."""
        rho = self.measure_density().astype(np.float64)
        return float(np.sum(self.particle_mass / np.maximum(rho, self.rest_density)))

    def momentum(self) -> np.ndarray:
        """Total linear momentum [kg m/s], (3,), summed in float64."""
        return self.particle_mass * self._v[: self.active_count].numpy().astype(np.float64).sum(axis=0)
