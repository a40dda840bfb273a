"""The donut heap: step time of the ``donuts`` scene (soft tori piling up, ws.SoftContact), the share
of each step spent in soft-body contact, eager against CUDA graph, and how the step grows with
the number of tori.

The scene is built with ``--count`` tori of ``--segments`` x ``--sides`` surface vertices
(default 12 tori of 50 x 40 = 2,000 vertices, plus each torus's interior lattice) and stepped at
its own step (``dt`` split into the inner steps its springs' stability limit needs) for
``--settle`` integration steps so that they touch (blow-up checks on). Then, in this process on
the same heap: the full integration step (semi-implicit Euler, springs, box walls, SoftContact:
BVH refits, vertex-triangle and edge-edge search, pushes and impulses), the SoftContact stage
alone, and the step without SoftContact. Printed: ms per step and steps/s, the contact stage's
share of a step, the ratio of a step with contact to one without, the contact counts; on CUDA
the step is also captured once as a CUDA graph and replayed (eager / graph).

``--compare-count M`` builds a second heap of M tori (same settling) and prints the ratio of its
step time to the first one's (linear in the number of tori would be M / count).

    python benchmarks/bench_donuts.py --device cpu --steps 20
    python benchmarks/bench_donuts.py --device cpu --count 12 --compare-count 48 --settle 600 --steps 10
    python benchmarks/bench_donuts.py --device cpu --count 3 --segments 16 --sides 8 --settle 200  # quick
    python benchmarks/bench_donuts.py --device cuda:0 --settle 3000 --steps 500
    python benchmarks/bench_donuts.py --device cuda:0 --count 1000 --settle 3000 --steps 200
    python benchmarks/bench_donuts.py --device cuda:0 --settle 1000 --steps 50 --profile  # kernel table

``--broad-phase list`` uses SoftContact's candidate list (``--pad``, ``--search-every``), ``--broad-phase
bvh`` (the scene's default) the two-level BVH search every step; ``--settle-broad-phase bvh`` settles with
the BVH search and then switches (the list is slow while tori fall).

``--integrator fast_mass_spring --dt 0.0041666667`` steps the heap by ``ws.FastMassSpring`` at 1/240 s
(``--solver-iterations N``, default the scene's 10); ``--integrator implicit_euler`` by Newton and CG.

``--integrator vbd --dt 0.0041666667`` steps the heap by ``ws.VBD`` (vertex block descent, contact inside the
descent; ``benchmarks/vbd_heap.py``: step, contact share, frames/s, deepest vertex, edges through triangles;
``--reference-integrator fast_mass_spring`` times that integrator on the same heap in the same run, ``newton_vbd``
Newton's ``SolverVBD`` (``pip install newton``; ``--newton-from-build``: both from the tori as built);
``--vbd-lanes 1,32`` settles with the first value of ``ws.VBD``'s ``lanes`` and times the colour sweep and the step
with each on the same heap: 1 a thread a particle, 32 a warp a particle; ``--cpu-blocks`` lets the CPU run
lanes as Warp's cooperative fibers, ``wp.config.enable_cpu_blocks``, else a CPU block is one lane).

``--profile`` prints the kernel table of ``--steps`` steps (``wp.timing_begin``/``end``), host read-backs
and synchronisations per step, and the contact search's candidates per query
(``SoftContact.record_candidates``); ``--rebuild-every N`` sets the contact's BVH rebuild period.
"""

import argparse
import time

import warp as wp
from timing import activity_name, eager_and_graph, time_per_call

from warpsim.scenes import get_scene


