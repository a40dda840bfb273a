"""Particle-fluid throughput against Warp's own SPH example, side by side in one process.

1. Warp's ``warp/examples/core/example_sph.py`` (Mueller et al. 2003, weakly compressible) with its
   own kernels and constants, its box widened to hold about ``--particles`` particles.
2. warpsim's position-based fluid at the same particle count: a dam break (a column n x 2n x n
   in a 4n x 3n x n box) advanced frame by frame in CFL-limited sub-steps with its default
   solver settings, as a user runs it.

For each: particle-steps per second and their ratio, and what a step buys, so the ratio is read
honestly: the density error each one actually keeps (max and mean |rho/rho0 - 1| over the
fluid interior, i.e. particles whose whole kernel support is fluid or wall; warpsim also gives
the mean compression over all particles), neighbours per particle, simulated seconds per
wall-clock second, and the same in gravity time units t sqrt(g / L) (L: particle spacing),
which compares step sizes across the two unit systems. Optionally warpsim's Warp step against a
NumPy + SciPy-cKDTree reference step of the same method (``warpsim.particle_fluids.reference``).

    python benchmarks/bench_sph.py                          # CPU, 8,000 particles
    python benchmarks/bench_sph.py --device cuda:0 --particles 1000000 --frames 4
"""

import argparse
import math
import sys
import time

import numpy as np
import warp as wp
from timing import activity_name

from warpsim.cli_common import DefaultsHelpFormatter, device_arg, run_script
from warpsim.particle_fluids.pbf import ParticleFluid
from warpsim.particle_fluids.reference import pbf_step_numpy
from warpsim.particle_fluids.smoothing import fluid_block, wall_tables
from warpsim.verbosity import set_warp_verbosity


def block_for(count, spacing):
    """A column of about ``count`` particles (base n x n, height 2n) and a box around it."""
    n = max(2, round((count / 2.0) ** (1.0 / 3.0)))
    size = np.array([n, 2 * n, n]) * spacing
    box = np.array([4 * n, 3 * n, n]) * spacing
    return fluid_block((0, 0, 0), size, spacing), box


def interior_mask(x, lower, upper, cell):
    """Particles whose cell (width ``cell`` = the kernel support) and its 26 neighbours all hold
    particles or lie outside the box [lower, upper] (walls): their kernel support is fluid or wall,
    not free surface."""
    dims = np.maximum(np.ceil((upper - lower) / cell).astype(int), 1)
    idx = np.clip(np.floor((x - lower) / cell).astype(int), 0, dims - 1)
    full = np.ones(dims + 2, bool)  # one layer of outside cells around the box counts as wall
    full[1:-1, 1:-1, 1:-1] = False
    full[idx[:, 0] + 1, idx[:, 1] + 1, idx[:, 2] + 1] = True
    ok = np.ones(dims, bool)
    for a in range(3):
        for b in range(3):
            for c in range(3):
                ok &= full[a:a + dims[0], b:b + dims[1], c:c + dims[2]]
    return ok[idx[:, 0], idx[:, 1], idx[:, 2]]


def density_errors(rho_ratio, interior):
    """(max |rho/rho0 - 1|, mean |rho/rho0 - 1|, max (rho/rho0 - 1)) over the interior particles
    (nan when there are none)."""
    e = np.asarray(rho_ratio, np.float64)[interior] - 1.0
    return (float(np.abs(e).max()), float(np.abs(e).mean()), float(e.max())) if e.size else (math.nan,) * 3


def sync_time(device):
    wp.synchronize_device(device)
    return time.perf_counter()


