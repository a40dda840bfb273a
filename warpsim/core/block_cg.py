"""Preallocated block-Jacobi preconditioned conjugate gradients for ``warp.sparse`` BSR (3x3)
systems, with every scalar kept on the device so a solve can be captured in a graph.

The loop runs under ``wp.capture_while`` on a device-side condition (r.r > tol^2 and
iterations < max), so the same code runs eagerly, inside a CPU graph capture or inside a CUDA
graph (conditional nodes). Dot products are one grid-stride kernel with a block-wide tile sum
per block, then one block adding the blocks in a fixed order (``kernels.block_cg.cg_dots``,
``cg_sum_partials``: every add whose order could vary lands on a zero, so the iteration count and
result are bit-reproducible; ``wp.utils.array_inner`` allocates on CUDA, which a conditional
graph body may not), the product is ``warp.sparse.bsr_mv``; nothing is allocated per solve.
ClothImplicitEuler uses it by default, and ImplicitEuler on the CPU: ``warp.optim.linear.cg``'s tile-based dot products
take ~10 ms each on the CPU, and without host checks (check_every=0) it runs to the cap there.
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp
import warp.sparse as wps

from ..kernels import block_cg as K


class BlockCG:
    """Solve A x = b (A symmetric positive definite, ``warp.sparse`` BSR of wp.mat33) with the
    block-Jacobi preconditioner ``inverse`` (wp.mat33, (n,)), to |b - A x| <= max(atol, rtol |b|)
    or ``max_iterations``. ``A``, ``b``, ``x`` and ``inverse`` are bound at construction (their
    values may change between solves; the arrays may not)."""

    def __init__(self, A, b, x, inverse, rtol=1.0e-5, atol=0.0, max_iterations=200):
        if not (rtol >= 0.0 and atol >= 0.0 and (rtol > 0.0 or atol > 0.0)):
            raise ValueError(f"BlockCG tolerances rtol = {rtol}, atol = {atol}; need both >= 0 and one > 0")
        if int(max_iterations) < 1:
            raise ValueError(f"BlockCG max_iterations = {max_iterations}; it must be >= 1")
        self.A, self.b, self.x, self.inverse = A, b, x, inverse
        self.rtol, self.atol, self.max_iterations = float(rtol), float(atol), int(max_iterations)
        n, d = b.shape[0], b.device
        self.device = d
        self.n = n
        self.r = wp.zeros(n, dtype=wp.vec3, device=d)
        self.z = wp.zeros(n, dtype=wp.vec3, device=d)
        self.p = wp.zeros(n, dtype=wp.vec3, device=d)
        self.Ap = wp.zeros(n, dtype=wp.vec3, device=d)
        self.scalars = wp.zeros(6, dtype=float, device=d)
        """[r.z, r.r, p.Ap, (r.z)_new, tol^2, |b|^2] on the device."""
        self.iteration = wp.zeros(1, dtype=int, device=d)
        self.condition = wp.zeros(1, dtype=wp.int32, device=d)
        blocks = (n + K.DOT_BLOCK - 1) // K.DOT_BLOCK
        self._blocks = max(1, min(blocks, 1024) if d.is_cuda else blocks)
        self._partials = wp.zeros(2 * self._blocks, dtype=float, device=d)
        """Per-block partial dot products, added in block order (bit-reproducible)."""

    def _dots(self, a, b, slot_ab, c=None, d=None, slot_cd=-1):
        """scalars[slot_ab] += a . b (and scalars[slot_cd] += c . d); the slots were cleared by the
        kernel before. Block partial sums, then one block adds them in a fixed order (each slot gets
        one add, onto 0): bit-reproducible."""
        wp.launch(K.cg_dots, (self._blocks, K.DOT_BLOCK), inputs=[a, b, a if c is None else c, b if d is None else d,
                                                                  self._blocks * K.DOT_BLOCK, slot_cd,
                                                                  self._partials],
                  block_dim=K.DOT_BLOCK, device=self.device)
        wp.launch(K.cg_sum_partials, (1, K.DOT_BLOCK), inputs=[self._partials, self._blocks, slot_ab, slot_cd,
                                                               self.scalars],
                  block_dim=K.DOT_BLOCK, device=self.device)

    def _iteration(self):
        n, d = self.n, self.device
        wps.bsr_mv(self.A, self.p, self.Ap, alpha=1.0, beta=0.0)
        self._dots(self.p, self.Ap, 2)
        wp.launch(K.cg_update_x_r, n, inputs=[self.scalars, self.p, self.Ap, self.inverse, self.x, self.r, self.z],
                  device=d)
        self._dots(self.r, self.z, 3, self.r, self.r, 1)
        wp.launch(K.cg_update_p, n, inputs=[self.scalars, self.z, self.p], device=d)
        wp.launch(K.cg_end_iteration, 1, inputs=[self.scalars, self.max_iterations, self.iteration, self.condition],
                  device=d)

    def solve(self) -> None:
        """Run the solve (x starts at 0). Allocation-free and capturable; read the outcome with
        ``stats()`` afterwards (a host read-back)."""
        n, d = self.n, self.device
        wp.launch(K.cg_start, n, inputs=[self.b, self.inverse, self.x, self.r, self.z, self.p, self.scalars], device=d)
        self._dots(self.r, self.z, 0, self.r, self.r, 1)
        wp.launch(K.cg_init_scalars, 1, inputs=[self.scalars, self.rtol, self.atol, self.max_iterations,
                                                self.iteration, self.condition], device=d)
        wp.capture_while(self.condition, self._iteration)

    def stats(self) -> tuple:
        """(iterations, final residual |r| (recursive), absolute tolerance) of the last solve."""
        s = self.scalars.numpy().astype(np.float64)
        return int(self.iteration.numpy()[0]), math.sqrt(max(s[1], 0.0)), math.sqrt(max(s[4], 0.0))