def build(args, count, device):
    cls = get_scene("donuts")
    params = cls.resolve_params({"count": count, "segments": args.segments, "sides": args.sides,
                                 "lattice_cells": args.lattice_cells, "dt": args.dt,
                                 "broad_phase": args.settle_broad_phase or args.broad_phase,
                                 "integrator": args.integrator,
                                 **{key: value for key, value in (
                                     ("contact_stiffness", args.contact_stiffness),
                                     ("contact_damping", args.contact_damping),
                                     ("newton_iterations", args.newton_iterations),
                                     ("solver_iterations", getattr(args, "solver_iterations", None)),
                                     ("contact_reach", args.contact_reach),
                                     ("contact_iterations", args.contact_iterations)) if value is not None},
                                 **dict(item.split("=", 1) for item in getattr(args, "set", []))})
    scene = cls(params, device=device)
    if args.cg_tol:
        scene.sim.integrator.cg_tol = args.cg_tol  # before the first step allocates the solver
    if args.linear_solver:
        scene.sim.integrator.linear_solver = args.linear_solver
    if scene.contact is not None:
        if args.search_every:
            scene.contact.search_every = args.search_every
        if args.pad:
            scene.contact.pad = args.pad
    return scene


def settle(args, count, device):
    """A heap of ``count`` tori after ``--settle`` integration steps; returns (scene, step h [s])."""
    t0 = time.perf_counter()
    scene = build(args, count, device)
    sim, contact = scene.sim, scene.contact
    h = scene.params["dt"] / scene.inner_steps
    model = sim.model
    print(f"device {device}; {count} tori x {args.segments * args.sides} surface vertices; {model.particle_count} "
          f"particles, {model.spring_count} springs, {contact.triangle_count} contact triangles, {contact.edge_count} "
          f"contact edges; step {h:.3g} s ({scene.inner_steps} per scene step of {scene.params['dt']:.3g} s, from "
          f"the springs' stability limit, {round(1.0 / 60.0 / h)} per frame of 1/60 s); contact search "
          f"{contact.broad_phase!r}" + (f" (pad {contact.pad * 1e3:.2g} mm, refit and search every "
                                        f"{contact.search_every} steps, {contact.capacity} candidates a query)"
                                        if contact.broad_phase == "list" else "") +
          f"; built in {time.perf_counter() - t0:.1f} s")
    t0 = time.perf_counter()
    for _ in range(args.settle):
        sim.step(h)
    wp.synchronize_device(device)
    sim.check_every = 0  # blow-ups were checked every settling step; no host read-back while timing
    if contact is not None and contact.broad_phase != args.broad_phase:
        contact.set_broad_phase(args.broad_phase)
        sim.step(h)
        wp.synchronize_device(device)
        print(f"search switched to {args.broad_phase!r} after settling")
    print(f"settled {args.settle} steps ({args.settle * h:.3f} s simulated) in {time.perf_counter() - t0:.1f} s; "
          f"{contact.contact_count} vertex and {contact.edge_contact_count} edge contacts, kinetic energy "
          f"{scene.kinetic_energy():.3g} J")
    return scene, h


class HostSyncCounter:
    """Counts host read-backs (``wp.array.numpy``) and explicit synchronisations while active."""

    def __enter__(self):
        self.readbacks = self.syncs = 0
        self._numpy, self._sync = wp.array.numpy, wp.synchronize_device
        counter = self

        def numpy(arr, *a, **k):
            counter.readbacks += 1
            return counter._numpy(arr, *a, **k)

        def sync(*a, **k):
            counter.syncs += 1
            return counter._sync(*a, **k)

        wp.array.numpy, wp.synchronize_device = numpy, sync
        return self

    def __exit__(self, *exc):
        wp.array.numpy, wp.synchronize_device = self._numpy, self._sync