def bench_warp_example(count, steps, device, fitted_grid=False):
    """Warp's example_sph kernels and constants at ``count`` particles (box widened to fit).
    Its hash grid is 25^3 cells of width h (``height / (4 h)``, sized for its own 62,500-particle
    box); ``fitted_grid`` sizes it like warpsim's instead (one cell per h over the particles'
    extent, at most 128 per axis), which removes hash collisions at large counts."""
    from warp.examples.core import example_sph as ex

    h = 0.8  # its smoothing length: the kernel support and the initial particle spacing
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
    t0 = sync_time(device)
    for _ in range(steps):
        step()
    wall = sync_time(device) - t0
    xs = x.numpy()
    lower, upper = np.zeros(3), np.array([width, height, length])
    err_max, err_mean, err_comp = density_errors(rho.numpy() / base_density, interior_mask(xs, lower, upper, h))
    out = dict(name="warp example_sph", n=n, steps=steps, wall=wall, sim_time=steps * dt, spacing=h, g=-gravity,
               err_max=err_max, err_mean=err_mean, err_comp=err_comp, compression=math.nan, iterations=math.nan,
               cfl=float(np.linalg.norm(v.numpy(), axis=1).max()) * dt / h)
    if n <= 200000:
        out["neighbors"] = neighbors_per_particle(xs, h)
    return out


def neighbors_per_particle(x, radius):
    """Mean number of other particles within ``radius`` (cKDTree; nan without SciPy)."""
    try:
        from scipy.spatial import cKDTree
    except ImportError:  # pragma: no cover - SciPy is optional
        return math.nan
    return 2.0 * len(cKDTree(x).query_pairs(radius)) / len(x)


def bench_warpsim(count, frames, warmup, device, sort_every=0, fixed_dt=None, steps_per_frame=10, **settings):
    """warpsim's dam break at ``count`` particles: ``warmup`` untimed frames, then ``frames``
    timed frames of 1/60 s (or, with ``fixed_dt``, frames of ``steps_per_frame`` steps of that
    length); density errors measured (untimed) after every timed frame."""
    s = 0.01
    x0, box = block_for(count, s)
    fluid = ParticleFluid(x0, spacing=s, domain=((0, 0, 0), box), sort_every=sort_every, device=device,
                          **settings)
    for _ in range(warmup):  # with fixed_dt in steps of that length too: PBF wants steps of similar size
        if fixed_dt is None:
            fluid.advance(1.0 / 60.0)
        else:
            for _ in range(steps_per_frame):
                fluid.step(fixed_dt)
    wall, steps, iters, sim = 0.0, 0, 0, 0.0
    worst, comp, means, compressions, cfl = 0.0, 0.0, [], [], 0.0
    for _ in range(frames):
        steps0, iters0, t_sim0 = fluid.step_count, fluid.total_iterations, fluid.time
        t0 = sync_time(device)
        if fixed_dt is None:
            fluid.advance(1.0 / 60.0)
        else:
            for _ in range(steps_per_frame):
                fluid.step(fixed_dt)
        wall += sync_time(device) - t0
        steps += fluid.step_count - steps0
        iters += fluid.total_iterations - iters0
        sim += fluid.time - t_sim0
        cfl = max(cfl, fluid.max_speed_now() * fluid.last_dt / s)
        rho = fluid.measure_density() / fluid.rest_density
        e_max, e_mean, e_comp = density_errors(rho, interior_mask(fluid.positions.numpy(), *fluid.domain, fluid.h))
        worst, comp = max(worst, e_max), max(comp, e_comp)
        means.append(e_mean)
        compressions.append(float(np.maximum(rho - 1.0, 0.0).mean()))
    n = fluid.active_count
    nb = fluid._neighbors.count.numpy()[:n]
    out = dict(name="warpsim PBF", n=n, steps=steps, wall=wall, sim_time=sim, spacing=s, g=9.81, err_max=worst,
               err_comp=comp, err_mean=float(np.mean(means)), compression=float(np.mean(compressions)),
               iterations=iters / max(steps, 1), neighbors=float(nb.mean()), cfl=cfl)
    return fluid, out


