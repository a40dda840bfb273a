"""Cloth frame time: warpsim against the mass-spring cloth benchmark that ships with Warp.

Reference: ``warp/examples/benchmarks/benchmark_cloth_warp.py`` (its ``WpIntegrator``, loaded
from the installed warp package) on the cloth of ``benchmark_cloth.py``: a dim x dim grid 0.1 m
apart, structural / shear / bend springs all k = 1000 N/m, damping 10 N s/m, 0.1 kg particles,
two corners fixed, 60 fps, 16 sub-steps, positions copied to the host every frame.

warpsim builds the same cloth with ``add_cloth_grid`` and steps it with ``ClothSimulator``
(semi-implicit Euler, each frame's 16 sub-steps replayed as one captured graph) while also
colliding it with a floor and a sphere (``--no-collisions`` to skip them); ``--modes simulator``
also steps it with the generic ``ws.Simulator`` at its defaults (semi-implicit Euler, gravity,
blow-up test every step, one ``step()`` per sub-step); all run in this process, frame by frame,
interleaved; ``--repeats`` repeats that in the same process (the spread of the ratio across
repeats is printed: on a shared machine only ratios measured side by side mean anything).
``--profile`` times every launch of one warpsim frame alone against the reference's launches.
Then implicit Euler (Baraff-Witkin, one step per frame): frame time and CG iterations.

    python benchmarks/bench_cloth.py --device cpu --dims 32 64 128 --implicit-dims 64 128
    python benchmarks/bench_cloth.py --device cpu --dims 64 --implicit-dims --modes auto simulator --no-collisions
    python benchmarks/bench_cloth.py --device cpu --dims 64 --implicit-dims --modes auto scatter --repeats 5 --profile
    python benchmarks/bench_cloth.py --device cuda:0 --dims 32 64 128 256 512 1024 --implicit-dims 64 128 256
"""

from __future__ import annotations

import argparse
import ast
import functools
import importlib.util
import os
import sys
import time

import numpy as np
import warp as wp

from warpsim.verbosity import set_warp_verbosity

set_warp_verbosity()  # quiet unless $WARPSIM_VERBOSE=1 (Warp 1.19 ignores config.quiet)
wp.config.log_level = getattr(wp, "LOG_WARNING", wp.config.log_level)  # no module-load lines

import warpsim as ws
import warpsim.bodies.colliders as ws_colliders
from warpsim.cli_common import DefaultsHelpFormatter, device_arg, run_script
from warpsim.cloth.builder import add_cloth_grid
from warpsim.cloth.solver import ClothImplicitEuler, ClothSemiImplicitEuler, ClothSimulator

FPS, SUBSTEPS, SPACING, K, KD, MASS = 60.0, 16, 0.1, 1000.0, 10.0, 0.1


def warp_benchmark_dir():
    return os.path.join(os.path.dirname(wp.__file__), "examples", "benchmarks")


def load_reference():
    """(Cloth class of benchmark_cloth.py, WpIntegrator of benchmark_cloth_warp.py).

    benchmark_cloth.py runs its benchmark at import, so only its ``Cloth`` class is executed;
    benchmark_cloth_warp.py calls ``wp.clear_kernel_cache()`` at import, which is skipped here
    (it would wipe every compiled kernel of this process's cache)."""
    folder = warp_benchmark_dir()
    with open(os.path.join(folder, "benchmark_cloth.py")) as f:
        tree = ast.parse(f.read())
    cls = next(node for node in tree.body if isinstance(node, ast.ClassDef) and node.name == "Cloth")
    namespace = {"np": np}
    exec(compile(ast.Module(body=[cls], type_ignores=[]), "benchmark_cloth.py", "exec"), namespace)  # noqa: S102
    spec = importlib.util.spec_from_file_location("benchmark_cloth_warp", os.path.join(folder, "benchmark_cloth_warp.py"))
    module = importlib.util.module_from_spec(spec)
    clear = wp.clear_kernel_cache
    wp.clear_kernel_cache = lambda: None
    try:
        spec.loader.exec_module(module)
    finally:
        wp.clear_kernel_cache = clear
    return namespace["Cloth"], module.WpIntegrator