def profile(scene, h, steps, device, top=14):
    """Kernel table of ``steps`` integration steps (``wp.timing_begin``/``end``, all CUDA activity),
    host read-backs and synchronisations per step, wall time minus GPU activity, and the contact
    search's candidates per query (``SoftContact.record_candidates``, one extra step)."""
    sim, contact = scene.sim, scene.contact
    sim.step(h)
    wp.synchronize_device(device)
    results = []
    if device.is_cuda:
        wp.timing_begin(cuda_filter=wp.TIMING_ALL)
    t0 = time.perf_counter()
    with HostSyncCounter() as hosts:
        for _ in range(steps):
            sim.step(h)
    if device.is_cuda:
        results = wp.timing_end()
    wp.synchronize_device(device)
    wall = (time.perf_counter() - t0) / steps
    totals, calls = {}, {}
    for r in results:
        name = activity_name(r)  # the kernel's Python name, without the module hash
        totals[name] = totals.get(name, 0.0) + r.elapsed / steps
        calls[name] = calls.get(name, 0) + 1
    gpu = sum(totals.values())
    print(f"profile, {steps} steps: wall {wall * 1e3:.3f} ms/step, GPU activity {gpu:.3f} ms/step, wall minus GPU "
          f"{wall * 1e3 - gpu:.3f} ms/step; host read-backs {hosts.readbacks / steps:.2f}/step, synchronisations "
          f"{hosts.syncs / steps:.2f}/step")
    if totals:
        print(f"  {'activity':44s} {'calls/step':>10s} {'ms/step':>9s} {'share':>7s}")
        for name, ms in sorted(totals.items(), key=lambda kv: -kv[1])[:top]:
            print(f"  {name[:44]:44s} {calls[name] / steps:10.2f} {ms:9.4f} {ms / gpu:7.1%}")
    if contact is not None and contact.broad_phase == "list":
        before = contact.list_stats()["searches"]
        for _ in range(steps):
            sim.step(h)
        ls = contact.list_stats()
        print(f"  candidate list: {(ls['searches'] - before) / steps:.3f} searches a step over {steps} steps (refit "
              f"every {contact.search_every}), overflowed queries so far {ls['overflow']}")
        for kind in ("vertex", "edge"):
            if kind in ls:
                print(f"  {kind} queries: candidates kept at the last search {ls[kind]['per_query']:.2f} per query "
                      f"(max {ls[kind]['max']})")
    elif contact is not None:
        contact.record_candidates(True)
        sim.step(h)
        for kind, st in contact.candidate_stats().items():
            print(f"  {kind} queries {st['queries']}: candidates visited {st['per_query']:.2f} per query (max "
                  f"{st['max_per_query']}), own body {st['own_body'] / max(st['visited'], 1):.1%} of them, contacts "
                  f"kept {st['kept']}, visited per contact kept {st['visited_per_kept']:.1f}")
        contact.record_candidates(False)