def report(r):
    rate = r["n"] * r["steps"] / r["wall"]
    tau = r["sim_time"] * math.sqrt(r["g"] / r["spacing"])
    print(f"{r['name']:18s}: {r['n']:9d} particles  {r['steps']:5d} steps  {r['wall'] / r['steps'] * 1e3:8.2f} ms/step  "
          f"{rate:10.4g} particle-steps/s")
    print(f"{'':18s}  interior |rho/rho0 - 1|: max {r['err_max']:.2e} (largest compression {r['err_comp']:+.2e}), "
          f"mean {r['err_mean']:.2e}"
          + (f"; mean compression (all) {r['compression']:.2e}" if not math.isnan(r["compression"]) else ""))
    print(f"{'':18s}  {r.get('neighbors', math.nan):5.1f} neighbours/particle"
          + (f", {r['iterations']:.2f} solver iterations/step" if not math.isnan(r["iterations"]) else "")
          + f", max CFL number v dt / spacing {r['cfl']:.3f}")
    print(f"{'':18s}  simulated {r['sim_time'] / r['wall']:.4g} s per wall-clock s; "
          f"{tau / r['wall']:.4g} gravity time units t sqrt(g/spacing) per wall-clock s "
          f"({tau / r['steps']:.3g} per step)")
    return rate, tau / r["wall"]


def profile_kernels(run, device, top=8):
    """Per-kernel GPU time of ``run()`` (Warp's activity timing; CUDA only), largest first."""
    if not device.is_cuda:
        print("  (--profile needs a CUDA device)")
        return
    wp.timing_begin(cuda_filter=wp.TIMING_ALL)
    run()
    results = wp.timing_end()
    totals = {}
    for r in results:
        name = activity_name(r)  # the kernel's Python name, without the module hash
        totals[name] = totals.get(name, 0.0) + r.elapsed
    whole = sum(totals.values())
    for name, ms in sorted(totals.items(), key=lambda kv: -kv[1])[:top]:
        print(f"    {ms:9.2f} ms  {100.0 * ms / whole:5.1f} %  {name}")


