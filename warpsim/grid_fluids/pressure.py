"""Pressure projection on a MAC grid: a matrix-free Poisson operator solved with
``warp.optim.linear.cg`` and a Jacobi, symmetric red-black Gauss-Seidel or geometric multigrid
(V-cycle, ``warpsim.grid_fluids.multigrid``) preconditioner.

The solver works with q = p dt / (rho dx) [m/s] (see kernels/grid.py): after ``project()`` the
FLUID cells' net outflow ``dx div(u)`` equals minus the CG residual, so
``||div(u)||_2 <= tol ||div(u_before)||_2`` up to float32 round-off.
"""

from __future__ import annotations

import numpy as np
import warp as wp
from warp.optim.linear import LinearOperator, cg

from .multigrid import Multigrid
from ..core.reduction import FixedOrderReduction
from ..kernels import grid as K
from ..kernels import multigrid as KM
from .mac_grid import check_positive

PRECONDITIONERS = ("jacobi", "rbgs", "mg", None)


class PressureSolver:
    """Makes a MacGrid's velocity divergence-free in its FLUID cells.

    Args:
        grid: the MacGrid (its labels must be current).
        tol: CG tolerance relative to the norm of the right-hand side (the initial net outflow).
        max_iterations: CG iteration cap (default: 4 x the largest grid dimension x dim, at least 200).
        preconditioner: ``"jacobi"`` (diagonal), ``"rbgs"`` (symmetric red-black Gauss-Seidel,
            3 half-sweeps per application; fewer iterations), ``"mg"`` (a multigrid V-cycle with red-black
            Gauss-Seidel smoothing; iterations nearly independent of the grid size) or None.
        check_every: CG convergence check interval (each check reads the residual on the host; default
            10, or 2 with ``"mg"``, whose iterations are few and costly).
        mg_smoothing: red-black Gauss-Seidel sweeps before and after each coarse correction (``"mg"``).
        atol: absolute floor on the residual norm [m/s] (default 1e-7 sqrt(cell_count): float32 noise of
            an already divergence-free field, so such a field costs no iterations).
        refine: after CG stops, run a second warm-started CG pass that restarts from the true residual
            (float32 drift of CG's recursive residual otherwise leaves ||div|| up to ~5x above tol).

    Attributes: ``q`` (pressure p dt / (rho dx) [m/s], flat, shape (cell_count,)), ``last_iterations``,
    ``last_residual`` (the CG residual norm, = ||dx div(u)|| after projection), ``last_tolerance``. With
    ``check_every=0`` (no host read-back, CUDA-graph capturable) these are device arrays: the first
    pass's iteration count and the squared residual and tolerance of the last pass.
    """

    def __init__(self, grid, tol=1.0e-5, max_iterations=None, preconditioner="jacobi", check_every=None, atol=None,
                 refine=True, mg_smoothing=2):
        self.grid = grid
        self.device = grid.device
        self.tol = check_positive(tol, "pressure tol")
        if self.tol >= 1.0:
            raise ValueError(f"pressure tol must be < 1 (relative residual), got {tol}")
        if preconditioner not in PRECONDITIONERS:
            raise ValueError(f"pressure preconditioner {preconditioner!r} is unknown; use one of {PRECONDITIONERS}")
        if max_iterations is None:
            max_iterations = max(200, 4 * max(grid.shape) * grid.dim)
        if int(max_iterations) != max_iterations or max_iterations < 1:
            raise ValueError(f"pressure max_iterations must be a positive integer, got {max_iterations!r}")
        self.max_iterations = int(max_iterations)
        self.preconditioner = preconditioner
        self.refine = bool(refine)
        n, d, shape = grid.cell_count, self.device, grid.shape
        self.atol = 1.0e-7 * float(np.sqrt(n)) if atol is None else check_positive(atol, "pressure atol")
        self.diag = wp.zeros(shape, dtype=float, device=d)
        self.plus = [wp.zeros(shape, dtype=float, device=d) for _ in range(3)]
        self.div = wp.zeros(shape, dtype=float, device=d)
        self.rhs = wp.zeros(n, dtype=float, device=d)
        self.q = wp.zeros(n, dtype=float, device=d)
        # (sum of rhs, FLUID cells, FLUID faces on AIR), summed in a fixed order (the same bits every run)
        self._domain_reduction = FixedOrderReduction(3, device=d)
        self._sums = self._domain_reduction.result
        self._first_iterations = wp.zeros(1, dtype=int, device=d)  # check_every=0: first CG pass's count
        self._z = wp.zeros(n, dtype=float, device=d)
        self._diag_flat = self.diag.reshape((n,))
        # On the CPU, one "batch" spanning all cells makes warp.optim.linear's dot products run as
        # plain loops instead of 512-wide emulated tiles (about 10x faster per CG iteration there).
        batch = None if d.is_cuda else wp.array([0, n], dtype=int, device=d)
        self.operator = LinearOperator((n, n), float, d, self._matvec, batch_offsets=batch)
        self._M = self.multigrid = None
        if check_every is None:
            check_every = 2 if preconditioner == "mg" else 10
        if preconditioner == "mg":
            self.multigrid = Multigrid(grid, self.diag, self.plus, smoothing=mg_smoothing)
            self._mg_in = wp.zeros(n, dtype=float, device=d)
            self._mean_reduction = FixedOrderReduction(1, device=d)  # FLUID sum of x, fixed order
            self._mean = self._mean_reduction.result
            self._M = LinearOperator((n, n), float, d, self._mg, batch_offsets=batch)
        elif preconditioner == "jacobi":
            self._M = LinearOperator((n, n), float, d, self._jacobi, batch_offsets=batch)
        elif preconditioner == "rbgs":
            self._M = LinearOperator((n, n), float, d, self._rbgs, batch_offsets=batch)
        self._cg = cg(self.operator, self.rhs, self.q, tol=self.tol, atol=self.atol, maxiter=self.max_iterations,
                      M=self._M, check_every=check_every, run=False)
        self.last_iterations, self.last_residual, self.last_tolerance = 0, 0.0, 0.0

    # ------------------------------------------------------------------ operator pieces
    def _matvec(self, x, y, z, alpha, beta):
        wp.launch(K.apply_pressure_operator, self.grid.shape,
                  inputs=[self.diag, *self.plus, x, y, float(alpha), float(beta)], outputs=[z], device=self.device)

    def _jacobi(self, x, y, z, alpha, beta):
        wp.launch(K.apply_jacobi, x.shape[0], inputs=[self._diag_flat, x, y, float(alpha), float(beta)],
                  outputs=[z], device=self.device)

    def _rbgs(self, x, y, z, alpha, beta):
        shape, s = self.grid.shape, self._z
        # SGS in red-black order from z = 0: red, black, red (each half sweep reads only the other colour)
        for color, first in ((0, 1), (1, 0), (0, 0)):
            wp.launch(K.gauss_seidel_color, shape, inputs=[self.diag, *self.plus, x, color, first], outputs=[s],
                      device=self.device)
        wp.launch(K.axpby, s.shape[0], inputs=[s, y, float(alpha), float(beta)], outputs=[z], device=self.device)

    def _project_closed(self, x, out):
        """out = x minus its FLUID mean when the domain is closed (all-Neumann: A's null space)."""
        g, d = self.grid, self.device
        reduction = self._mean_reduction
        wp.launch(KM.sum_fluid_closed, reduction.slots, inputs=[g.labels, self._sums, x],
                  outputs=[reduction.partials], device=d)
        reduction.finish()
        wp.launch(KM.remove_fluid_mean_closed, g.shape, inputs=[g.labels, self._sums, self._mean, x], outputs=[out],
                  device=d)

    def _mg(self, x, y, z, alpha, beta):
        # closed domains: P V P with P the projection off constants, so the V-cycle (whose singular
        # coarse levels amplify the constant mode) stays symmetric and CG sees no null-space growth
        self._project_closed(x, self._mg_in)
        self.multigrid.apply(self._mg_in, self._z)
        self._project_closed(self._z, self._z)
        wp.launch(K.axpby, self._z.shape[0], inputs=[self._z, y, float(alpha), float(beta)], outputs=[z],
                  device=self.device)

    def precondition(self, x, out):
        """out = M x for flat arrays of shape (cell_count,) (the preconditioner; identity when None)."""
        if self._M is None:
            wp.copy(out, x)
        else:
            self._M.matvec(x, x, out, 1.0, 0.0)
        return out

    def assemble(self, phi=None) -> None:
        """Fill the operator's coefficients from the grid labels (and the ghost-fluid weights of
        ``phi``, the liquid's signed distance at cell centres [m], when given)."""
        g = self.grid
        use = phi is not None
        wp.launch(K.pressure_coefficients, g.shape, inputs=[g.labels, phi if use else g.no_phi, int(use),
                                                            g.open_mask], outputs=[self.diag, *self.plus],
                  device=self.device)
        if self.multigrid is not None:
            self.multigrid.assemble()

    def apply(self, x, out):
        """out = A x for flat arrays of shape (cell_count,) (the assembled operator)."""
        self._matvec(x, x, out, 1.0, 0.0)
        return out

    # ------------------------------------------------------------------ projection
    def project(self, phi=None, target=None):
        """Solve for the pressure and subtract its gradient from the face velocities.

        Call after ``grid.label(...)``; ``phi`` gives the free surface position for the ghost-fluid
        boundary (None: the surface lies on the AIR cell centres). ``target`` (cell array [1/s], grid
        shape) is the divergence to leave in the FLUID cells instead of 0 (in a closed domain its mean
        over the fluid is removed). Returns the CG iteration count."""
        g, d = self.grid, self.device
        use = target is not None
        if use and tuple(target.shape) != tuple(g.shape):
            raise ValueError(f"pressure target has shape {tuple(target.shape)}; it must be the grid's {g.shape}")
        g.enforce_boundaries()
        self.assemble(phi)
        wp.launch(K.compute_divergence, g.shape, inputs=[g.u, g.v, g.w, g.labels, g.dx], outputs=[self.div],
                  device=d)
        wp.launch(K.pressure_rhs, g.shape, inputs=[self.div, g.labels, target if use else g.no_phi, int(use), g.dx],
                  outputs=[self.rhs], device=d)
        reduction = self._domain_reduction
        wp.launch(K.fluid_sums, reduction.slots, inputs=[g.labels, g.open_mask, self.rhs],
                  outputs=[reduction.partials], device=d)
        reduction.finish()
        wp.launch(K.remove_rhs_mean, g.shape, inputs=[g.labels, self._sums], outputs=[self.rhs], device=d)
        # CG's recursively updated residual drifts from the true one in float32; a second, warm-started
        # pass restarts from the true residual b - A q (and stops at once when that already meets tol).
        self.q.zero_()  # a cold start keeps float32 round-off proportional to this step's rhs
        first = result = self._cg()
        if isinstance(first[0], wp.array):  # check_every=0: device-side counters, which the refinement
            wp.copy(self._first_iterations, first[0])  # pass reuses: keep the first pass's count
        if self.refine:
            result = self._cg()
        if isinstance(result[0], wp.array):
            self.last_iterations = self._first_iterations
            self.last_residual, self.last_tolerance = result[1], result[2]
        else:
            self.last_iterations = int(result[0]) + (int(first[0]) if self.refine else 0)
            self.last_residual, self.last_tolerance = float(result[1]), float(result[2])
        use = phi is not None
        for axis, f in enumerate(g.faces):
            wp.launch(K.subtract_pressure_gradient, f.shape,
                      inputs=[self.q, g.labels, phi if use else g.no_phi, int(use), g.open_mask, axis], outputs=[f],
                      device=d)
        return self.last_iterations

    def pressure(self, dt, density=1000.0) -> np.ndarray:
        """Physical pressure p = q rho dx / dt [Pa] at cell centres, shape (nx, ny, nz) (host copy)."""
        dt = check_positive(dt, "dt")
        density = check_positive(density, "density")
        return self.q.numpy().reshape(self.grid.shape) * density * self.grid.dx / dt