class ReferenceCloth:
    """The arrays of benchmark_cloth.py's ``Cloth`` (same springs, same order), built with NumPy
    so that 1024^2 grids take seconds; checked against the original class up to 128^2."""

    def __init__(self, dim):
        d = dim
        idx = np.arange(d * d).reshape(d, d)  # [y, x]
        y, x = np.meshgrid(np.arange(d), np.arange(d), indexing="ij")
        # horizontal pass (y outer, x inner): (x-1), (x-2), (y-1, x+1), (y-1, x-1)
        cand = np.stack([idx - 1, idx - 2, idx - d + 1, idx - d - 1], axis=-1)
        ok = np.stack([x > 0, x > 1, (y > 0) & (x < d - 1), (y > 0) & (x > 0)], axis=-1)
        first = np.broadcast_to(idx[..., None], cand.shape)
        h = np.stack([first[ok], cand[ok]], axis=1)
        # vertical pass (x outer, y inner): (y-1), (y-2)
        cand = np.stack([idx - d, idx - 2 * d], axis=-1).transpose(1, 0, 2)
        ok = np.stack([y > 0, y > 1], axis=-1).transpose(1, 0, 2)
        first = np.broadcast_to(idx.T[..., None], cand.shape)
        v = np.stack([first[ok], cand[ok]], axis=1)
        pairs = np.concatenate([h, v])
        self.positions = np.stack([x * SPACING, 0 * x, y * SPACING], -1).reshape(-1, 3).astype(np.float32)
        self.velocities = np.zeros_like(self.positions)
        inv = np.full(d * d, 1.0 / MASS, dtype=np.float32)
        inv[[0, d - 1]] = 0.0
        self.inv_masses = inv
        self.spring_indices = pairs.reshape(-1).astype(np.int32)
        self.spring_lengths = np.linalg.norm(self.positions[pairs[:, 0]] - self.positions[pairs[:, 1]],
                                             axis=1).astype(np.float32)
        self.spring_stiffness = np.full(len(pairs), K, dtype=np.float32)
        self.spring_damping = np.full(len(pairs), KD, dtype=np.float32)
        self.num_particles = d * d
        self.num_springs = len(pairs)


def check_reference_cloth(Cloth, dim):
    ref = Cloth(lower=(0.0, 0.0, 0.0), dx=dim, dy=dim, radius=SPACING, stretch_stiffness=K, bend_stiffness=K,
                shear_stiffness=K, mass=MASS, fix_corners=True)
    mine = ReferenceCloth(dim)
    for name in ("positions", "inv_masses", "spring_indices", "spring_stiffness", "spring_damping"):
        if not np.array_equal(np.asarray(getattr(ref, name)), getattr(mine, name)):
            raise RuntimeError(f"NumPy rebuild of benchmark_cloth.Cloth differs in {name} at {dim}^2")
    if not np.allclose(ref.spring_lengths, mine.spring_lengths):
        raise RuntimeError(f"NumPy rebuild of benchmark_cloth.Cloth differs in spring_lengths at {dim}^2")


def warpsim_model(dim, device):
    b = ws.ModelBuilder()
    cloth = add_cloth_grid(b, (dim - 1, dim - 1), (SPACING * (dim - 1),) * 2, (0.0, 0.0, 0.0), u_axis=(1, 0, 0),
                           v_axis=(0, 0, 1), particle_mass=MASS, stiffness=K, damping=KD,
                           pin=["corner_00", "corner_10"])
    return b.finalize(device), cloth


def same_cloth(model, ref):
    """True when warpsim's model has the reference's particles, pins and springs (any order)."""
    a = np.sort(model.spring_indices.numpy().reshape(-1, 2), axis=1)
    b = np.sort(ref.spring_indices.reshape(-1, 2), axis=1)
    a, b = a[np.lexsort(a.T[::-1])], b[np.lexsort(b.T[::-1])]
    return (np.array_equal(a, b) and np.allclose(model.particle_q.numpy(), ref.positions)
            and np.array_equal(model.particle_inv_mass.numpy(), ref.inv_masses))


def colliders(dim, thickness):
    size = SPACING * (dim - 1)
    out = [ws.Plane((0.0, 1.0, 0.0), -0.6 * size, restitution=0.0, friction=0.5)]
    if hasattr(ws_colliders, "Sphere"):
        out.append(ws_colliders.Sphere((0.5 * size, -0.3 * size, 0.5 * size), 0.2 * size, restitution=0.0, friction=0.5,
                             thickness=thickness))
    return out


class Timer:
    """Wall time [s] of each call, and this thread's CPU time [s] (``cpu``): on the CPU device
    Warp runs kernels on the calling thread, so the CPU time is the work done, without the time
    the thread waited for a core on a shared machine."""

    def __init__(self, device):
        self.device = device
        self.times = []
        self.cpu = []

    def __call__(self, fn):
        wp.synchronize_device(self.device)
        c = time.thread_time()
        t = time.perf_counter()
        fn()
        wp.synchronize_device(self.device)
        self.times.append(time.perf_counter() - t)
        self.cpu.append(time.thread_time() - c)


