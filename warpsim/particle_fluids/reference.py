"""NumPy reference of one position-based-fluid step (the same method as ``warpsim.particle_fluids.pbf``), for
tests and benchmarks.

Neighbours come from ``scipy.spatial.cKDTree`` when SciPy is installed, else from a brute-force
NumPy search. Boundaries: planes only (``n . x = offset``, n toward the fluid). Vorticity
confinement and surface tension are not included.
"""

from __future__ import annotations

import numpy as np

from .smoothing import kernel_dw_numpy, kernel_numpy


def neighbor_pairs(x: np.ndarray, h: float, use_kdtree: bool = True):
    """All ordered pairs (i, j), i != j, with |x_i - x_j| < h: two int arrays."""
    if use_kdtree:
        try:
            from scipy.spatial import cKDTree
        except ImportError:  # pragma: no cover - SciPy is optional
            use_kdtree = False
    if use_kdtree:
        pairs = cKDTree(x).query_pairs(h, output_type="ndarray")
        d = np.linalg.norm(x[pairs[:, 0]] - x[pairs[:, 1]], axis=1)
        pairs = pairs[d < h]
    else:
        rows = []
        for start in range(0, len(x), 512):
            blk = x[start:start + 512]
            d2 = ((blk[:, None, :] - x[None, :, :]) ** 2).sum(-1)
            i, j = np.nonzero(d2 < h * h)
            i = i + start
            keep = i < j
            rows.append(np.stack([i[keep], j[keep]], 1))
        pairs = np.concatenate(rows) if rows else np.zeros((0, 2), np.int64)
    i = np.concatenate([pairs[:, 0], pairs[:, 1]])
    j = np.concatenate([pairs[:, 1], pairs[:, 0]])
    return i, j


def _wall(phi_table, dphi_table, d, h):
    s = np.clip(d, 0.0, None) / h * (len(phi_table) - 1)
    grid = np.arange(len(phi_table))
    phi = np.where(d >= h, 0.0, np.interp(s, grid, phi_table))
    dphi = np.where(d >= h, 0.0, np.interp(s, grid, dphi_table))
    return phi, dphi


def boundary_density(x, normals, offsets, phi_table, dphi_table, h):
    """(grad phi (N, 3) [1/m], phi (N,)) of the union of planes, as in the Warp kernels."""
    frac = np.ones(len(x))
    grad_frac = np.zeros_like(x)
    for n, o in zip(normals, offsets):
        phi, dphi = _wall(phi_table, dphi_table, x @ n - o, h)
        grad_frac = grad_frac * (1.0 - phi)[:, None] - frac[:, None] * dphi[:, None] * n[None, :]
        frac = frac * (1.0 - phi)
    return -grad_frac, 1.0 - frac


def project_planes(x, normals, offsets, radius):
    for n, o in zip(normals, offsets):
        d = x @ n - o
        x = x + np.clip(radius - d, 0.0, None)[:, None] * n[None, :]
    return x


def pbf_step_numpy(x, v, dt, *, h, mass, rest_density, kernel="cubic", gravity=(0.0, -9.81, 0.0), iterations=4,
                   viscosity=0.0, wall_friction=0.0, radius, relaxation, normals=(), offsets=(),
                   phi_table=None, dphi_table=None, use_kdtree=True):
    """One PBF step in float64 NumPy; returns (x, v, density) after the step."""
    x = np.asarray(x, np.float64)
    v = np.asarray(v, np.float64) + dt * np.asarray(gravity, np.float64)
    normals = np.asarray(normals, np.float64).reshape(-1, 3)
    offsets = np.asarray(offsets, np.float64).reshape(-1)
    xp = project_planes(x + dt * v, normals, offsets, radius)
    i, j = neighbor_pairs(xp, h, use_kdtree)
    n = len(x)
    scale = mass / rest_density
    w0 = float(kernel_numpy(0.0, h, kernel))

    def gradients(xc):
        rij = xc[i] - xc[j]
        r = np.linalg.norm(rij, axis=1)
        ok = r > 1e-9 * h
        g = rij * np.where(ok, kernel_dw_numpy(r, h, kernel) / np.where(ok, r, 1.0), 0.0)[:, None]
        return r, g

    density = np.zeros(n)
    for _ in range(iterations):
        r, g = gradients(xp)
        density = mass * w0 + np.bincount(i, mass * kernel_numpy(r, h, kernel), minlength=n)
        gb, phib = (np.zeros_like(xp), np.zeros(n)) if len(offsets) == 0 else boundary_density(
            xp, normals, offsets, phi_table, dphi_table, h)
        density = density + rest_density * phib
        gs = scale * g
        grad_i = np.stack([np.bincount(i, gs[:, k], minlength=n) for k in range(3)], 1) + gb
        sum2 = np.bincount(i, (gs * gs).sum(1), minlength=n) + (grad_i * grad_i).sum(1)
        c = np.clip(density / rest_density - 1.0, 0.0, None)
        lam = -c / (sum2 + relaxation)
        corr = (scale * (lam[i] + lam[j]))[:, None] * g
        dx = np.stack([np.bincount(i, corr[:, k], minlength=n) for k in range(3)], 1) + lam[:, None] * gb
        xp = project_planes(xp + dx, normals, offsets, radius)
    v = (xp - x) / dt
    if viscosity > 0.0 or wall_friction > 0.0:
        r = np.linalg.norm(xp[i] - xp[j], axis=1)
        wgt = 2.0 * mass / (density[i] + density[j]) * kernel_numpy(r, h, kernel)
        dv = (wgt[:, None] * (v[j] - v[i]))
        vnew = v + viscosity * np.stack([np.bincount(i, dv[:, k], minlength=n) for k in range(3)], 1)
        if wall_friction > 0.0 and len(offsets):
            _, phib = boundary_density(xp, normals, offsets, phi_table, dphi_table, h)
            vnew = vnew * np.exp(-wall_friction * phib * dt)[:, None]
        v = vnew
    return xp, v, density
