"""Geometric multigrid V-cycle for the MAC-grid pressure Poisson operator, used as a CG
preconditioner (McAdams, Sifakis & Teran 2010).

Level 0 is the solver's assembled operator (ghost-fluid weights included). Coarser levels halve the
cell counts (ceil(n / 2); 2D grids keep nz = 1), label a coarse cell AIR if any child is AIR, else
FLUID if any child is FLUID, else SOLID, and re-discretise the Poisson operator there with unit
weights: AIR neighbours are Dirichlet (q = 0), SOLID ones Neumann. The coarse system
A_2h e = R r uses R = (4 / 2^d) P^T with P cell-centred multilinear interpolation, which makes the
unit-weight coarse operator consistent with the fine one (A_h ~ h^2 (-Laplacian)).

The cycle is a fixed, symmetric linear map M r (so CG stays valid): from x = 0, ``smoothing``
red-black Gauss-Seidel sweeps (red then black) before the coarse correction and as many in the
reverse colour order after it; the coarsest level runs ``coarse_sweeps`` forward then as many
backward sweeps. Every level's arrays are allocated once here; ``assemble()`` refreshes the
coarse labels and coefficients from the fine labels (call it whenever they change).
"""

from __future__ import annotations

import warp as wp

from ..kernels import grid as K
from ..kernels import multigrid as KM


class _Level:
    def __init__(self, shape, device, labels=None, diag=None, plus=None):
        n = shape[0] * shape[1] * shape[2]
        fine = labels is not None
        self.shape = shape
        self.labels = labels if labels is not None else wp.zeros(shape, dtype=int, device=device)
        self.diag = diag if diag is not None else wp.zeros(shape, dtype=float, device=device)
        self.plus = plus if plus is not None else [wp.zeros(shape, dtype=float, device=device) for _ in range(3)]
        # right-hand side and correction (level 0 uses the caller's vectors instead)
        self.b = None if fine else wp.zeros(n, dtype=float, device=device)
        self.x = None if fine else wp.zeros(n, dtype=float, device=device)
        self.r = wp.zeros(n, dtype=float, device=device)  # residual b - A x


class Multigrid:
    """V-cycle preconditioner on the hierarchy below a PressureSolver's fine operator.

    Args:
        grid: the MacGrid (labels and open sides are read from it).
        diag, plus: the fine operator's coefficient arrays (grid shape), filled by the solver.
        smoothing: red-black Gauss-Seidel sweeps before and after each coarse correction (>= 1).
        coarse_sweeps: symmetric sweeps on the coarsest level (default: its largest dimension + 2).
        min_size: stop coarsening before a coarsened axis would drop below this many cells.
        air_first: coarse labels AIR if any child is AIR, else FLUID if any is FLUID, else SOLID (the
            coarse FLUID region never reaches into the fine AIR). ``False``: FLUID first, then AIR; near a free
            surface that V-cycle stalls or diverges as a stand-alone iteration (mean residual factor
            per cycle 0.9 on a 64^2 and 1.7 on a 32^3 liquid, against 0.32 and 0.22 with AIR first).
    """

    def __init__(self, grid, diag, plus, smoothing=2, coarse_sweeps=None, min_size=2, air_first=True):
        if int(smoothing) != smoothing or smoothing < 1:
            raise ValueError(f"multigrid smoothing must be a positive integer of sweeps, got {smoothing!r}")
        self.grid = grid
        self.device = d = grid.device
        self.smoothing = int(smoothing)
        self.air_first = int(bool(air_first))
        shape = tuple(grid.shape)
        self.coarsen = wp.vec3i(*[1 if s > 1 else 0 for s in shape])
        dims = sum(int(c) for c in self.coarsen)
        self.scale = 4.0 / 2.0**dims
        self.levels = [_Level(shape, d, grid.labels, diag, plus)]
        while True:
            s = self.levels[-1].shape
            nxt = tuple((n + 1) // 2 if c else n for n, c in zip(s, self.coarsen))
            if any(c and n < min_size for n, c in zip(nxt, self.coarsen)) or nxt == s:
                break
            self.levels.append(_Level(nxt, d))
        if coarse_sweeps is None:
            coarse_sweeps = max(self.levels[-1].shape) + 2
        self.coarse_sweeps = int(coarse_sweeps)

    @property
    def level_shapes(self):
        return [lv.shape for lv in self.levels]

    def assemble(self):
        """Coarse labels and unit-weight Poisson coefficients from the grid's current labels."""
        g, d = self.grid, self.device
        for fine, coarse in zip(self.levels[:-1], self.levels[1:]):
            wp.launch(KM.coarsen_labels, coarse.shape, inputs=[fine.labels, self.coarsen, self.air_first],
                      outputs=[coarse.labels], device=d)
            wp.launch(K.pressure_coefficients, coarse.shape, inputs=[coarse.labels, g.no_phi, 0, g.open_mask],
                      outputs=[coarse.diag, *coarse.plus], device=d)

    # ------------------------------------------------------------------ the cycle
    def _sweep(self, lv, b, x, color, first):
        wp.launch(K.gauss_seidel_color, lv.shape, inputs=[lv.diag, *lv.plus, b, color, int(first)], outputs=[x],
                  device=self.device)

    def apply(self, b, x):
        """x = M b for flat arrays of shape (cell_count,) (x must not alias b)."""
        d, levels = self.device, self.levels
        bs = [b] + [lv.b for lv in levels[1:]]
        xs = [x] + [lv.x for lv in levels[1:]]
        last = len(levels) - 1
        for l in range(last):
            lv = levels[l]
            for s in range(self.smoothing):
                self._sweep(lv, bs[l], xs[l], 0, s == 0)  # the first red sweep starts from x = 0
                self._sweep(lv, bs[l], xs[l], 1, False)
            wp.launch(K.apply_pressure_operator, lv.shape, inputs=[lv.diag, *lv.plus, xs[l], bs[l], -1.0, 1.0],
                      outputs=[lv.r], device=d)
            nxt = levels[l + 1]
            wp.launch(KM.restrict_residual, nxt.shape, inputs=[lv.labels, nxt.labels, lv.r, self.coarsen, self.scale],
                      outputs=[bs[l + 1]], device=d)
        lv = levels[last]
        for s in range(self.coarse_sweeps):
            self._sweep(lv, bs[last], xs[last], 0, s == 0)
            self._sweep(lv, bs[last], xs[last], 1, False)
        for _ in range(self.coarse_sweeps):
            self._sweep(lv, bs[last], xs[last], 1, False)
            self._sweep(lv, bs[last], xs[last], 0, False)
        for l in range(last - 1, -1, -1):
            lv = levels[l]
            wp.launch(KM.prolong_add, lv.shape, inputs=[lv.labels, levels[l + 1].labels, xs[l + 1], self.coarsen],
                      outputs=[xs[l]], device=d)
            for _ in range(self.smoothing):
                self._sweep(lv, bs[l], xs[l], 1, False)
                self._sweep(lv, bs[l], xs[l], 0, False)
        return x
