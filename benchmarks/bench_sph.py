"""Position-based-fluid step throughput, side by side in one process.

1. warpsim's Warp PBF step against a NumPy + SciPy-cKDTree reference step of the same method on
   the same particles (``warpsim.sph_reference``), with the largest position difference.
2. warpsim's PBF against Warp's own SPH example (``warp/examples/core/example_sph.py``, Mueller
   et al. 2003, weakly compressible, ~4 neighbours per particle) at the same particle count,
   running that example's kernels with its own constants; particle-steps per second for both
   and each one's density error (warpsim: mean compression max(rho/rho0 - 1, 0); the example:
   mean |rho/rho0 - 1| of its particles, rho0 = its base density).

    python benchmarks/bench_sph.py                          # CPU, 8,000 particles
    python benchmarks/bench_sph.py --device cuda:0 --particles 1000000 --steps 20
"""

import argparse
import math
import time

import numpy as np
import warp as wp

from warpsim.sph import ParticleFluid, fluid_block, wall_tables
from warpsim.sph_reference import pbf_step_numpy


def block_for(count, spacing):
    """A column of about ``count`` particles (base n x n, height 2n) and a box around it."""
    n = max(2, round((count / 2.0) ** (1.0 / 3.0)))
    size = np.array([n, 2 * n, n]) * spacing
    box = np.array([4 * n, 3 * n, n]) * spacing
    return fluid_block((0, 0, 0), size, spacing), box


def timed(fn, steps, device):
    wp.synchronize_device(device)
    t0 = time.perf_counter()
    for _ in range(steps):
        fn()
    wp.synchronize_device(device)
    return (time.perf_counter() - t0) / steps


def bench_warpsim(count, steps, iterations, device, shuffle=False):
    s = 0.01
    x0, box = block_for(count, s)
    if shuffle:  # memory order unrelated to space (as after long mixing), then sorted once
        x0 = x0[np.random.default_rng(0).permutation(len(x0))]
    fluid = ParticleFluid(x0, spacing=s, domain=((0, 0, 0), box), iterations=iterations, viscosity=0.01,
                          device=device)
    if shuffle == "sorted":
        fluid.sort_particles()
    dt = 1.0 / 400.0
    for _ in range(3):  # warm up (kernel compilation) and let pressure build
        fluid.step(dt)
    t = timed(lambda: fluid.step(dt), steps, device)
    return fluid, t, fluid.density_error()[0]


def bench_reference(fluid, steps):
    """NumPy/cKDTree steps from the fluid's current state, and a Warp step from the same state."""
    s = fluid.spacing
    lo, hi = fluid.domain
    eye = np.eye(3)
    normals = np.concatenate([eye, -eye])
    offsets = np.concatenate([lo, -hi])
    phi, dphi = wall_tables(fluid.h, fluid.kernel, s)
    x = fluid.positions.numpy().astype(np.float64)
    v = fluid.velocities.numpy().astype(np.float64)
    dt = fluid.last_dt
    args = dict(h=fluid.h, mass=fluid.particle_mass, rest_density=fluid.rest_density, kernel=fluid.kernel,
                iterations=fluid.iterations, viscosity=0.01, radius=0.5 * s, relaxation=1e-6 / s**2,
                normals=normals, offsets=offsets, phi_table=phi, dphi_table=dphi)
    t0 = time.perf_counter()
    xr, vr = x, v
    for _ in range(steps):
        xr, vr, _ = pbf_step_numpy(xr, vr, dt, **args)
    t_ref = (time.perf_counter() - t0) / steps
    for _ in range(steps):
        fluid.step(dt)
    diff = np.abs(fluid.positions.numpy() - xr).max()
    return t_ref, diff