def host_copy(sim, device):
    """The reference hands positions to the host every frame; do the same."""
    if device.is_cuda:
        host = wp.empty(sim.state.positions.shape, dtype=wp.vec3, device="cpu", pinned=True)

        def copy():
            wp.copy(host, sim.state.positions)
            wp.synchronize_device(device)
            return host.numpy()
    else:

        def copy():
            return sim.state.positions.numpy()
    return copy


def run_explicit(dim, args, device, Cloth, WpIntegrator):
    """Reference and warpsim (one simulator per kernel layout in ``args.modes``) frame by frame,
    interleaved; returns (model, reference frame times, {mode: frame times}) [s]."""
    if dim <= 128:
        check_reference_cloth(Cloth, dim)
    ref_cloth = ReferenceCloth(dim)
    model, _ = warpsim_model(dim, device)
    if not same_cloth(model, ref_cloth):
        raise RuntimeError(f"warpsim's cloth differs from the reference at {dim}^2")
    ref = WpIntegrator(ref_cloth, device)
    dt = 1.0 / FPS
    runs = {}
    for mode in args.modes:
        if mode == "simulator":  # the generic ws.Simulator, default settings (gravity, check every step)
            sim = ws.Simulator(model, colliders=[] if args.no_collisions else colliders(dim, 0.01))
            copy = host_copy(sim, device)

            def generic(sim=sim, copy=copy):
                for _ in range(SUBSTEPS):
                    sim.step(dt / SUBSTEPS)
                copy()

            runs[mode] = (generic, Timer(device))
            continue
        sim = ClothSimulator(model, ClothSemiImplicitEuler(None if mode == "auto" else mode),
                             colliders=[] if args.no_collisions else colliders(dim, 0.01))
        copy = host_copy(sim, device)

        def ours(sim=sim, copy=copy):
            sim.frame(dt, SUBSTEPS)
            copy()

        runs[f"{mode}:{sim.integrator.mode}" if mode == "auto" else mode] = (ours, Timer(device))

    def theirs():
        ref.simulate(dt, SUBSTEPS)

    for _ in range(args.warmup):
        theirs()
        for ours, _ in runs.values():
            ours()
    t_ref = Timer(device)
    for _ in range(args.frames):
        t_ref(theirs)
        for ours, timer in runs.values():
            timer(ours)
    if args.cpu_time:
        return model, np.array(t_ref.cpu), {mode: np.array(timer.cpu) for mode, (_, timer) in runs.items()}
    return model, np.array(t_ref.times), {mode: np.array(timer.times) for mode, (_, timer) in runs.items()}


def agreement(dim, device, WpIntegrator, frames=10):
    """Max distance [m] between the reference and warpsim without colliders after ``frames``."""
    ref = WpIntegrator(ReferenceCloth(dim), device)
    model, _ = warpsim_model(dim, device)
    sim = ClothSimulator(model, "semi_implicit_euler")
    for _ in range(frames):
        x_ref = ref.simulate(1.0 / FPS, SUBSTEPS)
        sim.frame(1.0 / FPS, SUBSTEPS)
    return float(np.abs(np.asarray(x_ref) - sim.state.positions.numpy()).max())


def record_frame(sim, ref, dt):
    """([(kernel, recorded launch), ...] of one eager warpsim frame, the same of one reference
    frame) in launch order: every ``wp.launch``, ``wp.copy`` and warpsim cached launch."""
    import warpsim.core.forces as ws_forces

    launch, copy, cached = wp.launch, wp.copy, ws_forces.cached_launch
    recorded = []

    def recording_launch(kernel, dim, inputs=(), outputs=(), device=None, record_cmd=False, **kw):
        cmd = launch(kernel, dim, inputs=inputs, outputs=outputs, device=device, record_cmd=True, **kw)
        recorded.append((kernel.key, cmd.launch))
        if record_cmd:
            return cmd
        cmd.launch()
        return None

    def recording_copy(dst, src, *a, **kw):
        recorded.append(("wp.copy", lambda: copy(dst, src, *a, **kw)))
        copy(dst, src, *a, **kw)

    def plain_cached(kernel, dim, inputs, device, cache, key=None, size=8):
        recording_launch(kernel, dim, inputs=list(inputs), device=device)

    wp.launch, wp.copy, ws_forces.cached_launch = recording_launch, recording_copy, plain_cached
    try:
        sim._frame_body(dt, SUBSTEPS)
        ours = list(recorded)
        recorded.clear()
        ref.simulate(dt, SUBSTEPS)
        theirs = list(recorded)
    finally:
        wp.launch, wp.copy, ws_forces.cached_launch = launch, copy, cached
    return ours, theirs