def bench_reference(fluid, steps):
    """NumPy/cKDTree steps from the fluid's current state, and Warp steps (fixed iterations, as
    the reference) from the same state; returns (seconds per reference step, max position
    difference)."""
    s = fluid.spacing
    lo, hi = fluid.domain
    eye = np.eye(3)
    normals = np.concatenate([eye, -eye])
    offsets = np.concatenate([lo, -hi])
    phi, dphi = wall_tables(fluid.h, fluid.kernel, s)
    x = fluid.positions.numpy().astype(np.float64)
    v = fluid.velocities.numpy().astype(np.float64)
    dt = fluid.last_dt
    fixed = ParticleFluid(x, v, spacing=s, domain=fluid.domain, iterations=fluid.iterations, density_tolerance=0.0,
                          viscosity=float(fluid._params.viscosity), device=fluid.device)
    args = dict(h=fluid.h, mass=fluid.particle_mass, rest_density=fluid.rest_density, kernel=fluid.kernel,
                iterations=fluid.iterations, viscosity=float(fluid._params.viscosity), radius=0.5 * s,
                relaxation=1e-6 / s**2, normals=normals, offsets=offsets, phi_table=phi, dphi_table=dphi)
    t0 = time.perf_counter()
    xr, vr = x, v
    for _ in range(steps):
        xr, vr, _ = pbf_step_numpy(xr, vr, dt, **args)
    t_ref = (time.perf_counter() - t0) / steps
    for _ in range(steps):
        fixed.step(dt)
    return t_ref, float(np.abs(fixed.positions.numpy() - xr).max())


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=DefaultsHelpFormatter)
    parser.add_argument("--particles", type=int, default=8000)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--frames", type=int, default=6, help="timed warpsim frames of 1/60 s")
    parser.add_argument("--warmup", type=int, default=2, help="untimed warpsim frames before timing")
    parser.add_argument("--steps", type=int, default=40, help="timed steps of Warp's example")
    parser.add_argument("--iterations", type=int, default=40,
                        help="warpsim's most PBF iterations per step (it stops at the density tolerance)")
    parser.add_argument("--matched-step", action="store_true",
                        help="also time warpsim at the example's step size in gravity time units")
    parser.add_argument("--order", action="store_true",
                        help="also time warpsim sorting its particles spatially every frame")
    parser.add_argument("--cfl", type=float, default=None,
                        help="warpsim's CFL number (default: the fluid's own, 0.4 on the CPU, 0.2 on GPUs)")
    parser.add_argument("--profile", action="store_true",
                        help="print the GPU time per kernel of one more warpsim frame and of 10 example steps")
    parser.add_argument("--reference-max", type=int, default=20000,
                        help="skip the NumPy reference above this many particles")
    args = parser.parse_args(argv)
    set_warp_verbosity()  # quiet unless $WARPSIM_VERBOSE=1 (Warp 1.19 ignores config.quiet)
    device = wp.get_device(device_arg(args.device))

    ex = bench_warp_example(args.particles, args.steps, device)
    ex_fit = bench_warp_example(args.particles, args.steps, device, fitted_grid=True)
    fluid, ws = bench_warpsim(ex["n"], args.frames, args.warmup, device, iterations=args.iterations, cfl=args.cfl)
    print(f"device {device}; warpsim: dam break, {args.warmup} + {args.frames} frames of 1/60 s in CFL sub-steps "
          f"(cfl {fluid.cfl:g}), "
          f"at most {args.iterations} PBF iterations/step"
          + (f", stopping at mean compression {fluid.density_tolerance:g}" if fluid._adaptive else ""))
    rate_ws, tau_ws = report(ws)
    rate_ex, tau_ex = report(ex)
    rate_fit = ex_fit["n"] * ex_fit["steps"] / ex_fit["wall"]
    print(f"{'  same, grid fitted':18s}: {ex_fit['n']:9d} particles  {ex_fit['steps']:5d} steps  "
          f"{ex_fit['wall'] / ex_fit['steps'] * 1e3:8.2f} ms/step  {rate_fit:10.4g} particle-steps/s")
    print(f"ratio warpsim / warp example, particle-steps/s: {rate_ws / rate_ex:.3f} "
          f"(vs the example with a fitted grid: {rate_ws / rate_fit:.3f}); "
          f"gravity time units per wall-clock s: {tau_ws / tau_ex:.3g}")
    if args.matched_step:  # the example's step t sqrt(g / spacing), in warpsim's units
        dt = ex["sim_time"] / ex["steps"] * math.sqrt(ex["g"] / ex["spacing"]) / math.sqrt(9.81 / 0.01)
        _, tiny = bench_warpsim(ex["n"], args.frames, args.warmup, device, fixed_dt=dt, iterations=args.iterations)
        tiny["name"] = "  warpsim, same dt"
        print(f"warpsim at the example's step size (dt = {dt:.3g} s) from the start of the dam break, "
              f"{args.warmup} x 10 steps untimed:")
        rate, _ = report(tiny)
        print(f"  ratio warpsim / warp example at equal step size, particle-steps/s: {rate / rate_ex:.3f}")
    if args.order:
        _, sorted_run = bench_warpsim(ex["n"], args.frames, args.warmup, device, sort_every=1,
                                      iterations=args.iterations)
        rate = sorted_run["n"] * sorted_run["steps"] / sorted_run["wall"]
        print(f"  warpsim sorting particles every frame: {rate:10.4g} particle-steps/s ({rate / rate_ws:.3f} x unsorted)")
    if args.profile:
        print("one more warpsim frame (1/60 s), GPU time per kernel:")
        profile_kernels(lambda: fluid.advance(1.0 / 60.0), device)
    if fluid.active_count <= args.reference_max:
        t_ref, diff = bench_reference(fluid, 2)
        n = fluid.active_count
        print(f"NumPy/cKDTree PBF   : {n:9d} particles  {t_ref * 1e3:8.2f} ms/step; warpsim with the same "
              f"{fluid.iterations} fixed iterations matches it to {diff:.2e} m after 2 steps")
    else:
        print(f"NumPy reference skipped above {args.reference_max} particles (--reference-max)")


if __name__ == "__main__":
    sys.exit(run_script(main))
