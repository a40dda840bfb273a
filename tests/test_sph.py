"""Position-based fluids (warpsim.particle_fluids.pbf), its surface (warpsim.particle_fluids.surface) and scenes.

Physics checked: smoothing kernels against NumPy and their integrals, a step against a NumPy
reference of the same method, a hydrostatic column (density and pressure), the dam-break front
against Martin and Moyce (1952), volume conservation, momentum of a free-falling blob,
containment by walls, spheres and meshes, emitters/sinks, CFL sub-stepping, and bad input.
"""

import time
from types import SimpleNamespace

import numpy as np
import pytest
import warp as wp
import warpsim.kernels.sph as K

from warpsim.core.errors import SimulationError
from warpsim.particle_fluids.emitters import Nozzle, Sink
from warpsim.particle_fluids.pbf import ParticleFluid
from warpsim.particle_fluids.smoothing import kernel_dw_numpy, fluid_block, kernel_numpy, lattice_mass, wall_tables
from warpsim.particle_fluids.reference import pbf_step_numpy

G = 9.81


@wp.kernel
def eval_kernels(r: wp.array(dtype=float), h: float, kind: int, w_out: wp.array(dtype=float),
                 dw_out: wp.array(dtype=float), coh_out: wp.array(dtype=float)):
    i = wp.tid()
    w_out[i] = K.kernel_w(r[i], h, kind)
    dw_out[i] = K.kernel_dw(r[i], h, kind)
    coh_out[i] = K.cohesion_spline(r[i], h)


# ------------------------------------------------------------------------------ kernels
@pytest.mark.parametrize("kernel", ["cubic", "wendland"])
def test_smoothing_kernels_match_numpy_and_integrate_to_one(kernel, device):
    h = 0.04
    r = np.linspace(0.0, 1.1 * h, 2001)
    out = [wp.zeros(len(r), dtype=float, device=device) for _ in range(3)]
    wp.launch(eval_kernels, len(r), inputs=[wp.array(r, dtype=float, device=device), h, K.KERNEL_CUBIC if kernel ==
                                            "cubic" else K.KERNEL_WENDLAND], outputs=out, device=device)
    w, dw, coh = (a.numpy().astype(np.float64) for a in out)
    np.testing.assert_allclose(w, kernel_numpy(r, h, kernel), rtol=2e-5, atol=1e-3)
    # integral over space: int 4 pi r^2 W dr = 1
    f = 4.0 * np.pi * r**2 * w
    assert abs(np.sum(0.5 * (f[1:] + f[:-1]) * np.diff(r)) - 1.0) < 1e-4
    # derivative: finite differences of W
    fd = np.gradient(kernel_numpy(r, h, kernel), r)
    inside = (r > 0.02 * h) & (r < 0.98 * h)
    np.testing.assert_allclose(dw[inside], fd[inside], rtol=2e-3, atol=2e-3 * np.abs(fd).max())
    assert np.all(w[r >= h] == 0.0) and np.all(dw[r >= h] == 0.0)
    # Akinci cohesion spline: repulsive near 0, attractive (positive) beyond h/2, zero at h
    assert coh[np.searchsorted(r, 0.1 * h)] < 0.0 < coh[np.searchsorted(r, 0.75 * h)]
    assert np.all(coh[r >= h] == 0.0)


