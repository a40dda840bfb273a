"""A liquid's surface mesh every frame: particles -> Zhu-Bridson field on a grid -> marching cubes.

Example::

    surface = FluidSurface(fluid)              # grid over the fluid's domain box
    result = surface.mesh()                    # MarchingCubesResult (views, valid until next call)
    vertices, faces, normals = result.numpy()
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from ..core import checks
from ..kernels import fluid_surface as K
from ..meshing.marching_cubes import MarchingCubes

__all__ = ["FluidSurface"]


class FluidSurface:
    """Surface of a :class:`warpsim.ParticleFluid` on a fixed grid.

    Args:
        fluid: the ParticleFluid.
        cell: grid node spacing [m]; default the fluid's particle spacing.
        lower, upper: grid box [m]; default the fluid's domain (required when it has none).
        radius: particle radius r of the field phi = |p - xbar| - r [m]; default 0.6 spacing.
        support: Zhu-Bridson averaging radius R [m]; default 2 spacings.

    The field is negative inside the liquid; the mesh closes where the liquid touches the grid box.
    """

    def __init__(self, fluid, cell=None, lower=None, upper=None, radius=None, support=None):
        self.fluid = fluid
        s = fluid.spacing
        self.cell = float(s if cell is None else cell)
        if not (math.isfinite(self.cell) and self.cell > 0.0):
            raise ValueError(f"FluidSurface cell must be > 0 [m], got {cell!r}")
        self.radius = float(0.6 * s if radius is None else radius)
        self.support = float(2.0 * s if support is None else support)
        if not (self.radius > 0.0 and self.support > 0.0):
            raise ValueError(f"FluidSurface radius ({radius!r}) and support ({support!r}) must be > 0 [m]")
        if lower is None or upper is None:
            if fluid.domain is None:
                raise ValueError("FluidSurface needs lower= and upper= (the grid box) when the fluid has no domain")
            lo, hi = fluid.domain
        else:
            lo, hi = np.array(checks.vec3(lower, "FluidSurface lower")), np.array(checks.vec3(upper, "FluidSurface upper"))
            if np.any(hi <= lo):
                raise ValueError(f"FluidSurface upper {tuple(hi)} must exceed lower {tuple(lo)} on every axis")
        self.shape = tuple(int(max(2, math.ceil((h - l) / self.cell) + 1)) for l, h in zip(lo, hi))
        self.origin = np.array(lo, dtype=np.float64)
        d = fluid.device
        self.device = d
        self.field = wp.zeros(self.shape, dtype=float, device=d)
        """The last splatted field, shape ``self.shape``, node (i, j, k) at origin + (i, j, k) cell."""
        dims = [int(min(128, max(1, math.ceil((h - l) / self.support)))) for l, h in zip(lo, hi)]
        self._grid = wp.HashGrid(*dims, device=d)
        self.mesher = MarchingCubes(self.shape, spacing=self.cell, origin=tuple(self.origin), device=d,
                                    close_boundary=True, inside="below")

    def splat(self) -> wp.array:
        """Fill and return ``self.field`` from the fluid's current particles."""
        x = self.fluid.positions
        far = self.support
        if x.shape[0] == 0:
            self.field.fill_(far)
            return self.field
        self._grid.build(x, self.support)
        wp.launch(K.splat_zhu_bridson, self.shape,
                  inputs=[self._grid.id, x, wp.vec3(*self.origin), self.cell, self.support, self.radius, far],
                  outputs=[self.field], device=self.device)
        return self.field

    def mesh(self):
        """Splat and mesh the liquid surface; returns a ``warpsim.meshing.marching_cubes.MarchingCubesResult``."""
        return self.mesher.mesh(self.splat(), 0.0)