def add_heap_arguments(parser) -> None:
    """The heap's device, torus count and torus resolution (also ``check_heap.py``'s)."""
    parser.add_argument("--device", default=None, help="Warp device (cpu, cuda:0); default: Warp's preferred")
    parser.add_argument("--count", type=int, default=12, help="number of tori")
    parser.add_argument("--segments", type=int, default=50, help="torus segments around its axis")
    parser.add_argument("--sides", type=int, default=40, help="torus segments around its tube")
    parser.add_argument("--lattice-cells", type=int, default=10, help="interior lattice cells across a torus")


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_heap_arguments(parser)
    parser.add_argument("--compare-count", type=int, default=0, help="also time a heap of this many tori")
    parser.add_argument("--dt", type=float, default=1.0 / 1200.0, help="the scene's step [s] (split into inner "
                        "steps from the springs' stability limit)")
    parser.add_argument("--integrator", default="semi_implicit_euler", help="the scene's integrator "
                        "(implicit_euler, fast_mass_spring: no spring limit on the step)")
    parser.add_argument("--solver-iterations", type=int, default=None, help="fast_mass_spring: local-global "
                        "iterations a step; vbd: colour sweeps a step (default: the scene's)")
    parser.add_argument("--reference-integrator", default=None, help="vbd: also build, settle and time the heap with "
                        "this integrator (e.g. fast_mass_spring) in the same run; newton_vbd: Newton's SolverVBD built "
                        "from VBD's heap as it is and stepped --steps steps from the same state "
                        "(tests/newton_reference.py; pip install newton)")
    parser.add_argument("--newton-from-build", action="store_true", help="newton_vbd: both integrators from the tori "
                        "as built, at rest in the air (they fall and land over --steps steps), instead of VBD's heap")
    parser.add_argument("--reference-dt", type=float, default=None, help="vbd: the reference integrator's scene step "
                        "[s] (default --dt): each integrator at its own step, compared per simulated second")
    parser.add_argument("--vbd-lanes", default=None, metavar="B[,B...]", help="vbd: threads a particle in the "
                        "colour solve (ws.VBD lanes; 1: a thread a particle): settle with the first, then time the "
                        "sweep and the step with each on the same heap (default: the integrator's, 32 on CUDA, 1 on "
                        "the CPU)")
    parser.add_argument("--vbd-max-registers", default=None, metavar="R[,R...]", help="vbd: time the colour sweep "
                        "and the step with each ws.VBD max_registers (none: the compiler's choice; 64) on the same "
                        "heap, after one step from one saved state with each (the same bits expected)")
    parser.add_argument("--vbd-split", default=None, metavar="S[,S...]", help="vbd: time the colour sweep and the "
                        "step with each ws.VBD split (true: the particles no contact can reach solved apart, a thread "
                        "each; false: every particle by the colour solve; auto) on the same heap, after one step from "
                        "one saved state with each")
    parser.add_argument("--query-block-dims", default=None, metavar="B[,B...]", help="vbd: time the contact "
                        "search with each CUDA block size of its pair queries")
    parser.add_argument("--no-oracles", action="store_true", help="vbd: skip the NumPy checks of the final heap "
                        "(deepest vertex, edges through; minutes at 100 tori)")
    parser.add_argument("--cpu-blocks", action="store_true", help="wp.config.enable_cpu_blocks: CPU blocks of more "
                        "than one lane run as Warp's cooperative fibers (else as one lane)")
    parser.add_argument("--contact-stiffness", type=float, default=None, help="implicit_euler: contact penalty "
                        "stiffness inside the solve [N/m] (the scene's contact_stiffness)")
    parser.add_argument("--contact-damping", type=float, default=None, help="implicit_euler: contact damping inside "
                        "the solve [N s/m]")
    parser.add_argument("--newton-iterations", type=int, default=None, help="implicit_euler: Newton iterations a "
                        "step (default: the scene's)")
    parser.add_argument("--contact-iterations", type=int, default=None, help="implicit_euler: contact passes after a "
                        "step (default: the scene's)")
    parser.add_argument("--cg-tol", type=float, default=0.0, help="implicit_euler: CG tolerance relative to |rhs| "
                        "(0: the integrator's default)")
    parser.add_argument("--linear-solver", default=None, choices=["warp_cg", "block_cg"],
                        help="implicit_euler: the CG (default: the integrator's auto choice; block_cg: no host "
                        "read-back with --newton-iterations 1, so the step records in a CUDA graph)")
    parser.add_argument("--contact-reach", type=float, default=None, help="implicit_euler: speculative contact "
                        "distance beyond the thickness [m] (the scene's contact_reach)")
    parser.add_argument("--settle", type=int, default=1000, help="integration steps before timing (tori touching)")
    parser.add_argument("--steps", type=int, default=50, help="timed steps")
    parser.add_argument("--rebuild-every", type=int, default=None, help="SoftContact BVH rebuild period in steps "
                        "(refits between; 0: refit only; default: the contact's own)")
    parser.add_argument("--broad-phase", default="bvh", choices=["list", "bvh", "all_pairs"],
                        help="SoftContact search while timed (list: candidate list; bvh: two-level BVH search every "
                        "step)")
    parser.add_argument("--settle-broad-phase", default=None, choices=["list", "bvh", "all_pairs"],
                        help="SoftContact search while settling (default: --broad-phase); the timed steps switch "
                        "to --broad-phase (SoftContact.set_broad_phase)")
    parser.add_argument("--search-every", type=int, default=0, help="list: steps between refit-and-search "
                        "(0: the contact's default)")
    parser.add_argument("--pad", type=float, default=0.0, help="list: motion pad [m] (0: the contact's default)")
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                        help="another donuts parameter (repeatable), e.g. solver_chebyshev=true")
    parser.add_argument("--profile", action="store_true", help="print the kernel table (wp.timing_begin/end), host "
                        "read-backs per step and the contact search's candidates per query first")
    args = parser.parse_args()
    device = wp.get_device(args.device)
    wp.config.quiet = True
    if args.cpu_blocks:
        wp.config.enable_cpu_blocks = True
    if args.integrator == "vbd":
        from vbd_heap import run_vbd

        return run_vbd(args, device, build)

    scene, h = settle(args, args.count, device)
    sim, contact = scene.sim, scene.contact
    if args.rebuild_every is not None:
        contact.rebuild_period = args.rebuild_every
        print(f"BVH rebuild every {args.rebuild_every} steps from here (0: refit only)")
    if args.profile:
        profile(scene, h, args.steps, device)
    model = sim.model
    full = time_per_call(lambda: sim.step(h), args.steps, device)
    st = sim.state
    stage = time_per_call(lambda: contact.apply(model, st, sim._q_prev, h), args.steps, device)
    contacts = (contact.contact_count, contact.edge_contact_count)
    colliders = sim.colliders
    sim.colliders = [c for c in colliders if c is not contact]
    without = time_per_call(lambda: sim.step(h), args.steps, device)
    sim.colliders = colliders
    print(f"step with contact     {full * 1e3:9.3f} ms   {1.0 / full:8.1f} steps/s "
          f"({1.0 / (full * scene.inner_steps):.1f} scene steps/s)")
    print(f"SoftContact stage     {stage * 1e3:9.3f} ms   share of a step: {stage / full:.1%}  "
          f"({contacts[0]} vertex, {contacts[1]} edge contacts)")
    print(f"step without contact  {without * 1e3:9.3f} ms   with / without: {full / without:.2f}x")
    per_frame = round(1.0 / 60.0 / h)
    print(f"frames of 1/60 s per wall second: {1.0 / (full * per_frame):.2f} ({per_frame} steps a frame)")
    if contact is not None and contact.broad_phase == "list":
        print(f"candidate overflow (queries, so far): {contact.candidate_overflow}")
    if device.is_cuda:
        try:
            # one graph of a whole rebuild period (a rebuild and its refits), against as many eager steps
            period = contact.schedule_period if contact is not None else 1

            calls = max(1, args.steps // period)
            eager, graph = eager_and_graph(lambda: sim.step(h), period, calls, device)
            print(f"step as a CUDA graph  {graph * 1e3:9.3f} ms   {1.0 / graph:8.1f} steps/s   eager / graph: "
                  f"{eager / graph:.2f}x (a graph of {period} steps against {period} eager steps, {eager * 1e3:.3f} "
                  f"ms a step; fastest of 3 alternating rounds of {calls} x {period} steps)")
        except Exception as exc:  # noqa: BLE001 (report and go on: the eager figures stand)
            print(f"CUDA graph capture failed: {exc}")
    if args.compare_count:
        other, h2 = settle(args, args.compare_count, device)
        other.sim.check_every = 0
        # alternate the two heaps and keep each one's fastest round: the machine's load changes
        rounds = {args.count: [], args.compare_count: []}
        for _ in range(3):
            rounds[args.count].append(time_per_call(lambda: sim.step(h), args.steps, device))
            rounds[args.compare_count].append(time_per_call(lambda: other.sim.step(h2), args.steps, device))
        a, b = min(rounds[args.count]), min(rounds[args.compare_count])
        print(f"step with {args.count} tori {a * 1e3:9.3f} ms, with {args.compare_count} tori {b * 1e3:9.3f} ms (fastest of "
              f"3 alternating rounds): {args.compare_count} / {args.count} tori step time {b / a:.2f}x (linear: "
              f"{args.compare_count / args.count:.2f}x)")

if __name__ == "__main__":
    main()