@wp.kernel
def eval_pair_terms(p: K.FluidParams, r: wp.array(dtype=float), out: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    wf = K.pair_terms(p, r[i] * r[i])
    out[i] = wp.vec3(wf[0], wf[1], K.pair_density(p, r[i]))


@pytest.mark.parametrize("kernel", ["cubic", "wendland"])
def test_pair_terms_match_numpy(kernel, device):
    """The solver's fused inner-loop kernel terms (precomputed constants, no branches): m W(r) and
    the gradient factor f with (m / rho0) grad_i W = f (x_i - x_j), from r = 0 to beyond h."""
    s = 0.02
    f = ParticleFluid(fluid_block((0, 0, 0), (0.06, 0.06, 0.06), s), spacing=s, kernel=kernel, device=device)
    h, m, rho0 = f.h, f.particle_mass, f.rest_density
    r = np.concatenate([[0.0], np.linspace(1e-3 * h, 1.2 * h, 997), [0.5 * h, h]])
    out = wp.zeros(len(r), dtype=wp.vec3, device=device)
    wp.launch(eval_pair_terms, len(r), inputs=[f._params, wp.array(r, dtype=float, device=device)], outputs=[out],
              device=device)
    w, g, w_only = out.numpy().astype(np.float64).T
    np.testing.assert_allclose(w, m * kernel_numpy(r, h, kernel), rtol=1e-5, atol=1e-6 * m * kernel_numpy(0.0, h, kernel))
    np.testing.assert_allclose(w, w_only, rtol=1e-6, atol=0.0)
    expected = m / rho0 * kernel_dw_numpy(r[1:], h, kernel) / r[1:]
    np.testing.assert_allclose(g[1:], expected, rtol=1e-4, atol=1e-5 * np.abs(expected).max())
    assert np.isfinite(g[0])  # at r = 0 the gradient f (x_i - x_j) is 0 whatever f is
    assert np.all(w[r >= h] == 0.0) and np.all(g[r >= h] == 0.0)


def test_wall_tables_continuous_and_lattice():
    h, s = 0.04, 0.02
    phi_c, dphi_c = wall_tables(h, "cubic")
    assert abs(phi_c[0] - 0.5) < 1e-3 and phi_c[-1] == 0.0  # half the kernel lies beyond a wall through x
    d = np.linspace(0.0, h, len(phi_c))
    np.testing.assert_allclose(np.gradient(phi_c, d)[5:-5], dphi_c[5:-5], atol=0.01 / h)
    phi, dphi = wall_tables(h, "cubic", s)
    # a lattice particle half a spacing from the wall: its missing neighbours exactly
    n = 4
    g = np.arange(-n, n + 1) * s
    xj = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    below = xj[xj[:, 1] < -0.5 * s + 1e-12]
    missing = lattice_mass(s, h, 1.0) * kernel_numpy(np.linalg.norm(below, axis=1), h).sum()
    assert abs(np.interp(0.5 * s, d, phi) - missing) < 1e-4
    np.testing.assert_allclose(np.gradient(phi, d)[5:-5], dphi[5:-5], atol=0.02 / h)


@pytest.mark.parametrize("kernel", ["cubic", "wendland"])
def test_lattice_at_walls_has_rest_density(kernel, device):
    s = 0.02
    f = ParticleFluid(fluid_block((0, 0, 0), (0.16, 0.16, 0.16), s), spacing=s,
                      domain=((0, 0, 0), (0.16, 0.3, 0.16)), kernel=kernel, device=device)
    rho = f.measure_density()
    x = f.positions.numpy()
    below_top = x[:, 1] < 0.16 - 2.0 * s  # the free surface (top) has a kernel deficiency
    # faces (one wall) are exact; edges and corners (two or three walls) slightly under-dense
    assert np.all(rho[below_top] <= 1000.0 * (1 + 1e-4))
    assert np.all(rho[below_top] >= 1000.0 * (1 - 0.01))
    assert f.density_error()[1] < 1e-4


# ------------------------------------------------------------------------------ reference
def test_step_matches_numpy_reference(device):
    s = 0.02
    rng = np.random.default_rng(3)
    x0 = fluid_block((0.0, 0.0, 0.0), (0.12, 0.12, 0.1), s, jitter=0.15, seed=1) + np.array([0.01, 0.0, 0.0])
    x0 = np.clip(x0, 0.5 * s, None)
    v0 = rng.normal(0.0, 0.2, x0.shape)
    dom = ((0.0, 0.0, 0.0), (0.2, 0.3, 0.12))
    f = ParticleFluid(x0, v0, spacing=s, domain=dom, viscosity=0.05, wall_friction=20.0, iterations=3,
                      density_tolerance=0.0, device=device)
    phi, dphi = wall_tables(f.h, "cubic", s)
    eye = np.eye(3)
    normals = np.concatenate([eye, -eye])
    offsets = np.concatenate([np.zeros(3), -np.array(dom[1])])
    x, v = f.positions.numpy().astype(np.float64), f.velocities.numpy().astype(np.float64)
    dt = 1.0 / 240.0
    for _ in range(3):
        x, v, rho = pbf_step_numpy(x, v, dt, h=f.h, mass=f.particle_mass, rest_density=1000.0, iterations=3,
                                   viscosity=0.05, wall_friction=20.0, radius=0.5 * s,
                                   relaxation=1e-6 / s**2, normals=normals, offsets=offsets, phi_table=phi,
                                   dphi_table=dphi)
        f.step(dt)
    assert np.abs(f.positions.numpy() - x).max() < 2e-6
    assert np.abs(f.velocities.numpy() - v).max() < 2e-3
    np.testing.assert_allclose(f.density.numpy(), rho, rtol=1e-4)


def test_fused_neighbor_density_pass_matches_separate_passes():
    """The CPU's path (neighbour search with the first density pass fused in, pair gradients
    cached in the list) gives bit for bit the steps of the GPUs' path run on the CPU (list, then
    density over the list; gradients re-evaluated in every correction)."""
    s = 0.02
    x0 = fluid_block((0, 0, 0), (0.1, 0.16, 0.1), s, jitter=0.1, seed=5)
    x0 = np.clip(x0, 0.5 * s, None)
    runs = []
    for fused in (True, False):
        f = ParticleFluid(x0, spacing=s, domain=((0, 0, 0), (0.3, 0.3, 0.1)), device="cpu")
        f._fused_density = fused
        f._neighbors.cache_gradients = int(fused)
        for _ in range(15):
            f.step(1.0 / 300.0)
        runs.append((f.positions.numpy(), f.density.numpy(), f.total_iterations))
    np.testing.assert_array_equal(runs[0][0], runs[1][0])
    np.testing.assert_array_equal(runs[0][1], runs[1][1])
    assert runs[0][2] == runs[1][2]


def test_adaptive_iterations_stop_below_the_tolerance():
    """On the CPU a step stops iterating once the mean compression is below density_tolerance
    and the largest below peak_tolerance (10 x): every step that stopped early ends below both,
    a fluid nothing compresses needs no iteration, and tolerance 0 runs every iteration."""
    s = 0.02
    tol = 0.002
    f = ParticleFluid(fluid_block((0, 0, 0), (0.12, 0.24, 0.1), s), spacing=s,
                      domain=((0, 0, 0), (0.4, 0.3, 0.1)), iterations=6, density_tolerance=tol, device="cpu")
    used = []
    for _ in range(40):
        f.step(1.0 / 200.0)
        used.append(f.last_iterations)
        if f.last_iterations < f.iterations:
            rho = f.measure_density() / f.rest_density
            assert np.maximum(rho - 1.0, 0.0).mean() < tol
            assert rho.max() - 1.0 < f.peak_tolerance == 10 * tol
    print("iterations per step:", used)
    assert min(used) < max(used) == 6 and f.total_iterations == sum(used)  # it adapts
    free = ParticleFluid(fluid_block((0, 0, 0), (0.1, 0.1, 0.1), s), spacing=s, device="cpu")
    for _ in range(5):
        free.step(1.0 / 200.0)  # falling freely: nothing compresses the lattice
    assert free.total_iterations == 0
    fixed = ParticleFluid(fluid_block((0, 0, 0), (0.1, 0.1, 0.1), s), spacing=s, iterations=3,
                          density_tolerance=0.0, device="cpu")
    fixed.step(1.0 / 200.0)
    assert fixed.last_iterations == 3


# ------------------------------------------------------------------------------ validation
def test_hydrostatic_column_density_and_pressure():
    """A 0.3 m column at rest in a box: compression < 1 % and, at least one kernel radius from
    the side walls, pressure within 5 % of rho g depth (averaged over layers 2 spacings thick)."""
    s, width, height = 0.03, 0.3, 0.3
    f = ParticleFluid(fluid_block((0, 0, 0), (width, height, width), s), spacing=s,
                      domain=((0, 0, 0), (width, height + 0.1, width)), viscosity=0.05, iterations=4,
                      max_dt=1.0 / 240.0, device="cpu")
    for _ in range(90):
        f.advance(1.0 / 60.0)
    assert f.max_speed_now() < 0.1  # at rest
    mean, peak = f.density_error()
    assert mean < 0.01 and peak < 0.02
    x = f.positions.numpy()
    p = f.pressure.numpy()
    interior = np.all((x[:, [0, 2]] > f.h) & (x[:, [0, 2]] < width - f.h), axis=1)
    # depth of rest-density fluid above each particle: the weight above it per unit area / (rho0 g)
    # (each particle's mass spread over one spacing in y), free of where the surface layer sits
    y = x[:, 1]
    above = np.clip((y[None, :] + 0.5 * s - y[:, None]) / s, 0.0, 1.0).sum(axis=1)
    depth = above * f.particle_mass / (1000.0 * width * width)
    edges = np.arange(2 * s, height + 2 * s, 2 * s)
    checked = 0
    for a, b in zip(edges[:-1], edges[1:]):
        m = interior & (depth >= a) & (depth < b)
        if m.sum() < 4:
            continue
        ratio = p[m].mean() / (1000.0 * G * depth[m].mean())
        assert abs(ratio - 1.0) < 0.05, (a, b, ratio)
        checked += 1
    assert checked >= 3


# Martin and Moyce (1952), "Part IV. An experimental study of the collapse of liquid columns on
# a rigid horizontal plane", Phil. Trans. R. Soc. Lond. A 244, 312-324, Table 2: surge front of
# the column with n^2 = 2 (height 2a), a = 2.25 in; Z = z/a against T = t sqrt(2 g / a). (The
# same numbers are quoted, e.g., in the plotting script of the Ocellaris solver; PySPH's
# db_exp_data.py digitises their Fig. 3 and agrees.)
MM_T = np.array([0.41, 0.84, 1.19, 1.43, 1.63, 1.83, 1.98, 2.20, 2.32, 2.51, 2.65, 2.83, 2.98])
MM_Z = np.array([1.11, 1.22, 1.44, 1.67, 1.89, 2.11, 2.33, 2.56, 2.78, 3.00, 3.22, 3.44, 3.67])


def run_dam_break(res=10, **settings):
    """A 2D-like slab (3 particles thick, walls on every side): column a x 2a, a = ``res`` spacings,
    advanced over T = 0 .. 3.1 in equal frames (PBF wants sub-steps of similar size). The walls
    resist like the experiment's floor (the default wall_friction, 5 /s). Records the front Z(T), the
    density-based volume, the mean and peak compression and the largest speed at every sample."""
    a = 0.1
    s = a / res
    f = ParticleFluid(fluid_block((0, 0, 0), (a, 2 * a, 3 * s), s), spacing=s,
                      domain=((0, 0, 0), (5 * a, 2.5 * a, 3 * s)), viscosity=0.01, max_dt=1.0 / 100.0,
                      device="cpu", **settings)
    scale = np.sqrt(2.0 * G / a)
    frame_dt = 0.05 / scale
    volume0 = f.volume()
    out = {"T": [0.0], "Z": [1.0], "volume": [1.0], "compression": [f.density_error()[0]], "peak": [0.0],
           "speed": [0.0]}
    start = time.perf_counter()
    for _ in range(62):
        f.advance(frame_dt)  # raises SimulationError on a blow-up (max_speed 100 m/s)
        x = f.positions.numpy()
        out["T"].append(f.time * scale)
        out["Z"].append((x[:, 0].max() + 0.5 * s) / a)
        out["volume"].append(f.volume() / volume0)
        mean, peak = f.density_error()
        out["compression"].append(mean)
        out["peak"].append(peak)
        out["speed"].append(f.max_speed_now())
    out = {k: np.array(v) for k, v in out.items()}
    out.update(fluid=f, height=2 * a, res=res, steps=f.step_count, particles=f.active_count,
               seconds=time.perf_counter() - start)
    return out


@pytest.fixture(scope="module")
def dam_break():
    """The dam break at the default settings (see :func:`run_dam_break`)."""
    return run_dam_break()


def test_dam_break_front_martin_moyce(dam_break):
    """Front Z(T) (furthest particle + half a spacing) against Martin and Moyce, T <= 3, raw.

    Measured (a/spacing = 10, no-slip walls): -3 % at T = 0.41, +9 % at 0.84, +2..+10 % for
    T >= 1.9, but +11..+13 % for 1.0 < T < 1.9 (free-slip walls: the same early lead and +6..+11 %
    later, a surge 4 % faster at T = 3: the floor's friction acts on the thin surge). The early
    lead is not numerical: it stays with 5x the solver iterations (full incompressibility), with
    the front taken as the colour-field = 1/2 surface at the floor instead of the furthest
    particle, it stays at a/spacing = 20 (+11..16 %), and an independent Eulerian method shares it
    (FLIP on a MAC grid, +16..19 %: tests/test_dam_break_crosscheck.py). The experiment's front moves
    only 0.11 a between T = 0.41 and 0.84, where any instantaneous release accelerates: its
    release is not instantaneous. So the raw curve is asserted within 10 % outside
    1.0 < T < 1.9 and within 15 % there; one time-origin shift dT (least squares, small) brings
    every point within 10 %."""
    T, Z = dam_break["T"], dam_break["Z"]
    raw = np.interp(MM_T, T, Z) / MM_Z - 1.0
    print("Z_sim / Z_exp - 1 at T =", MM_T, ":", np.round(raw, 3))
    early = (MM_T > 1.0) & (MM_T < 1.9)
    assert np.all(np.abs(raw[~early]) < 0.10), raw
    assert np.all(np.abs(raw[early]) < 0.15), raw
    shifts = np.linspace(0.0, 0.5, 101)
    errs = [np.max(np.abs(np.interp(MM_T - dT, T, Z, left=1.0) / MM_Z - 1.0)) for dT in shifts]
    best = int(np.argmin(errs))
    print(f"time-origin shift dT = {shifts[best]:.3f}: max |Z_sim / Z_exp - 1| = {errs[best]:.3f}")
    assert shifts[best] < 0.35 and errs[best] < 0.10, (shifts[best], errs[best])
    assert Z[-1] > 3.0  # the surge really travels (T = 3)


def test_dam_break_volume_and_density(dam_break):
    """Density-based volume sum m / max(rho, rho0) stays within 1 %; compression < 1 %."""
    assert np.all(np.abs(dam_break["volume"] - 1.0) < 0.01), dam_break["volume"].min()
    assert np.all(dam_break["compression"] < 0.01)
    f = dam_break["fluid"]
    x = f.positions.numpy()
    lo, hi = f.domain
    assert np.all(x >= lo + 0.5 * f.spacing - 1e-5) and np.all(x <= hi - 0.5 * f.spacing + 1e-5)


@pytest.mark.parametrize("cfl", [None, 0.1, 0.05])
def test_dam_break_small_steps_stay_bounded(cfl, dam_break):
    """Smaller CFL sub-steps must not destabilise the dam break. Regression: with cfl = 0.1 the
    adaptive stop skipped the solve in most steps (mean compression below the tolerance while a
    few particles next to the side walls were compressed up to 20 %); the compression a step
    leaves becomes velocity ~ C spacing / dt at the next correction, the kick made the steps
    shorter still and the slab blew up at t ~ 0.1 s (> 100 m/s). Now every step with a particle
    compressed beyond the tolerance runs at least one correction. Checked: finite, the largest
    speed below 2 sqrt(2 g H) (free fall from the column height H reaches sqrt(2 g H)), peak
    compression < 5 %, volume within 1 % and the surge still travelling over the same span."""
    run = dam_break if cfl is None else run_dam_break(cfl=cfl)
    f = run["fluid"]
    assert np.all(np.isfinite(f.positions.numpy())) and np.all(np.isfinite(f.velocities.numpy()))
    bound = 2.0 * np.sqrt(2.0 * G * run["height"])
    print(f"cfl {f.cfl}: {f.step_count} steps, {f.total_iterations / f.step_count:.2f} corrections per step, "
          f"max speed {run['speed'].max():.3f} m/s (bound {bound:.3f}), peak compression {run['peak'].max():.4f}, "
          f"front Z(T = 3.1) = {run['Z'][-1]:.2f}")
    assert run["speed"].max() < bound, run["speed"].max()
    assert np.all(run["peak"] < 0.05), run["peak"].max()
    assert np.all(np.abs(run["volume"] - 1.0) < 0.01), run["volume"].min()
    # the wall friction is a rate, so the front does not depend on the step size: measured
    # |Z(cfl) / Z(cfl 0.4) - 1| <= 0.8 % (cfl 0.1) and 1.4 % (0.05) at the Martin and Moyce
    # samples (the earlier per-step friction: up to 3.7 % and 9 %)
    drift = np.interp(MM_T, run["T"], run["Z"]) / np.interp(MM_T, dam_break["T"], dam_break["Z"]) - 1.0
    print("front against cfl 0.4:", np.round(drift, 3))
    assert np.all(np.abs(drift) < 0.03), drift
    assert run["Z"][-1] > 3.0


def test_free_fall_momentum_matches_gravity(device):
    """No walls: internal forces (PBF corrections, XSPH, surface tension) are pairwise
    antisymmetric, so the total momentum changes by exactly M g t."""
    s = 0.02
    x0 = fluid_block((-0.05, -0.05, -0.05), (0.05, 0.05, 0.05), s, jitter=0.1, seed=2) * 0.9
    rng = np.random.default_rng(0)
    v0 = rng.normal(0.0, 0.3, x0.shape)
    f = ParticleFluid(x0, v0, spacing=s, viscosity=0.1, surface_tension=0.5, device=device)
    p0 = f.momentum()
    mass = f.total_mass
    t = 0.0
    for _ in range(40):
        f.step(1.0 / 400.0)
        t += 1.0 / 400.0
    expected = p0 + mass * np.array([0.0, -G, 0.0]) * t
    err = np.abs(f.momentum() - expected).max()
    assert err < 2e-5 * mass * G * t, err / (mass * G * t)
    # the blob stayed together and compressed < 1 %
    assert f.density_error()[0] < 0.01


def test_containment_walls_sphere_and_mesh():
    """Fluid thrown at a solid sphere, a solid box mesh and a thin quad inside a closed box:
    nothing leaves the box or comes within a particle radius of the solids (the obstacles are
    more than a particle diameter apart: a particle jammed in a narrower gap can only be kept
    out of one of them)."""
    s = 0.02
    rng = np.random.default_rng(4)
    x0 = fluid_block((0.02, 0.3, 0.02), (0.18, 0.46, 0.18), s)
    v0 = rng.normal(0.0, 1.5, x0.shape) + np.array([0.0, -3.0, 0.0])
    sphere = SimpleNamespace(center=(0.07, 0.09, 0.07), radius=0.04)
    cube = np.array([[i & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], float) * 0.06 + [0.14, 0.0, 0.14]
    faces = np.array([[0, 2, 1], [1, 2, 3], [4, 5, 6], [5, 7, 6], [0, 1, 4], [1, 5, 4],
                      [2, 6, 3], [3, 6, 7], [0, 4, 2], [2, 4, 6], [1, 3, 5], [3, 7, 5]])
    box_mesh = SimpleNamespace(points=cube, faces=faces, solid=True)
    quad = SimpleNamespace(corners=lambda: np.array([[0.0, 0.22, 0.0], [0.0, 0.22, 0.08], [0.08, 0.22, 0.08],
                                                     [0.08, 0.22, 0.0]]))
    lo, hi = np.zeros(3), np.array([0.2, 0.5, 0.2])
    f = ParticleFluid(x0, v0, spacing=s, domain=(lo, hi), colliders=[sphere, box_mesh, quad], device="cpu")
    tol = 1e-4
    for _ in range(20):
        f.advance(1.0 / 60.0)
        x = f.positions.numpy()
        assert np.all(x >= lo + 0.5 * s - tol) and np.all(x <= hi - 0.5 * s + tol)
        assert np.linalg.norm(x - sphere.center, axis=1).min() >= sphere.radius + 0.5 * s - tol
        gap = np.maximum(np.abs(x - cube.mean(0)) - 0.03, 0.0)  # distance outside the cube
        assert np.linalg.norm(gap, axis=1).min() >= 0.5 * s - tol
        on_quad = np.all((x[:, [0, 2]] > 0.0) & (x[:, [0, 2]] < 0.08), axis=1)
        assert np.all(np.abs(x[on_quad, 1] - 0.22) >= 0.5 * s - tol)
    assert f.active_count == len(x0)


def test_warpsim_colliders_become_boundaries():
    """Plane, Box, Sphere (solid and hollow), Capsule, Quad and TriangleMesh colliders are read at
    their pose, thickened by their thickness."""
    from warpsim.bodies import colliders as C

    s = 0.02
    cube = np.array([[i & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], float) * 0.1
    faces = np.array([[0, 2, 1], [1, 2, 3], [4, 5, 6], [5, 7, 6], [0, 1, 4], [1, 5, 4],
                      [2, 6, 3], [3, 6, 7], [0, 4, 2], [2, 4, 6], [1, 3, 5], [3, 7, 5]])
    cols = [C.Plane((0, 1, 0), 0.1, thickness=0.01), C.Box((-1, 0, -1), (1, 2, 1)),
            C.Sphere((0.5, 0.5, 0.5), 0.1), C.Sphere((0, 1, 0), 0.9, inside=True),
            C.Capsule((0, 0.2, 0), (0.2, 0.2, 0), 0.05, thickness=0.01),
            C.Quad((0, 1.5, 0), (0.1, 0, 0), (0, 0, 0.1)),
            C.TriangleMesh(cube, faces, solid=True, position=(0.3, 0.0, 0.3))]
    f = ParticleFluid(fluid_block((-0.1, 0.5, -0.1), (0.1, 0.7, 0.1), s), spacing=s, colliders=cols, device="cpu")
    b = f._boundaries
    np.testing.assert_allclose(b.plane_offsets.numpy()[:1], [0.11], rtol=1e-6)  # offset + thickness
    assert b.plane_offsets.shape[0] == 7
    np.testing.assert_allclose(b.capsule_radii.numpy(), [0.1, 0.9, 0.06], rtol=1e-6)
    np.testing.assert_allclose(b.capsule_signs.numpy(), [1.0, -1.0, 1.0])
    np.testing.assert_allclose(b.capsule_b.numpy()[2], [0.2, 0.2, 0.0], atol=1e-6)
    assert list(b.mesh_solid.numpy()) == [0, 1]
    # the mesh is in world space: a particle just outside its +x face sees it at distance ~0
    assert f._meshes[1].points.numpy()[:, 0].min() == pytest.approx(0.3)


def test_emitter_sink_ids_and_capacity():
    s = 0.02
    nozzle = Nozzle(center=(0.1, 0.3, 0.1), direction=(0, -1, 0), radius=0.03, speed=1.0, stop=0.2)
    per_layer = len(nozzle.layer_offsets(s))
    sinks = [Sink((0.0, 0.0, 0.0), (0.1, 0.1, 0.2)), Sink((0.1, 0.0, 0.0), (0.2, 0.1, 0.2))]
    f = ParticleFluid(np.zeros((0, 3)), spacing=s, capacity=4000, domain=((0, 0, 0), (0.2, 0.4, 0.2)),
                      emitters=[nozzle], sinks=sinks, device="cpu")
    assert f.active_count == 0
    for _ in range(12):  # 0.2 s of emission: 0.2 m of jet = 10 layers
        f.advance(1.0 / 60.0)
    assert nozzle.emitted == 10 * per_layer
    ids = f.ids.numpy()
    assert len(np.unique(ids)) == len(ids) == f.active_count
    assert f.next_id == nozzle.emitted
    # falling 0.2-0.3 m: the jet reaches the sink, which removes what enters it
    for _ in range(30):
        f.advance(1.0 / 60.0)
    assert sinks[0].removed > 0 and sinks[1].removed > 0  # the jet spreads over both halves
    assert f.active_count == nozzle.emitted - sinks[0].removed - sinks[1].removed
    x = f.positions.numpy()
    ids2 = f.ids.numpy()
    assert np.all(x[:, 1] > 0.1 - 1e-6) or f.active_count == 0
    assert set(ids2) <= set(range(f.next_id)) and len(np.unique(ids2)) == len(ids2)
    # a full capacity stops emission with a warning
    small = ParticleFluid(np.zeros((0, 3)), spacing=s, capacity=per_layer + 3,
                          domain=((0, 0, 0), (0.2, 0.4, 0.2)), emitters=[Nozzle((0.1, 0.3, 0.1), radius=0.03)],
                          device="cpu")
    with pytest.warns(RuntimeWarning, match="capacity"):
        for _ in range(3):
            small.advance(1.0 / 60.0)
    assert small.active_count == per_layer + 3 and small.dropped > 0


def test_sort_particles_keeps_ids_with_their_particles():
    s = 0.02
    x0 = fluid_block((0.0, 0.0, 0.0), (0.1, 0.1, 0.1), s)
    x0 = x0[np.random.default_rng(1).permutation(len(x0))]
    v0 = np.random.default_rng(2).normal(size=x0.shape)
    f = ParticleFluid(x0, v0, spacing=s, device="cpu")
    f.sort_particles()
    ids = f.ids.numpy()
    assert sorted(ids) == list(range(len(x0))) and not np.array_equal(ids, np.arange(len(x0)))
    np.testing.assert_array_equal(f.positions.numpy(), x0[ids].astype(np.float32))
    np.testing.assert_array_equal(f.velocities.numpy(), v0[ids].astype(np.float32))
    # memory order now follows space: consecutive particles are mostly close together
    gaps = np.linalg.norm(np.diff(f.positions.numpy(), axis=0), axis=1)
    assert np.median(gaps) < 2.5 * s < np.median(np.linalg.norm(np.diff(x0, axis=0), axis=1))


def test_cfl_substeps_and_blow_up():
    s = 0.02
    x0 = fluid_block((0.0, 0.0, 0.0), (0.06, 0.06, 0.06), s)
    f = ParticleFluid(x0, np.tile([4.0, 0.0, 0.0], (len(x0), 1)), spacing=s, gravity=(0, 0, 0), cfl=0.4,
                      max_dt=1.0, device="cpu")
    n = f.advance(1.0 / 60.0)
    assert n == int(np.ceil((1.0 / 60.0) * 4.0 / (0.4 * s)))  # v dt <= cfl spacing
    assert f.last_substeps == n
    f._v.fill_(wp.vec3(np.nan, 0.0, 0.0))
    with pytest.raises(SimulationError, match="particle"):
        f.advance(1.0 / 60.0)


def test_vorticity_confinement_and_surface_tension():
    """Vorticity confinement adds rotational energy to a spinning blob; surface tension pulls a
    cube-shaped blob in zero gravity toward a sphere (smaller spread of radii)."""
    s = 0.02
    x0 = fluid_block((-0.06, -0.06, -0.06), (0.06, 0.06, 0.06), s)
    spin = np.cross([0.0, 0.0, 2.0], x0)

    # the curl kernel: a rigid rotation v = W x x has vorticity 2 W in the bulk
    f = ParticleFluid(x0, spin, spacing=s, gravity=(0, 0, 0), device="cpu")
    f.measure_density()
    n = f.active_count
    dt = 0.01  # velocities as the solver sees them: (x - x_old) / dt
    x_old = wp.array(x0 - dt * spin, dtype=wp.vec3, device="cpu")
    wp.launch(K.compute_curl_normals, n, inputs=[f._params, x_old, f.positions, dt, f._density, f._neighbors],
              outputs=[f._curl, f._normal], device="cpu")
    bulk = np.all(np.abs(x0) < 0.06 - f.h, axis=1)
    # (the cubic lattice's SPH gradient moment is 1.02, not 1)
    np.testing.assert_allclose(f._curl.numpy()[:n][bulk], np.tile([0.0, 0.0, 4.0], (bulk.sum(), 1)), atol=0.1)
    normal = f._normal.numpy()[:n]
    assert np.abs(normal[bulk]).max() < 1e-3  # surface normals vanish in the bulk ...
    corner = np.argmax(x0.sum(axis=1))
    assert np.dot(normal[corner], [-1, -1, -1]) > 0.0  # ... and point inward (Akinci) at the surface

    def energy(vort):
        f = ParticleFluid(x0, spin, spacing=s, gravity=(0, 0, 0), vorticity=vort, viscosity=0.0, device="cpu")
        for _ in range(20):
            f.step(1.0 / 240.0)
        return float((f.velocities.numpy() ** 2).sum())

    assert energy(0.02) > 1.01 * energy(0.0)

    def spread(gamma):
        f = ParticleFluid(x0, spacing=s, gravity=(0, 0, 0), surface_tension=gamma, viscosity=0.05, device="cpu")
        for _ in range(30):
            f.advance(1.0 / 60.0)
        x = f.positions.numpy()
        r = np.linalg.norm(x - x.mean(0), axis=1)
        outer = r > np.percentile(r, 80)
        return r[outer].std() / r[outer].mean()

    assert spread(1.0) < 0.8 * spread(0.0)


def test_bad_input_names_the_item():
    s = 0.02
    good = fluid_block((0, 0, 0), (0.06, 0.06, 0.06), s)
    cases = [
        (dict(positions=np.zeros((3, 2))), "positions"),
        (dict(positions=np.array([[0.0, np.nan, 0.0]])), "particle 0"),
        (dict(velocities=np.zeros((2, 3))), "velocities"),
        (dict(spacing=-1.0), "spacing"),
        (dict(kernel="gauss"), "kernel"),
        (dict(iterations=0), "iterations"),
        (dict(density_tolerance=-0.1), "density_tolerance"),
        (dict(viscosity=2.0), "viscosity"),
        (dict(capacity=3), "capacity"),
        (dict(domain=((0, 0, 0), (0.01, 0.01, 0.01))), "domain"),
        (dict(domain=((0.1, 0, 0), (1, 1, 1))), "outside the domain"),
        (dict(colliders=[object()]), "colliders\\[0\\]"),
        (dict(emitters=["nozzle"]), "emitters\\[0\\]"),
        (dict(cfl=0.0), "cfl"),
        (dict(sort_every=-1), "sort_every"),
    ]
    for kwargs, match in cases:
        args = dict(positions=good, spacing=s)
        args.update(kwargs)
        with pytest.raises(ValueError, match=match):
            ParticleFluid(args.pop("positions"), spacing=args.pop("spacing"), device="cpu", **args)
    with pytest.raises(ValueError, match="radius"):
        Nozzle((0, 0, 0), radius=0.0)
    with pytest.raises(ValueError, match="Sink upper"):
        Sink((0, 0, 0), (1, -1, 1))
    f = ParticleFluid(good, spacing=s, device="cpu")
    with pytest.raises(ValueError, match="dt"):
        f.step(0.0)


# ------------------------------------------------------------------------------ surface
def test_fluid_surface_block_volume_and_watertight():
    from warpsim.particle_fluids.surface import FluidSurface

    s = 0.02
    f = ParticleFluid(fluid_block((0.1, 0.0, 0.1), (0.3, 0.2, 0.3), s), spacing=s,
                      domain=((0, 0, 0), (0.4, 0.4, 0.4)), device="cpu")
    surface = FluidSurface(f, cell=0.5 * s)
    v, faces, _ = surface.mesh().numpy()
    volume = np.einsum("ij,ij->i", v[faces[:, 0]], np.cross(v[faces[:, 1]], v[faces[:, 2]])).sum() / 6.0
    assert abs(volume / 0.2**3 - 1.0) < 0.03
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert np.all(counts == 2)  # closed (the floor side is capped at the grid boundary)
    field = surface.field.numpy()
    assert field.min() < 0.0 < field.max()


# ------------------------------------------------------------------------------ scenes, example
@pytest.mark.parametrize("name, params, frames", [
    ("dam_break", {"spacing": 0.05, "column": (0.2, 0.3, 0.2), "box": (0.6, 0.4, 0.2)}, 4),
    ("pour", {"spacing": 0.04}, 24),
    ("dam_break", {"spacing": 0.05, "column": (0.2, 0.3, 0.2), "box": (0.6, 0.4, 0.2), "method": "dfsph"}, 4),
    ("pour", {"spacing": 0.04, "method": "dfsph"}, 24),
])
def test_scene_writes_points_with_ids_and_a_changing_surface(name, params, frames, tmp_path):
    from pxr import Usd

    from warpsim.scenes import get_scene
    from warpsim.usd.writer import UsdCacheWriter

    scene = get_scene(name)(params, device="cpu")
    with UsdCacheWriter(str(tmp_path / f"{name}.usda"), fps=60) as writer:
        scene.declare(writer)
        writer.write_frame(0, scene.frame_data())
        for frame in range(1, frames + 1):
            scene.advance(1.0 / 60.0, 1)
            writer.write_frame(frame, scene.frame_data())
    stage = Usd.Stage.Open(writer.output_path)
    points = stage.GetPrimAtPath("/World/particles")
    surface = stage.GetPrimAtPath("/World/surface")
    counts = []
    for t in range(frames + 1):
        ids = np.array(points.GetAttribute("ids").Get(t))
        assert len(np.unique(ids)) == len(ids) == len(points.GetAttribute("points").Get(t))
        counts.append(len(ids))
    first = np.array(surface.GetAttribute("faceVertexIndices").Get(frames // 2))
    last = np.array(surface.GetAttribute("faceVertexIndices").Get(frames))
    assert len(last) > 0 and not np.array_equal(first, last)  # the topology changes
    if name == "pour":
        assert counts[0] == 0 and counts[-1] > counts[frames // 2] > 0  # the nozzle keeps emitting
    else:
        assert len(set(counts)) == 1
    # checkpoint / restore continues bit for bit
    saved = scene.checkpoint()
    scene.advance(1.0 / 60.0, 1)
    after = scene.fluid.positions.numpy().copy()
    scene.restore(saved)
    scene.advance(1.0 / 60.0, 1)
    np.testing.assert_array_equal(scene.fluid.positions.numpy(), after)


def test_dam_break_example_runs(tmp_path):
    import os
    import subprocess
    import sys
    from pathlib import Path

    script = Path(__file__).resolve().parents[1] / "examples" / "dam_break.py"
    out = subprocess.run([sys.executable, str(script), "--frames", "3", "--spacing", "0.05", "--depth", "0.1",
                          "--out", str(tmp_path / "db.usda"), "--figure", str(tmp_path / "front.png")],
                         capture_output=True, text=True, timeout=600,
                         env=dict(os.environ, WARP_QUIET="1"))
    assert out.returncode == 0, out.stderr[-2000:]
    rows = [line.split() for line in out.stdout.splitlines() if line.strip()[:1].isdigit() and len(line.split()) == 6]
    assert [int(r[0]) for r in rows] == [1, 2, 3]
    assert float(rows[-1][2]) > 1.0  # the front has moved
    assert (tmp_path / "db.usda").exists()
    from PIL import Image

    with Image.open(tmp_path / "front.png") as fig:  # the surge front against Martin and Moyce
        assert fig.size == (540, 360)


def test_deep_column_small_steps_keep_peak_compression():
    """A 3D column 24 x 48 x 24 particles collapsing, at cfl 0.1 against cfl 0.4 (5 frames).
    Regression: with only the mean-compression stop, the small steps ran ~1 correction each, a
    local compression under the column grew to 10 % (the mean stayed below 0.2 %) and turned into
    velocity ~ C spacing / dt: 2.92 m/s at t = 0.083 s against 1.72 at cfl 0.4 (the same column
    with 1M particles on an H200 blew up). Now a step also iterates while any particle is
    compressed by peak_tolerance (2 %) or more. Measured: peak <= 1.9 % at every frame end, speeds
    1.76 vs 1.73 m/s at frame 5, 1.9 corrections per step (10.8 at cfl 0.4)."""
    s, n = 0.01, 24
    x0 = fluid_block((0, 0, 0), (n * s, 2 * n * s, n * s), s)
    runs = {}
    for cfl in (0.4, 0.1):
        f = ParticleFluid(x0, spacing=s, domain=((0, 0, 0), (4 * n * s, 3 * n * s, n * s)), cfl=cfl, device="cpu")
        peaks, speeds = [], []
        for _ in range(5):
            f.advance(1.0 / 60.0)
            peaks.append(f.density_error()[1])
            speeds.append(f.max_speed_now())
        runs[cfl] = (np.array(peaks), np.array(speeds), f.total_iterations / f.step_count)
        print(f"cfl {cfl}: peak compression {np.round(peaks, 4)}, max speed {np.round(speeds, 3)}, "
              f"{runs[cfl][2]:.2f} corrections/step")
    peaks, speeds, per_step = runs[0.1]
    assert np.all(peaks < 0.03), peaks
    np.testing.assert_allclose(speeds, runs[0.4][1], rtol=0.1)
    assert per_step < 3.0  # the peak criterion costs little: small steps still need few corrections