def per_frame_ms(times, launches, name, q):
    """Per-frame cost [ms] of kernel ``name``: its launches a frame x the q-th percentile of its
    single-launch times [s]."""
    return 1e3 * np.percentile(times[name], q) * launches[name]


def profile(dim, args, device, WpIntegrator, repeats=40):
    """Per-launch profile of one frame: the recorded frames (warpsim's, then the reference's)
    replayed ``repeats`` times in launch order, each launch timed alone (thread CPU time with
    ``--cpu-time``); per frame = launches a frame x min (and 10th percentile)."""
    dt = 1.0 / FPS
    ref = WpIntegrator(ReferenceCloth(dim), device)
    for mode in [m for m in args.modes if m != "simulator"]:
        model, _ = warpsim_model(dim, device)
        sim = ClothSimulator(model, ClothSemiImplicitEuler(None if mode == "auto" else mode),
                             colliders=[] if args.no_collisions else colliders(dim, 0.01))
        for _ in range(args.warmup):
            sim.frame(dt, SUBSTEPS)
            ref.simulate(dt, SUBSTEPS)
        ours_list, theirs_list = record_frame(sim, ref, dt)
        ours, theirs = {}, {}
        for group, prefix, cmds in ((theirs, "ref ", theirs_list), (ours, "", ours_list)):
            for name, fn in cmds:
                group.setdefault(prefix + name, []).append(fn)
        everything = list(theirs.items()) + list(ours.items())
        times = {k: [] for k, _ in everything}
        clock = time.thread_time if args.cpu_time else time.perf_counter
        for _ in range(repeats):
            for prefix, cmds in (("ref ", theirs_list), ("", ours_list)):
                for name, fn in cmds:
                    wp.synchronize_device(device)
                    t = clock()
                    fn()
                    wp.synchronize_device(device)
                    times[prefix + name].append(clock() - t)

        launches = {name: len(fns) for name, fns in everything}
        per_frame = functools.partial(per_frame_ms, times, launches)

        ref_total = sum(per_frame(k, 10) for k in theirs)
        print(f"profile, {dim}^2, ClothSimulator mode {sim.integrator.mode}: per frame [ms] = launches a frame x "
              f"(min, 10th percentile) of {repeats} timings ({'thread CPU' if args.cpu_time else 'wall'} time) of "
              "each launch alone; share: p10 against the reference's kernels' p10")
        print(f"| {'kernel':30s} | launches | min [ms] | p10 [ms] | share |")
        for name, fns in everything:
            print(f"| {name:30s} | {len(fns):8d} | {per_frame(name, 0):8.3f} | {per_frame(name, 10):8.3f} | "
                  f"{per_frame(name, 10) / ref_total:5.3f} |")
        total = sum(per_frame(k, 10) for k in ours)
        print(f"| {'warpsim total':30s} |          | {sum(per_frame(k, 0) for k in ours):8.3f} | {total:8.3f} | "
              f"{total / ref_total:5.3f} |")
        print(flush=True)


