"""``bench_donuts.py --integrator vbd``: the donut heap stepped by ``ws.VBD`` (contact inside the descent).

After ``--settle`` steps of ``--dt`` (blow-up checks on), on the same heap: the full step (eager, and on
CUDA as a graph of one BVH-rebuild period), the contact search alone (``VBDContact.search``, times the
searches the timed steps ran, those within a step skipped at rest not counted: its share of a step), one
colour sweep, frames of 1/60 s per wall second, the pairs listed, the queries past the lists' capacity at the
last search and the most pairs one query met (per search: figures that cannot wrap), then the two properties
the heap tests assert on the final state: the deepest vertex of a torus inside another [mm] and the surface
edges passing through another torus's triangles (the NumPy oracles of ``tests/test_soft_contact_scale.py``).
``--reference-integrator fast_mass_spring`` builds and settles the same heap with that integrator in the same process
(at ``--reference-dt``, default ``--dt``: each at its own step, settled as long in simulated time) and prints the ratio
of the time per simulated second; ``--reference-integrator newton_vbd`` builds Newton's ``SolverVBD`` on the same heap
(``tests/newton_reference.py``), steps both ``--steps`` steps from VBD's state (``--newton-from-build``: from the
tori as built) and prints the time ratio and both heaps' state (lowest vertex, mean height, kinetic energy, the
oracles). ``--vbd-lanes 1,32`` settles with ``ws.VBD(lanes=1)`` and then times the sweep and
the step (on CUDA also as a graph) with each value on the same heap (a thread a particle against a warp a particle),
after one step from one saved state with each value compared with the first's positions. ``--vbd-max-registers none,64``
does the same with ``ws.VBD``'s ``max_registers`` (the colour solve's registers a thread on CUDA: the same sums, so
the one step from the saved state must give the same bits), ``--vbd-split true,false`` with its ``split`` (the
particles no contact can reach solved apart, a thread each).
``--query-block-dims 256,128,64`` times the contact search with each CUDA block size of its pair queries.

    python benchmarks/bench_donuts.py --integrator vbd --device cpu --count 12 --segments 24 --sides 12 \\
        --lattice-cells 8 --dt 0.0041666667 --settle 240 --steps 20
    python benchmarks/bench_donuts.py --integrator vbd --device cuda:0 --dt 0.0041666667 --settle 2400 --steps 200 \\
        --reference-integrator fast_mass_spring --set solver_chebyshev=true --solver-iterations 12
    python benchmarks/bench_donuts.py --integrator vbd --device cuda:0 --dt 0.0041666667 --settle 600 --steps 100 \\
        --vbd-lanes 1,32,64
"""

import math
import os
import sys
import time

import numpy as np
import warp as wp
from timing import activity_name, eager_and_graph, time_per_call

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests"))
from test_soft_contact_scale import deepest_vertex, edges_through_other_bodies  # noqa: E402 (the tests' oracles)


