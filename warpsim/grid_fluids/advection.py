"""Advection of MAC-grid fields: semi-Lagrangian with an RK2 back-trace, MacCormack, or BFECC
(both with the min/max limiter of Selle et al. 2008), for face velocities and cell-centred scalars
(density, temperature, level sets)."""

from __future__ import annotations

import warp as wp

from ..kernels import advect as K
from .mac_grid import OFFSETS, check_positive

SCHEMES = ("semi_lagrangian", "maccormack", "bfecc")
_SCHEME_ID = {"maccormack": 0, "bfecc": 1}


class Advector:
    """Advects fields stored on a MacGrid through its face velocity.

    Args:
        grid: the MacGrid.
        scheme: ``"semi_lagrangian"`` (first order, diffusive), ``"maccormack"`` (2 semi-Lagrangian
            passes) or ``"bfecc"`` (3 passes); the last two are second order where smooth and clamped
            to the local extrema.

    Scratch buffers for the cell and the three face shapes are allocated here, once.
    """

    def __init__(self, grid, scheme="maccormack"):
        if scheme not in SCHEMES:
            raise ValueError(f"advection scheme {scheme!r} is unknown; use one of {SCHEMES}")
        self.grid, self.scheme, self.device = grid, scheme, grid.device
        self._scratch = {}
        for f in (grid.labels, *grid.faces):
            self._scratch[tuple(f.shape)] = [wp.zeros(f.shape, dtype=float, device=self.device) for _ in range(3)]
        self._velocity_out = [wp.zeros(f.shape, dtype=float, device=self.device) for f in grid.faces]

    def _sl(self, f_in, offset, vel, dt, f_out):
        g = self.grid
        wp.launch(K.advect_semi_lagrangian, f_in.shape,
                  inputs=[f_in, offset, *vel, g.wp_origin, g.dx, dt], outputs=[f_out], device=self.device)

    def advect(self, f_in, f_out, dt, where="center", velocity=None):
        """f_out = f_in carried by the velocity over ``dt`` [s]. ``where``: ``"center"``, ``"u"``,
        ``"v"`` or ``"w"`` (the field's staggering); ``velocity``: (u, v, w) face arrays, default the
        grid's. ``f_out`` must not alias ``f_in``."""
        dt = check_positive(dt, "advection dt")
        if where not in OFFSETS:
            raise ValueError(f"advect: where={where!r} is unknown; use one of {sorted(OFFSETS)}")
        if f_in.ptr == f_out.ptr:
            raise ValueError("advect: f_out must be a different array from f_in")
        shape = tuple(f_in.shape)
        if shape not in self._scratch:
            raise ValueError(f"advect: field shape {shape} matches none of the grid's cell or face shapes")
        vel = tuple(self.grid.faces) if velocity is None else tuple(velocity)
        offset = wp.vec3(*OFFSETS[where])
        if self.scheme == "semi_lagrangian":
            self._sl(f_in, offset, vel, dt, f_out)
            return f_out
        a, b, c = self._scratch[shape]
        g = self.grid
        self._sl(f_in, offset, vel, dt, a)  # f_hat
        self._sl(a, offset, vel, -dt, b)  # f_bar
        if self.scheme == "maccormack":
            src = f_in
        else:
            wp.launch(K.bfecc_midpoint, shape, inputs=[f_in, b], outputs=[c], device=self.device)
            src = c
        wp.launch(K.advect_limited, shape,
                  inputs=[src, f_in, a, b, _SCHEME_ID[self.scheme], offset, *vel, g.wp_origin, g.dx, dt],
                  outputs=[f_out], device=self.device)
        return f_out

    def advect_velocity(self, dt) -> None:
        """Self-advect the grid's face velocity over ``dt`` [s] (the old field carries all three)."""
        g = self.grid
        for f, out, where in zip(g.faces, self._velocity_out, "uvw"):
            if where == "w" and g.dim == 2:
                continue
            self.advect(f, out, dt, where)
        for f, out, where in zip(g.faces, self._velocity_out, "uvw"):
            if not (where == "w" and g.dim == 2):
                wp.copy(f, out)
