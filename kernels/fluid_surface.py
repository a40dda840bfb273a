"""Fluid surface field: a signed-distance-like field splatted from particles onto a grid.

Zhu and Bridson (2005), "Animating sand as a fluid": at a grid node p, with weights
k(s) = max(0, 1 - s^2)^3 of s = |p - x_i| / R over the particles within R,
``phi(p) = |p - xbar| - r`` where xbar is the weighted mean particle position and r the particle
radius. phi < 0 inside the liquid; nodes with no particle within R get ``far`` (> 0).
"""

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.kernel
def splat_zhu_bridson(
    grid: wp.uint64,
    x: wp.array(dtype=wp.vec3),
    origin: wp.vec3,
    cell: float,
    support: float,
    radius: float,
    far: float,
    field_out: wp.array3d(dtype=float),
):
    """field_out[i, j, k] = phi at origin + (i, j, k) * cell [m] (see the module docstring)."""
    i, j, k = wp.tid()
    p = origin + cell * wp.vec3(float(i), float(j), float(k))
    wsum = float(0.0)
    xsum = wp.vec3(0.0)
    r2 = support * support
    for idx in wp.hash_grid_query(grid, p, support):
        xi = x[idx]
        d2 = wp.length_sq(p - xi)
        if d2 < r2:
            s = 1.0 - d2 / r2
            w = s * s * s
            wsum += w
            xsum += w * xi
    phi = far
    if wsum > 0.0:
        phi = wp.min(wp.length(p - xsum / wsum) - radius, far)
    field_out[i, j, k] = phi