def searches_per_step(integrator) -> int:
    """Contact searches a VBD step makes at most (one opens it, one every ``detect_every`` iterations after; those
    the device finds unneeded are skipped, ``ws.VBD``'s ``renew_fraction``)."""
    every = integrator.detect_every
    return 1 + ((integrator.iterations - 1) // every if every else 0)


def lanes_of(args) -> list:
    """``--vbd-lanes`` as a list of ints (threads a particle in VBD's colour solve)."""
    return [int(b) for b in args.vbd_lanes.split(",")]


def registers_of(args) -> list:
    """``--vbd-max-registers`` as a list of ``ws.VBD`` ``max_registers`` values (``none``: the compiler's choice,
    ``auto``: by the colours' size)."""
    words = [r.strip().lower() for r in args.vbd_max_registers.split(",")]
    return [None if r == "none" else r if r == "auto" else int(r) for r in words]


def splits_of(args) -> list:
    """``--vbd-split`` as a list of ``ws.VBD`` ``split`` values (true, false, auto)."""
    words = [w.strip().lower() for w in args.vbd_split.split(",")]
    return [w if w == "auto" else w == "true" for w in words]


def compare_setting(args, sim, h, device, attribute: str, values: list) -> None:
    """One colour sweep and one step (on CUDA also as a graph of one BVH rebuild period) with each of ``values`` of
    the integrator's ``attribute`` (``lanes``, ``max_registers``, ``split``) on the heap as it is (a step first records the
    sweep's launches); first, from one saved state (positions, velocities, the previous velocities of the adaptive
    guess), one step with each value, its positions against the first value's (other sums' order: rounding; the
    same sums in the same order: the same bits; and each value's own bits when it runs twice)."""
    integrator = sim.integrator
    # the setting as the heap was built, set back at the end: what follows (the reference's ratio) times that
    own = getattr(integrator, attribute)
    q, qd = sim.state.positions, sim.state.velocities
    saved = [wp.clone(a) for a in (q, qd, integrator.qd_prev)]
    first = None
    for value in values + values[:1]:
        setattr(integrator, attribute, value)
        for a, b in zip((q, qd, integrator.qd_prev), saved):
            wp.copy(a, b)
        sim.step(h)
        x = q.numpy()
        label = f"{attribute} {value}"
        if first is None:
            first = (label, x)
        else:
            d = np.linalg.norm(x - first[1], axis=1)
            same = "the same bits" if (x == first[1]).all() else (
                f"|dx| largest {d.max():.3g} m, 99.9th percentile {np.quantile(d, 0.999):.3g} m, median "
                f"{np.median(d):.3g} m, {int((d > 1.0e-5).sum())} particles past 0.01 mm (a search within the step "
                "run or skipped, a friction or bound clip, can turn on rounding in a moving heap)")
            print(f"{label}: one step from the saved state against {first[0]}'s: {same}")
    for a, b in zip((q, qd, integrator.qd_prev), saved):
        wp.copy(a, b)
    for value in values:
        setattr(integrator, attribute, value)
        sim.step(h)  # records the colour solves with this value
        sweep = time_per_call(lambda: [launch.launch() for launch in integrator._sweep], args.steps, device)
        full = time_per_call(lambda: sim.step(h), args.steps, device)
        line = f"{attribute} {value!s:>4}: one colour sweep {sweep * 1e3:9.3f} ms, VBD step {full * 1e3:9.3f} ms"
        if device.is_cuda:
            every = integrator.contact.rebuild_every
            period = every // math.gcd(every, searches_per_step(integrator))
            _, graph = eager_and_graph(lambda: sim.step(h), period, max(1, args.steps // period), device)
            line += f", step as a CUDA graph {graph * 1e3:9.3f} ms"
        print(line)
    setattr(integrator, attribute, own)


def compare_query_blocks(args, contact, q, device) -> None:
    """One contact search with each CUDA block size of ``--query-block-dims`` for the pair queries (a launch
    setting: the lists are the same bits, checked here)."""
    reference = None
    for block in [int(b) for b in args.query_block_dims.split(",")]:
        contact.query_block_dim = block
        contact._recorded_key = None  # (records the queries again with this block size)
        search = time_per_call(lambda: contact.search(q), args.steps, device)
        lists = [a.numpy().tobytes() for a in (contact._vt, contact._tv, contact._ee, contact._vt_min)]
        same = "" if reference is None else f", lists {'the same' if lists == reference else 'DIFFER'}"
        reference = reference or lists
        print(f"query block {block:4d}: contact search {search * 1e3:9.3f} ms{same}")


def settle(build, args, device, integrator):
    """Build the heap with ``integrator`` and take ``--settle`` steps; returns (scene, h, build seconds)."""
    args.integrator = integrator
    t0 = time.perf_counter()
    scene = build(args, args.count, device)
    if integrator == "vbd" and getattr(args, "vbd_lanes", None):
        scene.sim.integrator.lanes = lanes_of(args)[0]
    wp.synchronize_device(device)
    built = time.perf_counter() - t0
    h = scene.params["dt"] / scene.inner_steps
    t0 = time.perf_counter()
    for _ in range(args.settle):
        scene.sim.step(h)
    wp.synchronize_device(device)
    scene.sim.check_every = 0  # no host read-back while timing
    print(f"{integrator}: built in {built:.2f} s; settled {args.settle} steps of {h:.4g} s in "
          f"{time.perf_counter() - t0:.1f} s; kinetic energy {scene.kinetic_energy():.3g} J")
    return scene, h, built


def kernel_table(step, steps, device, top=16) -> None:
    """The GPU's activity over ``steps`` calls of ``step`` (``wp.timing_begin``/``end``, kernels, copies and
    BVH work): per name, calls and milliseconds a step, largest first."""
    step()
    wp.synchronize_device(device)
    wp.timing_begin(cuda_filter=wp.TIMING_ALL)
    for _ in range(steps):
        step()
    results = wp.timing_end()
    totals, calls = {}, {}
    for r in results:
        name = activity_name(r)  # the kernel's Python name, without the module hash
        totals[name] = totals.get(name, 0.0) + r.elapsed / steps
        calls[name] = calls.get(name, 0) + 1
    gpu = sum(totals.values()) or 1.0
    print(f"kernel table, {steps} steps: GPU activity {gpu:.3f} ms a step")
    for name, ms in sorted(totals.items(), key=lambda kv: -kv[1])[:top]:
        print(f"  {name[:52]:52s} {calls[name] / steps:8.2f} calls {ms:9.4f} ms {ms / gpu:7.1%}")


def heap_state(scene, renew_fraction) -> str:
    """What keeps the searches running on a heap (one read-back): the fastest particles [m/s] and the tori that
    hold those past 0.1 m/s, the bounds of the surface vertices [mm] and the smallest vertex-triangle distance met
    at the last search [mm]; a search within a step runs when any particle has moved ``renew_fraction`` of its
    bound."""
    sim, contact = scene.sim, scene.vbd_contact
    speed = np.linalg.norm(sim.state.velocities.numpy(), axis=1)
    fast = np.flatnonzero(speed > 0.1)
    tori = len(np.unique(fast // contact.body_size)) if contact.body_size else "-"
    surface = contact.surface_particles
    bound = contact.bound.numpy()[surface] * 1e3
    cap = contact.cap.numpy()[surface] * 1e3
    gap = contact.nearest_triangles
    gap = gap[gap < 1.0e29] * 1e3  # vertices with a listed pair (1e30: none)
    gaps = f"{gap.min():.3g} / {np.percentile(gap, 1):.3g}" if len(gap) else "- / -"
    return (f"heap state: fastest particle {speed.max():.3g} m/s, 99.9th percentile {np.percentile(speed, 99.9):.3g}, "
            f"{len(fast)} particles past 0.1 m/s in {tori} tori; surface bounds min / 1st percentile / median "
            f"{bound.min():.3g} / {np.percentile(bound, 1):.3g} / {np.median(bound):.3g} mm (a search runs past "
            f"{renew_fraction} of one); caps median / 99th percentile / max {np.median(cap):.3g} / "
            f"{np.percentile(cap, 99):.3g} / {cap.max():.3g} mm; vertex-triangle distance min / 1st percentile "
            f"{gaps} mm (thickness {contact.thickness * 1e3:.3g})")


def heap_figures(x: np.ndarray, v: np.ndarray, mass: np.ndarray, bodies, oracles: bool) -> str:
    """A heap's state in one line: lowest vertex [mm], mean height [m], kinetic energy [J], fastest particle [m/s],
    and with ``oracles`` the deepest vertex inside another torus [mm] and the edges through another torus's triangles
    (the tests' NumPy oracles)."""
    energy = 0.5 * float((mass * (v.astype(np.float64) ** 2).sum(axis=1)).sum())
    line = (f"lowest vertex {x[:, 1].min() * 1e3:.3f} mm, mean height {x[:, 1].mean():.4f} m, kinetic energy "
            f"{energy:.4g} J, fastest particle {np.linalg.norm(v, axis=1).max():.3g} m/s")
    if oracles:
        crossings = sum(n for _, _, n in edges_through_other_bodies(x, bodies))
        line += f", deepest vertex {deepest_vertex(x, bodies) * 1e3:.3f} mm, edges through {crossings}"
    return line


def compare_newton(args, scene, h, device) -> None:
    """Newton's ``SolverVBD`` on the same heap (``tests/newton_reference.py``): built from VBD's state as it is (with
    ``--newton-from-build`` the tori as built instead, at rest in the air), then ``--steps`` steps of each from that one
    state (VBD's saved and set back), each timed over its steps, and the two heaps' states after them."""
    from newton_reference import NewtonHeap, newton_version

    version = newton_version()
    if version is None:
        print("newton_vbd: Newton is not installed (pip install newton); not compared")
        return
    sim = scene.sim
    q, qd, previous = sim.state.positions, sim.state.velocities, sim.integrator.qd_prev
    saved = [wp.clone(a) for a in (q, qd, previous)]
    start = "VBD's state"
    if getattr(args, "newton_from_build", False):  # the tori as built, at rest in the air: both fall and land
        wp.copy(saved[0], sim.model.particle_q)
        saved[1].zero_()
        saved[2].zero_()
        start = "the tori as built"
    t0 = time.perf_counter()
    other = NewtonHeap(scene, device)
    other.step(h)  # compiles Newton's kernels and builds its solver: not timed
    other.load(saved[0], saved[1])
    wp.synchronize_device(device)
    built = time.perf_counter() - t0
    steps = max(1, args.steps)
    t0 = time.perf_counter()
    for _ in range(steps):
        other.step(h)
    wp.synchronize_device(device)
    theirs = (time.perf_counter() - t0) / steps
    for a, b in zip((q, qd, previous), saved):
        wp.copy(a, b)
    if getattr(args, "newton_from_build", False):  # a state set from outside: the adaptive guess forgets the
        sim.notify_changed("state")  # steps before (VBD.forget_history), the energy balance starts again
        sim.integrator.contact.searches = 0  # and the next search runs, with a BVH rebuild
    t0 = time.perf_counter()
    for _ in range(steps):
        sim.step(h)
    wp.synchronize_device(device)
    ours = (time.perf_counter() - t0) / steps
    print(f"newton_vbd: Newton {version} SolverVBD on the same heap ({other.iterations} iterations, a self-contact "
          f"detection every {other.detect_every}; built and first step {built:.1f} s); {steps} steps of {h:.4g} s from "
          f"{start}: Newton {theirs * 1e3:.3f} ms a step, VBD {ours * 1e3:.3f} ms: Newton / VBD time "
          f"{theirs / ours:.2f}x")
    mass = sim.model.particle_mass.numpy()
    oracles = not getattr(args, "no_oracles", False)
    print(f"  after them, VBD:    {heap_figures(q.numpy(), qd.numpy(), mass, scene.bodies, oracles)}")
    print(f"  after them, Newton: {heap_figures(other.positions(), other.velocities(), mass, scene.bodies, oracles)}")


def run_vbd(args, device, build) -> None:
    scene, h, _ = settle(build, args, device, "vbd")
    sim, integrator, contact = scene.sim, scene.sim.integrator, scene.vbd_contact
    model = sim.model
    print(f"device {device}; {args.count} tori x {args.segments * args.sides} surface vertices; {model.particle_count} "
          f"particles, {model.spring_count} springs, {integrator.colour_count} colours, {contact.triangle_count} "
          f"triangles, {contact.edge_count} edges; {integrator.iterations} sweeps and {searches_per_step(integrator)} "
          f"contact searches a step (a pair's radius r_c + its caps: {contact.thickness * 1e3:.3g} + caps of "
          f"{contact.min_displacement * 1e3:.3g}-{contact.max_displacement * 1e3:.3g} mm a side)")
    before = contact.searches_run
    full = time_per_call(lambda: sim.step(h), args.steps, device)
    ran = (contact.searches_run - before) / (args.steps + 1)  # searches run a timed step (warm-up call included)
    q = sim.state.positions
    search = time_per_call(lambda: contact.search(q), args.steps, device)
    sweep = time_per_call(lambda: [launch.launch() for launch in integrator._sweep], args.steps, device)
    per_frame = round(1.0 / 60.0 / h)
    share = search * ran / full
    vt, ee = contact.pair_counts()
    print(f"VBD step              {full * 1e3:9.3f} ms   {1.0 / full:8.1f} steps/s")
    print(f"contact search        {search * 1e3:9.3f} ms x {ran:.2f} a step run (of {searches_per_step(integrator)}: "
          f"those within the step skipped where every particle is well inside its bound): share of a step "
          f"{share:.1%} ({vt} vertex-triangle, {ee} edge-edge pairs listed)")
    over, most = contact.overflow, contact.most_pairs
    print(f"queries past the lists' capacity of {contact.capacity} at the last search (vertex, triangle, edge): "
          f"{over}; the most pairs one query met: {most}")
    kept, whole = contact.near_stats()
    print(f"one colour sweep      {sweep * 1e3:9.3f} ms x {integrator.iterations} a step (gathering over {kept} list "
          f"entries that can push, {whole} vertices past near_capacity {contact.near_capacity} over their whole lists)")
    print(f"frames of 1/60 s per wall second: {1.0 / (full * per_frame):.2f} ({per_frame} steps a frame)")
    if integrator.split_on(device):
        listed = int(integrator._listed_count.numpy().sum())
        print(f"split sweeps: particles listed as able to touch a contact (the colour solve, checked) {listed} of "
              f"{model.particle_count} ({listed / model.particle_count:.1%}; the rest solve_free, a thread each)")
    else:
        print("sweeps not split: every particle by the colour solve (ws.VBD split)")
    print(heap_state(scene, integrator.renew_fraction))
    if device.is_cuda:
        period = contact.rebuild_every // math.gcd(contact.rebuild_every, searches_per_step(integrator))
        eager, graph = eager_and_graph(lambda: sim.step(h), period, max(1, args.steps // period), device)
        print(f"step as a CUDA graph  {graph * 1e3:9.3f} ms   eager / graph {eager / graph:.2f}x (a graph of {period} "
              f"steps, one BVH rebuild period); frames of 1/60 s per wall second {1.0 / (graph * per_frame):.2f}")
    if getattr(args, "vbd_lanes", None):
        compare_setting(args, sim, h, device, "lanes", lanes_of(args))
    if getattr(args, "vbd_max_registers", None):
        compare_setting(args, sim, h, device, "max_registers", registers_of(args))
    if getattr(args, "vbd_split", None):
        compare_setting(args, sim, h, device, "split", splits_of(args))
    if getattr(args, "query_block_dims", None):
        compare_query_blocks(args, contact, q, device)
    if args.profile and device.is_cuda:
        kernel_table(lambda: sim.step(h), min(args.steps, 20), device)
    x = sim.state.positions.numpy()
    t0 = time.perf_counter()
    if getattr(args, "no_oracles", False):
        print("deepest vertex and edges through: not checked (--no-oracles)")
    else:
        crossings = sum(n for _, _, n in edges_through_other_bodies(x, scene.bodies))
        print(f"deepest vertex inside another torus {deepest_vertex(x, scene.bodies) * 1e3:.3f} mm (thickness "
              f"{scene.params['thickness'] * 1e3:.3g} mm); edges through another torus's triangles: {crossings} "
              f"(oracles, {time.perf_counter() - t0:.1f} s)")
    if args.reference_integrator == "newton_vbd":
        compare_newton(args, scene, h, device)
    elif args.reference_integrator:
        own = (args.dt, args.settle)  # the reference settles as long in simulated time, at its own step
        args.dt = getattr(args, "reference_dt", None) or args.dt
        args.settle = round(own[1] * own[0] / args.dt)
        other, h2, _ = settle(build, args, device, args.reference_integrator)
        args.dt, args.settle = own
        reference = time_per_call(lambda: other.sim.step(h2), args.steps, device)
        again = time_per_call(lambda: sim.step(h), args.steps, device)
        print(f"{args.reference_integrator} step {reference * 1e3:9.3f} ms at {h2:.4g} s; VBD step {again * 1e3:.3f} ms "
              f"at {h:.4g} s: {args.reference_integrator} / vbd time per simulated second "
              f"{(reference / h2) / (again / h):.2f}x")
        y = other.sim.state.positions.numpy()
        print(f"{args.reference_integrator}: deepest vertex {deepest_vertex(y, other.bodies) * 1e3:.3f} mm, edges "
              f"through: {sum(n for _, _, n in edges_through_other_bodies(y, other.bodies))}")