def bench_warp_example(count, steps, device, fitted_grid=False):
    """Warp's example_sph kernels and constants at ``count`` particles (box widened to fit).
    Its hash grid is 25^3 cells of width h (``height / (4 h)``, sized for its own 62,500-particle
    box); ``fitted_grid`` sizes it like warpsim's instead (one cell per h over the particles'
    extent, at most 128 per axis), which removes hash collisions at large counts."""
    from warp.examples.core import example_sph as ex

    h = 0.8
    height = 80.0
    nr_y = int(height / h)
    nr_xz = max(1, round(math.sqrt(count / nr_y)))
    width = length = 4.0 * h * nr_xz + 1e-3
    n = nr_xz * nr_y * nr_xz
    mass = 0.01 * h**3
    dt = 0.01 * h
    base_density, isotropic_exp, visc, damping, gravity = 1.0, 20.0, 0.025, -0.95, -0.1
    density_norm = (315.0 * mass) / (64.0 * np.pi * h**9)
    pressure_norm = -(45.0 * mass) / (np.pi * h**6)
    viscous_norm = (45.0 * visc * mass) / (np.pi * h**6)
    x = wp.empty(n, dtype=wp.vec3, device=device)
    v = wp.zeros(n, dtype=wp.vec3, device=device)
    rho = wp.zeros(n, dtype=float, device=device)
    a = wp.zeros(n, dtype=wp.vec3, device=device)
    wp.launch(ex.initialize_particles, n, inputs=[x, h, width, height, length], device=device)
    grid_size = int(height / (4.0 * h))
    dims = (grid_size,) * 3
    if fitted_grid:
        dims = tuple(int(min(128, math.ceil(e / h) + 1)) for e in (width, height, length))
    grid = wp.HashGrid(*dims, device=device)

    def step():
        grid.build(x, h)
        wp.launch(ex.compute_density, n, inputs=[grid.id, x, rho, density_norm, h], device=device)
        wp.launch(ex.get_acceleration, n, inputs=[grid.id, x, v, rho, a, isotropic_exp, base_density, gravity,
                                                  pressure_norm, viscous_norm, h], device=device)
        wp.launch(ex.apply_bounds, n, inputs=[x, v, damping, width, height, length], device=device)
        wp.launch(ex.kick, n, inputs=[v, a, dt], device=device)
        wp.launch(ex.drift, n, inputs=[x, v, dt], device=device)

    for _ in range(3):
        step()
    t = timed(step, steps, device)
    return n, t, float(np.abs(rho.numpy() / base_density - 1.0).mean())


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--particles", type=int, default=8000)
    parser.add_argument("--steps", type=int, default=5)
    parser.add_argument("--iterations", type=int, default=4)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--order", action="store_true",
                        help="also time warpsim with particles shuffled in memory, and shuffled then sorted")
    parser.add_argument("--reference-max", type=int, default=100000,
                        help="skip the NumPy reference above this many particles")
    args = parser.parse_args(argv)
    wp.config.quiet = True
    device = wp.get_device(args.device)

    n_ex, t_ex, err_ex = bench_warp_example(args.particles, args.steps, device)
    _, t_fit, _ = bench_warp_example(args.particles, args.steps, device, fitted_grid=True)
    fluid, t_ws, err_ws = bench_warpsim(n_ex, args.steps, args.iterations, device)
    n = fluid.active_count
    print(f"device {device}, {args.iterations} PBF iterations, {args.steps} timed steps")
    print(f"warpsim PBF          : {n:9d} particles  {t_ws * 1e3:9.2f} ms/step  {n / t_ws:12.4g} particle-steps/s  "
          f"mean compression {err_ws:.2e}")
    print(f"warp example_sph     : {n_ex:9d} particles  {t_ex * 1e3:9.2f} ms/step  {n_ex / t_ex:12.4g} particle-steps/s  "
          f"mean |rho/rho0 - 1| {err_ex:.2e}")
    print(f"  same, grid fitted  : {n_ex:9d} particles  {t_fit * 1e3:9.2f} ms/step  {n_ex / t_fit:12.4g} particle-steps/s")
    print(f"ratio warpsim / warp example (particle-steps/s): {(n / t_ws) / (n_ex / t_ex):.3f} "
          f"(vs the example with a fitted grid: {(n / t_ws) / (n_ex / t_fit):.3f})")
    if args.order:
        for mode in ("shuffled", "sorted"):
            f2, t2, _ = bench_warpsim(n_ex, args.steps, args.iterations, device, shuffle=mode)
            print(f"  warpsim, {mode:9s} : {f2.active_count:9d} particles  {t2 * 1e3:9.2f} ms/step  "
                  f"{f2.active_count / t2:12.4g} particle-steps/s  (memory order {mode})")
    if n <= args.reference_max:
        steps = max(1, min(args.steps, 3))
        t_ref, diff = bench_reference(fluid, steps)
        print(f"NumPy/cKDTree PBF    : {n:9d} particles  {t_ref * 1e3:9.2f} ms/step  {n / t_ref:12.4g} particle-steps/s")
        print(f"ratio warpsim / NumPy reference (same method, same particles): {t_ref / t_ws:.1f}x faster; "
              f"max position difference after {steps} steps {diff:.2e} m")
    else:
        print(f"NumPy reference skipped above {args.reference_max} particles (--reference-max)")


if __name__ == "__main__":
    main()
