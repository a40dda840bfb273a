"""Smoke on a MAC grid (Fedkiw, Stam and Jensen 2001): density and temperature carried by the
velocity, buoyancy from both, vorticity confinement, and a pressure projection around solids."""

from __future__ import annotations

import numpy as np
import warp as wp

from ..core.solver import SolverBase, check_change
from .advection import Advector
from .pressure import PressureSolver
from ..kernels import grid_forces as KF
from .mac_grid import check_finite, check_positive


class Smoke(SolverBase):
    """Buoyant smoke filling every non-solid cell of a MacGrid (a ``warpsim.core.solver.Solver``).

    Args:
        grid: the MacGrid (open the top, e.g. ``open_sides=("+y",)``, to let the plume leave).
        scheme: advection scheme (see Advector).
        density_buoyancy: alpha [m/s^2 per unit density]: smoke density pulls down.
        temperature_buoyancy: beta [m/s^2 per K above ambient]: heat lifts.
        ambient_temperature: T_ambient [K] (temperatures are stored as offsets from any reference).
        vorticity: vorticity-confinement strength epsilon (0 disables).
        tol, preconditioner: pressure solver settings (see PressureSolver).
        graph: on a CUDA device, record a step once as a CUDA graph (per dt) and replay it: the
            pressure solver then decides convergence on the device (``check_every=0``, so
            ``pressure.last_iterations`` is a device array) and the step reads nothing back
            (H100, 128^3, mg: the host's launches and residual read-backs doubled the 15 ms of GPU
            work to 29.5 ms per step). Ignored on the CPU.

    Attributes: ``density`` and ``temperature`` (wp.array3d at cell centres), ``pressure`` (PressureSolver).
    """

    def __init__(self, grid, scheme="maccormack", density_buoyancy=0.1, temperature_buoyancy=1.0,
                 ambient_temperature=0.0, vorticity=0.0, tol=1.0e-5, preconditioner="mg", graph=False):
        self.grid, self.device = grid, grid.device
        self.alpha = check_finite(density_buoyancy, "density_buoyancy")
        self.beta = check_finite(temperature_buoyancy, "temperature_buoyancy")
        self.ambient = check_finite(ambient_temperature, "ambient_temperature")
        self.vorticity = check_finite(vorticity, "vorticity")
        if self.vorticity < 0.0:
            raise ValueError(f"vorticity (confinement epsilon) must be >= 0, got {vorticity}")
        self.advector = Advector(grid, scheme)
        self.graph = bool(graph) and grid.device.is_cuda
        self.pressure = PressureSolver(grid, tol=tol, preconditioner=preconditioner,
                                       check_every=0 if self.graph else None)
        self._graphs = {}  # (dt, id of the pressure solver, source count) -> (captured step, solver)
        d, shape = self.device, grid.shape
        self.density = wp.zeros(shape, dtype=float, device=d)
        self.temperature = wp.full(shape, self.ambient, dtype=float, device=d)
        self._tmp = wp.zeros(shape, dtype=float, device=d)
        self._omega = wp.zeros(shape, dtype=wp.vec3, device=d)
        self._force = wp.zeros(shape, dtype=wp.vec3, device=d)
        self.sources: list[tuple] = []
        self.time = 0.0
        self.steps = 0
        grid.label(None)

    @property
    def state(self):
        """The MacGrid whose face velocities (``u``, ``v``, ``w``) this solver advances (the solver
        protocol's ``state``; the other fields are this object's attributes)."""
        return self.grid

    def notify_changed(self, what: str) -> None:
        """Announce an outside edit (``warpsim.core.solver.CHANGES``): the captured step graphs,
        which bake buoyancy, vorticity and source values into their launches, are dropped."""
        check_change(what, "Smoke")
        self._graphs.clear()

    def add_source(self, lower, upper, density=1.0, temperature=1.0) -> None:
        """Emit smoke in the box [lower, upper] [m]: every step the cells inside are raised to at
        least ``density`` and ``temperature`` [K]."""
        n = len(self.sources)
        lo = self.grid.point(lower, f"smoke source {n} lower")
        hi = self.grid.point(upper, f"smoke source {n} upper")
        if self.grid.dim == 2:
            lo[2], hi[2] = self.grid.origin[2], self.grid.origin[2] + self.grid.dx
        if any(h < l for l, h in zip(lo, hi)):
            raise ValueError(f"smoke source {n}: upper {hi} must not be below lower {lo}")
        rho = check_finite(density, f"smoke source {n} density")
        temp = check_finite(temperature, f"smoke source {n} temperature")
        if rho < 0.0:
            raise ValueError(f"smoke source {n} density must be >= 0, got {density}")
        self.sources.append((wp.vec3(*lo), wp.vec3(*hi), rho, temp))

    def _advect_scalar(self, f, dt):
        self.advector.advect(f, self._tmp, dt, "center")
        wp.copy(f, self._tmp)
        wp.launch(KF.zero_in_solid, self.grid.shape, inputs=[self.grid.solid_phi], outputs=[f], device=self.device)

    def step(self, dt) -> None:
        """Advance by ``dt`` [s]: sources, advection of density, temperature and velocity, buoyancy
        and vorticity confinement, projection (replayed as a CUDA graph with ``graph=True``)."""
        dt = check_positive(dt, "dt")
        if self.graph and self.steps > 0:  # the first step runs eagerly: kernels load outside any capture
            key = (dt, id(self.pressure), len(self.sources))
            if key not in self._graphs:
                with wp.ScopedCapture(device=self.device) as capture:
                    self._step_kernels(dt)
                # the solver stays referenced with its graph, so its id cannot be reused by a new one
                self._graphs[key] = (capture.graph, self.pressure)
            wp.capture_launch(self._graphs[key][0])
        else:
            self._step_kernels(dt)
        self.time += dt
        self.steps += 1

    def _step_kernels(self, dt):
        g, d = self.grid, self.device
        for lo, hi, rho, temp in self.sources:
            wp.launch(KF.source_in_box, g.shape, inputs=[lo, hi, rho, g.wp_origin, g.dx], outputs=[self.density],
                      device=d)
            wp.launch(KF.source_in_box, g.shape, inputs=[lo, hi, temp, g.wp_origin, g.dx],
                      outputs=[self.temperature], device=d)
        self._advect_scalar(self.density, dt)
        self._advect_scalar(self.temperature, dt)
        self.advector.advect_velocity(dt)
        wp.launch(KF.add_buoyancy, g.v.shape,
                  inputs=[self.density, self.temperature, self.alpha, self.beta, self.ambient, dt], outputs=[g.v],
                  device=d)
        if self.vorticity > 0.0:
            wp.launch(KF.compute_vorticity, g.shape, inputs=[*g.faces, g.dx], outputs=[self._omega], device=d)
            wp.launch(KF.vorticity_confinement_force, g.shape, inputs=[self._omega, self.vorticity, g.dx],
                      outputs=[self._force], device=d)
            for axis, f in enumerate(g.faces):
                if not (axis == 2 and g.dim == 2):
                    wp.launch(KF.add_cell_force, f.shape, inputs=[self._force, axis, dt], outputs=[f], device=d)
        self.pressure.project()

    def checkpoint(self) -> dict:
        """Everything needed to continue bit for bit (host copies)."""
        return {**self.grid.checkpoint(), "density": self.density.numpy(), "temperature": self.temperature.numpy(),
                "time": self.time, "steps": self.steps}

    def restore(self, data) -> None:
        """Inverse of :meth:`checkpoint` (same grid and settings)."""
        self.grid.restore(data)
        self.density.assign(np.asarray(data["density"]))
        self.temperature.assign(np.asarray(data["temperature"]))
        self.time, self.steps = float(data["time"]), int(data["steps"])

    def total_density(self) -> float:
        """Sum of density x cell volume (host read-back)."""
        return float(self.density.numpy().sum()) * self.grid.dx ** 3

    def density_centroid(self) -> np.ndarray:
        """Density-weighted mean position [m], shape (3,) (host read-back)."""
        rho = self.density.numpy()
        total = rho.sum()
        if total <= 0.0:
            return np.full(3, np.nan)
        return (self.grid.positions("center") * rho[..., None]).reshape(-1, 3).sum(axis=0) / total