def run_implicit(dim, args, device):
    model, _ = warpsim_model(dim, device)
    solver = ClothImplicitEuler(cg_tol=args.cg_tol, cg_max_iterations=args.cg_max)
    sim = ClothSimulator(model, solver, colliders=[] if args.no_collisions else colliders(dim, 0.01))
    copy = host_copy(sim, device)
    iterations = []

    def ours():
        sim.frame(1.0 / FPS, 1)
        copy()

    for _ in range(args.warmup):
        ours()
    timer = Timer(device)
    for _ in range(args.implicit_frames):
        timer(ours)
        iterations.append(solver.last_cg_iterations)  # read back outside the timed frame
    return np.median(timer.times), np.mean(iterations), np.max(iterations)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=DefaultsHelpFormatter)
    parser.add_argument("--device", default=None, help="Warp device (default: Warp's preferred device)")
    parser.add_argument("--dims", type=int, nargs="+", default=[32, 64, 128], help="grid sizes (particles per side)")
    parser.add_argument("--implicit-dims", type=int, nargs="*", default=[64, 128, 256])
    parser.add_argument("--frames", type=int, default=60, help="timed frames per size")
    parser.add_argument("--implicit-frames", type=int, default=30)
    parser.add_argument("--warmup", type=int, default=3, help="untimed frames (compilation, graph capture)")
    parser.add_argument("--modes", nargs="+", choices=["auto", "scatter", "gather", "owner", "lanes", "simulator"],
                        default=["auto"],
                        help="warpsim explicit kernel layouts to time (auto: lanes on CPU where it fills half its "
                             "lanes, else owner; gather on CUDA; "
                             "simulator: the generic ws.Simulator with default settings, one step() per sub-step)")
    parser.add_argument("--cpu-time", action="store_true",
                        help="frame times as this thread's CPU time (CPU device: the work done, less the waits "
                             "for a core on a shared machine) instead of wall time")
    parser.add_argument("--repeats", type=int, default=1, help="timed runs of --frames frames per size, same process")
    parser.add_argument("--profile", action="store_true",
                        help="per-launch kernel times of one frame of each ClothSimulator mode at the first size")
    parser.add_argument("--no-collisions", action="store_true", help="warpsim without floor and sphere")
    parser.add_argument("--cg-tol", type=float, default=1.0e-4)
    parser.add_argument("--cg-max", type=int, default=200)
    args = parser.parse_args()

    wp.init()
    device = wp.get_device(device_arg(args.device))
    Cloth, WpIntegrator = load_reference()
    collide = "no collisions" if args.no_collisions else ("floor + sphere" if hasattr(ws_colliders, "Sphere") else "floor")
    print(f"device {device} ({device.name}); {SUBSTEPS} sub-steps per frame at {FPS:g} fps; warpsim colliders: "
          f"{collide}")
    print(f"agreement with the reference after 10 frames at {args.dims[0]}^2 (no colliders): "
          f"max |x_ref - x_warpsim| = {agreement(args.dims[0], device, WpIntegrator):.2e} m")
    print()
    if args.profile:
        profile(args.dims[0], args, device, WpIntegrator)
    clock = "thread CPU time" if args.cpu_time else "wall time"
    print(f"semi-implicit Euler: frame time [ms] ({clock}), median (min); ratio = warpsim / reference (< 1: warpsim "
          "faster);")
    print("ratio med: median over frames of (warpsim frame / the reference frame timed next to it)")
    print(f"{'grid':>7} {'particles':>10} {'springs':>9} {'Warp ref':>17} {'warpsim':>17} {'ratio med':>10} "
          f"{'ratio min':>10}  layout")
    frame_ref = {}
    for dim in args.dims:
        ratios = {}
        for _ in range(max(1, args.repeats)):
            model, t_ref, t_ws = run_explicit(dim, args, device, Cloth, WpIntegrator)
            frame_ref[dim] = np.median(t_ref)
            for mode, t in t_ws.items():
                ratios.setdefault(mode, []).append(np.median(t / t_ref))
                print(f"{dim:>5}^2 {model.particle_count:>10} {model.spring_count:>9} "
                      f"{1e3 * np.median(t_ref):>9.3f} ({1e3 * t_ref.min():>5.3f}) "
                      f"{1e3 * np.median(t):>9.3f} ({1e3 * t.min():>5.3f}) {ratios[mode][-1]:>10.3f} "
                      f"{t.min() / t_ref.min():>10.3f}  {mode}", flush=True)
        if args.repeats > 1:
            for mode, r in ratios.items():
                print(f"{dim:>5}^2 {mode}: ratio med over {len(r)} repeats: {min(r):.3f} - {max(r):.3f} "
                      f"(median {np.median(r):.3f})", flush=True)
    if args.implicit_dims:
        print()
        print(f"implicit Euler (Baraff-Witkin), 1 step per frame, CG tol {args.cg_tol:g}: median frame time [ms]")
        print(f"{'grid':>7} {'warpsim':>10} {'CG its mean':>12} {'CG its max':>11} {'ratio vs ref explicit':>22}")
        for dim in args.implicit_dims:
            t, mean_it, max_it = run_implicit(dim, args, device)
            ratio = f"{t / frame_ref[dim]:.3f}" if dim in frame_ref else "-"
            print(f"{dim:>5}^2 {1e3 * t:>10.3f} {mean_it:>12.1f} {max_it:>11d} {ratio:>22}", flush=True)


if __name__ == "__main__":
    sys.exit(run_script(main))
