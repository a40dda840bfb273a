"""SPH smoothing kernels on the host (NumPy, float64): W and grad W of the cubic B-spline and
Wendland C2, the wall tables a signed-distance boundary adds to the density, the lattice mass,
and :func:`fluid_block` (a lattice of particle centres)."""

from __future__ import annotations

import math

import numpy as np

from ..core import checks

KERNELS = {"cubic": 0, "wendland": 1}
_TABLE_COUNT = 257


# ------------------------------------------------------------------------------ NumPy kernels
def kernel_numpy(r, h: float, kernel: str = "cubic"):
    """W(r) [1/m^3] in NumPy, support radius h (same definitions as ``kernels/sph.py``)."""
    q = np.asarray(r, dtype=np.float64) / h
    w = np.zeros_like(q)
    if kernel == "cubic":
        k = 8.0 / (np.pi * h**3)
        inner = q <= 0.5
        outer = (q > 0.5) & (q < 1.0)
        w[inner] = k * (6.0 * q[inner] ** 3 - 6.0 * q[inner] ** 2 + 1.0)
        w[outer] = 2.0 * k * (1.0 - q[outer]) ** 3
    else:
        m = q < 1.0
        w[m] = 21.0 / (2.0 * np.pi * h**3) * (1.0 - q[m]) ** 4 * (1.0 + 4.0 * q[m])
    return w


def kernel_gradient_numpy(rij, h: float, kernel: str = "cubic"):
    """grad_i W(x_i - x_j) for rij (..., 3) = x_i - x_j, in NumPy [1/m^4]."""
    rij = np.asarray(rij, dtype=np.float64)
    r = np.linalg.norm(rij, axis=-1)
    ok = r > 1e-9 * h
    scale = np.where(ok, kernel_dw_numpy(r, h, kernel) / np.where(ok, r, 1.0), 0.0)
    return rij * scale[..., None]


def wall_tables(h: float, kernel: str = "cubic", spacing: float | None = None, count: int = _TABLE_COUNT):
    """Volume fraction phi(d) of the solid beyond a plane at distance d, sampled at
    d = k h / (count - 1), and its derivative phi'(d) [1/m].

    With ``spacing`` the solid is a lattice of virtual particles of that spacing whose first
    layer lies half a spacing behind the plane (so a lattice of fluid particles at a wall has
    exactly the rest density): phi(d) = sum_virtual W(r) / sum_lattice W(r). Without it, phi is
    the continuous integral int_d^h A(z) dz, A(z) = 2 pi int_z^h W(r) r dr."""
    d = np.linspace(0.0, h, count)
    if spacing is None:
        fine = 8192
        z = np.linspace(0.0, h, fine + 1)
        wr = kernel_numpy(z, h, kernel) * z
        seg = 0.5 * (wr[1:] + wr[:-1]) * np.diff(z)
        a = 2.0 * np.pi * np.concatenate([np.cumsum(seg[::-1])[::-1], [0.0]])
        seg_a = 0.5 * (a[1:] + a[:-1]) * np.diff(z)
        phi = np.concatenate([np.cumsum(seg_a[::-1])[::-1], [0.0]])
        return np.interp(d, z, phi), -np.interp(d, z, a)
    m = int(math.ceil(h / spacing)) + 1
    g = np.arange(-m, m + 1) * spacing
    aa, bb = np.meshgrid(g, g, indexing="ij")
    rho2 = (aa * aa + bb * bb).reshape(1, 1, -1)
    layers = (np.arange(m + 1) + 0.5) * spacing  # virtual layer depths behind the plane
    z = d[:, None, None] + layers[None, :, None]  # (count, layers, 1)
    r = np.sqrt(z * z + rho2)
    norm = lattice_mass(spacing, h, 1.0, kernel)  # volume per particle for exact lattice density
    phi = norm * kernel_numpy(r, h, kernel).sum(axis=(1, 2))
    # d/dd of W(|r|) with z = d + depth: dW/dr * z / r, i.e. the z component of grad W(rvec)
    rr = np.where(r > 0, r, 1.0)
    dphi = norm * (kernel_dw_numpy(r, h, kernel) * z / rr).sum(axis=(1, 2))
    return phi, dphi


def kernel_dw_numpy(r, h: float, kernel: str = "cubic"):
    """dW/dr [1/m^4] in NumPy."""
    q = np.asarray(r, dtype=np.float64) / h
    dw = np.zeros_like(q)
    if kernel == "cubic":
        l = 48.0 / (np.pi * h**4)
        inner = q <= 0.5
        outer = (q > 0.5) & (q < 1.0)
        dw[inner] = l * q[inner] * (3.0 * q[inner] - 2.0)
        dw[outer] = -l * (1.0 - q[outer]) ** 2
    else:
        m = q < 1.0
        dw[m] = -21.0 / (2.0 * np.pi * h**4) * 20.0 * q[m] * (1.0 - q[m]) ** 3
    return dw


def lattice_mass(spacing: float, h: float, rest_density: float, kernel: str = "cubic") -> float:
    """Particle mass [kg] that gives exactly ``rest_density`` inside a cubic lattice of ``spacing``."""
    n = int(math.ceil(h / spacing)) + 1
    g = np.arange(-n, n + 1) * spacing
    x, y, z = np.meshgrid(g, g, g, indexing="ij")
    r = np.sqrt(x * x + y * y + z * z)
    return float(rest_density / kernel_numpy(r, h, kernel).sum())


def fluid_block(lower, upper, spacing: float, jitter: float = 0.0, seed: int = 0) -> np.ndarray:
    """Cubic lattice of particle centres filling the box [lower, upper] [m], first layer half a
    spacing inside each face; shape (N, 3). ``jitter``: random offsets, a fraction of spacing."""
    lo = np.array(checks.vec3(lower, "fluid_block lower"))
    hi = np.array(checks.vec3(upper, "fluid_block upper"))
    spacing = checks.positive(spacing, "fluid_block spacing", "m")
    if np.any(hi - lo < spacing):
        raise ValueError(f"fluid_block upper {hi.tolist()} must exceed lower {lo.tolist()} by at least one spacing "
                         f"{spacing:g} m on every axis; enlarge the box or reduce the spacing")
    counts = np.floor((hi - lo) / spacing + 1e-6).astype(int)
    axes = [lo[k] + (np.arange(counts[k]) + 0.5) * spacing for k in range(3)]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    if jitter:
        pts = pts + np.random.default_rng(seed).uniform(-jitter, jitter, pts.shape) * spacing
    return pts
