"""Vertex block descent (``ws.VBD``, ``ws.VBDContact``; kernels ``warpsim.kernels.vbd`` and ``vbd_contact``):
one Newton step on one spring is backward Euler's analytic step; converged VBD is ``ImplicitEuler``'s
step; the greedy colouring never gives two ends of a spring one colour; runs are bit-identical and a
step allocates nothing; no edge passes through a triangle (brute force over all non-adjacent pairs,
every frame) in a two-torus drop with self contact and a small heap; the donuts scene's 12-torus heap
holds over its 600 frames under three roundings; the stability report and the energy balance know VBD;
bad input is refused with the item, the value and a fix."""
import io
import re
import types

import numpy as np
import pytest
import warp as wp
from test_soft_contact_scale import deepest_vertex, edges_through_other_bodies, segments_cross_triangles

import warpsim as ws
from warpsim.bodies import meshtools
from warpsim.core.colouring import colour_groups, greedy_colouring, tile_colouring
from warpsim.core.energy import MARGIN
from warpsim.kernels import vbd as vbd_kernels
from warpsim.kernels.vbd import may_touch
from warpsim.scenes import get_scene

DEVICE = "cpu"
SMALL = {"segments": 10, "sides": 6, "lattice_cells": 5}


def crossings(x, faces):
    """Edges (of all surfaces) passing through triangles they share no vertex with, brute force over
    every such pair (NumPy oracle ``segments_cross_triangles``; small meshes)."""
    x = x.astype(np.float64)
    edges, _, _ = meshtools.edge_topology(faces)
    count = 0
    for t, tri in enumerate(faces):
        keep = ~np.isin(edges, tri).any(1)
        hit = segments_cross_triangles(x[edges[keep, 0]], x[edges[keep, 1]], x[tri][None])
        count += int(hit.sum())
    return count


def spring_pair(k=40.0, c=0.0, stretch=0.03, speed=0.5):
    """Particle 0 pinned at the origin, particle 1 (0.2 kg) at rest length 0.1 m + ``stretch`` on +x moving
    at ``speed`` [m/s] along x, one spring (k [N/m], damping c [N s/m])."""
    b = ws.ModelBuilder()
    b.add_particle((0.0, 0.0, 0.0), mass=0.0)
    b.add_particle((0.1 + stretch, 0.0, 0.0), vel=(speed, 0.0, 0.0), mass=0.2)
    b.add_spring(0, 1, k, c, rest_length=0.1)
    return b.finalize(DEVICE)


@pytest.mark.parametrize("damping", [0.0, 1.5])
def test_one_newton_step_on_one_spring_is_the_backward_euler_step(damping):
    """Along the spring its energy is quadratic, so VBD's one Newton step from y = x0 + h v0 lands on
    backward Euler's solution m (x - y) / h^2 = -k (x - L) - c (x - x0) / h."""
    k, m, L, h = 40.0, 0.2, 0.1, 1.0 / 30.0
    model = spring_pair(k, damping)
    sim = ws.Simulator(model, integrator=ws.VBD(iterations=1), forces=[])
    sim.step(h)
    x0, v0 = 0.13, 0.5
    y = x0 + h * v0
    x = (m / h**2 * y + k * L + damping / h * x0) / (m / h**2 + k + damping / h)
    got = sim.state.positions.numpy()[1]
    assert got[0] == pytest.approx(x, rel=1e-6) and np.abs(got[1:]).max() == 0.0
    assert sim.state.velocities.numpy()[1][0] == pytest.approx((x - x0) / h, rel=1e-4)
    assert (sim.state.positions.numpy()[0] == 0.0).all()  # pinned


def test_the_sweeps_read_the_springs_as_the_model_holds_them_at_each_step():
    """The sweeps read each step's packed copy of the springs (``kernels.vbd.pack_springs``): a stiffness changed
    between steps gives the next step backward Euler's step with the new stiffness, and a spring broken between
    steps exerts nothing (the particle moves on at its velocity), each checked against the analytic step."""
    m, L, h = 0.2, 0.1, 1.0 / 30.0
    model = spring_pair(40.0)
    sim = ws.Simulator(model, integrator=ws.VBD(iterations=1), forces=[])

    def step_and_check(k):
        x0, v0 = (float(a[1][0]) for a in (sim.state.positions.numpy(), sim.state.velocities.numpy()))
        y = x0 + h * v0
        expected = (m / h**2 * y + k * L) / (m / h**2 + k)
        sim.step(h)
        assert sim.state.positions.numpy()[1][0] == pytest.approx(expected, rel=1e-6), k
        return x0

    step_and_check(40.0)
    model.spring_stiffness.assign(np.array([90.0], np.float32))
    step_and_check(90.0)
    entries = sim.integrator._springs.numpy()
    assert [int(e[0]) for e in entries] == [1, 0] and all(float(e[2]) == 90.0 for e in entries)
    model.spring_broken.assign(np.array([1], np.int32))
    step_and_check(0.0)  # broken: the inertial step y
    assert all(int(e[0]) == -1 for e in sim.integrator._springs.numpy())

def small_torus(position=(0.0, 0.3, 0.0), builder=None, segments=10, sides=6):
    b = builder or ws.ModelBuilder()
    points, faces = ws.torus_mesh(0.1, 0.04, segments, sides)
    body = ws.add_soft_body(b, points, faces, total_mass=1.0, stiffness=150.0, damping=0.05, lattice_cells=5,
                            position=position)
    return b, body


@pytest.mark.parametrize("forget", [False, True])
def test_a_torus_released_in_the_air_falls_as_backward_eulers_free_fall(forget):
    """A torus of the scene's full resolution (50 x 40 surface vertices and its 10-cell lattice, 2,124 particles)
    released at rest in the air falls, with VBD's adaptive guess (the default), as backward Euler's free fall: after
    k steps of h its centre has dropped g h^2 k (k + 1) / 2 and it moves at g h k. The guess takes the acceleration
    of the step before; for the first step there is none, and taking none (the velocities as given, at rest) made its
    first guess gravity-free: 12 sweeps do not carry a whole torus's translation, and it fell 32.6 mm instead of
    35.8 mm in 20 steps, 10 % of its kinetic energy short. ``forget``: the same after 5 steps without gravity (a
    history that says "at rest"), gravity turned on and the state set back from outside (``notify_changed("state")``:
    ``VBD.forget_history``)."""
    cls = get_scene("donuts")
    scene = cls(cls.resolve_params({"count": 1, "segments": 50, "sides": 40, "lattice_cells": 10,
                                    "dt": 1.0 / 240.0, "integrator": "vbd"}), device=DEVICE)
    sim = scene.sim
    mass = sim.model.particle_mass.numpy().astype(np.float64)
    if forget:  # a history that says "at rest": steps with gravity off, then the state set back and gravity on
        g = sim.forces[0].g
        sim.forces[0].g = (0.0, 0.0, 0.0)
        for _ in range(5):
            sim.step(1.0 / 240.0)
        sim.forces[0].g = g
        sim.state.positions.assign(sim.model.particle_q)
        sim.state.velocities.zero_()
        sim.notify_changed("state")
    start = (mass * sim.state.positions.numpy()[:, 1]).sum() / mass.sum()
    h, steps, gravity = 1.0 / 240.0, 20, scene.params["gravity"]
    for _ in range(steps):
        sim.step(h)
    x, v = sim.state.positions.numpy().astype(np.float64), sim.state.velocities.numpy().astype(np.float64)
    drop = start - (mass * x[:, 1]).sum() / mass.sum()
    assert drop == pytest.approx(gravity * h * h * steps * (steps + 1) / 2.0, rel=1.0e-3), drop  # 35.77 mm
    energy = 0.5 * (mass[:, None] * v * v).sum()
    assert energy == pytest.approx(0.5 * mass.sum() * (gravity * h * steps) ** 2, rel=3.0e-3), energy


def test_converged_vbd_is_implicit_euler():
    """A torus falling and wobbling at 1/60 s: 400 VBD sweeps a step give ImplicitEuler's step (Newton
    to 1e-9 m/s, CG to 1e-10) over 5 steps, to 1e-5 m; 3 sweeps do not (the test can fail)."""
    b, _ = small_torus()
    model = b.finalize(DEVICE)
    q = model.particle_q.numpy()
    q[::3] += 0.01  # strain the springs
    model.particle_q.assign(q)

    def run(integrator):
        sim = ws.Simulator(model, integrator=integrator, forces=[ws.Gravity()])
        for _ in range(5):
            sim.step(1.0 / 60.0)
        return sim.state.positions.numpy().astype(np.float64)

    reference = run(ws.ImplicitEuler(newton_iterations=30, newton_tol=1e-9, cg_tol=1e-10))
    assert np.abs(run(ws.VBD(iterations=400)) - reference).max() < 1e-5
    assert np.abs(run(ws.VBD(iterations=3)) - reference).max() > 1e-4


def test_greedy_colouring_separates_every_spring_and_tiles():
    b, body = small_torus()
    model = b.finalize(DEVICE)
    springs = model.spring_indices.numpy().reshape(-1, 2)
    colours = greedy_colouring(model.particle_count, springs)
    assert (colours[springs[:, 0]] != colours[springs[:, 1]]).all()
    assert np.array_equal(colours, greedy_colouring(model.particle_count, springs))  # deterministic
    degree = np.bincount(springs.reshape(-1), minlength=model.particle_count)
    assert colours.max() <= degree.max()  # greedy: at most max degree + 1 colours
    tiled = tile_colouring(colours, 3)
    P = model.particle_count
    every = np.concatenate([springs + k * P for k in range(3)])
    assert (tiled[every[:, 0]] != tiled[every[:, 1]]).all()
    offsets, particles = colour_groups(tiled)
    assert sorted(particles.tolist()) == list(range(3 * P))
    for c in range(len(offsets) - 1):
        assert (tiled[particles[offsets[c]:offsets[c + 1]]] == c).all()
    with pytest.raises(ValueError, match=r"pair 1 joins particle 2 to itself"):
        greedy_colouring(4, [(0, 1), (2, 2)])


def two_tori(self_contact=True, gap=0.02, **contact_options):
    """Two tori of 10 x 6, the upper tilted, dropped on a floor, VBD with contact (self contact on; more
    ``VBDContact`` options as keywords)."""
    b = ws.ModelBuilder()
    _, lower = small_torus((0.0, 0.06, 0.0), b)
    points, faces = ws.torus_mesh(0.1, 0.04, 10, 6)
    tilt = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(1.2), -np.sin(1.2)], [0.0, np.sin(1.2), np.cos(1.2)]])
    upper = ws.add_soft_body(b, points @ tilt.T, faces, total_mass=1.0, stiffness=150.0, damping=0.05,
                             lattice_cells=5, position=(0.05, 0.06 + 0.1 + 0.04 + gap, 0.0))
    model = b.finalize(DEVICE)
    # the tilted torus's lattice differs: no copies, one colouring of the whole model, bodies by particle
    body = np.zeros(model.particle_count, dtype=np.int64)
    body[upper.particle_start:] = 1
    faces = np.concatenate([lower.faces, upper.faces])
    contact = ws.VBDContact(faces, particle_body=body, thickness=0.006, self_contact=self_contact,
                            planes=[((0.0, 1.0, 0.0), 0.0)], **contact_options)
    sim = ws.Simulator(model, integrator=ws.VBD(10, contact=contact), forces=[ws.Gravity()])
    return sim, contact, faces


def test_two_torus_drop_keeps_every_edge_out_of_every_triangle_and_repeats_bit_for_bit():
    """Two tori (one tilted through the other's hole) dropped on the floor at 1/240 s with self contact:
    at every frame no edge passes through any triangle it shares no vertex with (either torus's own
    included), no vertex is under the floor, the tori touch; a second run gives the same bits."""
    runs = []
    for _ in range(2):
        sim, contact, faces = two_tori()
        touched = 0
        for frame in range(40):
            sim.frame(1.0 / 60.0, 4)
            x = sim.state.positions.numpy()
            if not runs:
                assert crossings(x, faces) == 0, frame
                assert x[:, 1].min() > 0.0, frame
            touched = max(touched, contact.pair_counts()[0])
        runs.append((sim.state.positions.numpy(), sim.state.velocities.numpy(), touched))
    assert runs[0][2] > 0  # they met
    assert np.array_equal(runs[0][0], runs[1][0]) and np.array_equal(runs[0][1], runs[1][1])
    assert sim.energy_gain < MARGIN


def test_a_contact_between_vertices_of_one_colour_closes_its_gap_once_not_twice():
    """A vertex of one triangle 4 mm above the inside of another (thickness 6 mm, contact 2,000 N/m against a
    vertex's m / h^2 of 57.6 N/m, no gravity, no friction): the vertex and the nearest corner below it have one
    colour, so one sweep moves them at once. Each takes the pair's Hessian block twice (``same_colour``): together
    they close the 2 mm overlap at most (taken once, the gap grew to 6.67 mm, past the thickness, and a resting
    heap jittered at up to 0.8 m/s); the sweep's other colours then add little."""
    b = ws.ModelBuilder()
    lower = [(0.0, 0.0, 0.0), (0.1, 0.0, 0.0), (0.0, 0.0, 0.1)]
    upper = [(0.02, 0.004, 0.02), (0.02, 0.08, 0.06), (0.06, 0.08, 0.02)]
    for x in lower + upper:
        b.add_particle(x, mass=1.0e-3)
    for first in (0, 3):
        for i, j in ((0, 1), (1, 2), (0, 2)):
            pi, pj = np.array((lower + upper)[first + i]), np.array((lower + upper)[first + j])
            b.add_spring(first + i, first + j, 150.0, 0.0, rest_length=float(np.linalg.norm(pi - pj)))
    model = b.finalize(DEVICE)
    contact = ws.VBDContact([[0, 1, 2], [3, 4, 5]], particle_body=[0, 0, 0, 1, 1, 1], thickness=0.006,
                            stiffness=2000.0, friction=0.0, bound_fraction=0.499)
    sim = ws.Simulator(model, integrator=ws.VBD(1, contact=contact, detect_every=0), forces=[])
    sim.step(1.0 / 240.0)
    colour = sim.integrator.particle_colour.numpy()
    assert colour[3] == colour[0] and len(set(colour[:3])) == 3  # the vertex and the corner under it: one colour
    x = sim.state.positions.numpy().astype(np.float64)
    normal = np.cross(x[1] - x[0], x[2] - x[0])
    gap = abs(np.dot(x[3] - x[0], normal / np.linalg.norm(normal)))  # the vertex stays above the triangle's inside
    assert 0.004 + 0.0017 < gap <= 0.006 + 1.0e-6, gap  # 5.98 mm


def test_a_pressed_heap_comes_to_rest_where_whole_newton_steps_jitter():
    """Four small tori in a narrow box pressed by contacts 200x stiffer than their springs (30,000 N/m): with
    whole Newton steps (``vbd_line_search=0``) a step can enter a contact or compress a spring past where the
    particle's energy drops, the sweeps cycle and the heap jitters after 2 s (particles past 0.05 m/s turning back
    every step); with each step checked against the particle's energy (the default, 4 halvings) the sweeps
    descend and the heap comes to rest without it."""
    figures = {}
    for line_search in (0, 4):
        cls = get_scene("donuts")
        p = cls.resolve_params({"count": 4, **SMALL, "box": 0.16, "integrator": "vbd", "contact_stiffness": 30000.0,
                                "vbd_line_search": line_search})
        scene = cls(p, device=DEVICE)
        turned, before = [], None
        for step in range(480):
            scene.sim.step(1.0 / 240.0)
            if step >= 440:
                v = scene.sim.state.velocities.numpy()
                if before is not None:
                    fast = np.linalg.norm(v, axis=1) > 0.05
                    turned.append(int((fast & (np.einsum("ij,ij->i", v, before) < 0.0)).sum()))
                before = v.copy()
        figures[line_search] = (float(np.mean(turned)), float(np.linalg.norm(v, axis=1).max()))
    assert figures[0][0] > 5.0, figures  # whole steps: a jitter (14 a step, up to 1 m/s, when written)
    assert figures[4][0] < 0.5 and figures[4][1] < 0.3, figures  # checked steps: nothing turns back


def test_a_step_allocates_nothing(monkeypatch):
    """After the first step, VBD steps (contact search, sweeps, bounds) allocate no memory on the CPU
    device (what a CUDA graph needs); on CUDA the steps are also captured and replayed as a graph and give
    the eager steps' bits."""
    sim, _, _ = two_tori()
    sim.step(1.0 / 240.0)
    allocator = wp.get_device(DEVICE).default_allocator
    sizes = []
    allocate = allocator.allocate
    monkeypatch.setattr(allocator, "allocate", lambda size: sizes.append(size) or allocate(size))
    wp.zeros(4, dtype=float, device=DEVICE)
    assert sizes == [16]  # the counter sees allocations
    sizes.clear()
    for _ in range(3):
        sim.integrator.step(sim.system, sim.state.positions, sim.state.velocities, sim._time, 1.0 / 240.0)
    monkeypatch.undo()
    assert sizes == []
    if wp.is_cuda_available():
        check_graph_capture("cuda:0")


def test_lanes_split_each_particles_sums_within_rounding_and_repeat_their_bits(monkeypatch):
    """``VBD(lanes=B)``: each particle's springs and contact entries dealt over the B lanes of a block, their
    partial sums added by a fixed-order tile reduction (``kernels.vbd.solve_colour_lanes``, the CUDA default; on
    the CPU its lanes run as Warp's fibers, ``wp.config.enable_cpu_blocks``). Two tori dropped on each other with
    self contact: within rounding of a thread a particle (4 lanes over the kept entries; 3 over the whole lists,
    ``near_capacity`` 1), two runs the same bits (the second with the colour solve compiled for the compiler's choice
    of registers, ``max_registers=None``: the same sums), and a step allocates nothing."""
    monkeypatch.setattr(wp.config, "enable_cpu_blocks", True)
    runs = []
    for lanes, near_capacity, registers in ((1, 128, 64), (4, 128, 64), (4, 128, None), (3, 1, 64)):
        sim, _, _ = two_tori(gap=0.004, near_capacity=near_capacity)
        sim.integrator.lanes, sim.integrator.max_registers = lanes, registers
        for _ in range(12):
            sim.frame(1.0 / 60.0, 4)
        solves = (vbd_kernels.solve_colour, vbd_kernels.solve_colour_lanes, vbd_kernels.solve_colour_lanes_compact)
        solve = next(launch for launch in sim.integrator._sweep if launch.kernel in solves)  # (after solve_free)
        assert solve.block_dim == lanes
        if lanes > 1:
            compact = solve.kernel is vbd_kernels.solve_colour_lanes_compact
            assert compact == (registers is not None)
        runs.append((sim.state.positions.numpy(), sim.state.velocities.numpy()))
    (x1, v1), (x4, v4), (x4b, v4b), (x3, v3) = runs
    assert np.array_equal(x4, x4b) and np.array_equal(v4, v4b)
    assert not np.array_equal(x4, x1)  # the lanes ran: the sums' order differs
    for x, v in ((x4, v4), (x3, v3)):
        assert np.abs(x - x1).max() < 1.0e-5  # [m], tori of 0.1 m
        assert np.abs(v - v1).max() < 5.0e-4  # [m/s]: a velocity is the step's displacement / h, 1 um is 2.4e-4
    allocator = wp.get_device(DEVICE).default_allocator
    sizes = []
    allocate = allocator.allocate
    monkeypatch.setattr(allocator, "allocate", lambda size: sizes.append(size) or allocate(size))
    for _ in range(3):
        sim.integrator.step(sim.system, sim.state.positions, sim.state.velocities, sim._time, 1.0 / 240.0)
    assert sizes == []


def test_the_compact_colour_solve_is_chosen_by_the_colours_size(monkeypatch):
    """``max_registers="auto"`` (the default): the colour solve compiled for 64 registers a thread on CUDA when the
    largest colour holds more particles than 32 warps x the device's multiprocessors (more warps resident pay for
    the spills there; on an H200 a 12-torus heap's colours of 2,300 particles ran 16-18 % slower with it), never on the
    CPU; 64 and None choose it or not whatever the size."""
    sim, _, _ = two_tori()
    integrator = sim.integrator
    integrator.prepare(sim.system)
    largest = max(np.diff(integrator.colour_offsets))
    assert not integrator.compact_on("cpu")
    import warpsim.bodies.vbd as vbd_module

    for sm_count, want in ((largest // 32 + 1, False), (largest // 32 - 1, True)):
        fake = types.SimpleNamespace(is_cuda=True, sm_count=int(sm_count))
        monkeypatch.setattr(vbd_module.wp, "get_device", lambda device, fake=fake: fake)
        assert integrator.compact_on("cuda:0") is want, sm_count
        for registers in (64, None):
            integrator.max_registers = registers
            assert integrator.compact_on("cuda:0") is (registers is not None)
        integrator.max_registers = "auto"


def check_graph_capture(device):
    """Eager steps and the same steps replayed from a CUDA graph give the same bits (CUDA only)."""
    results = []
    for graph in (False, True):
        with wp.ScopedDevice(device):
            b = ws.ModelBuilder()
            _, lower = small_torus((0.0, 0.06, 0.0), b)
            small_torus((0.02, 0.2, 0.0), b)
            model = b.finalize(device)
            P = lower.particle_count
            contact = ws.VBDContact(lower.faces, body_size=P, planes=[((0.0, 1.0, 0.0), 0.0)], rebuild_every=1000)
            integ = ws.VBD(6, contact=contact, body_size=P)
            sim = ws.Simulator(model, integrator=integ, forces=[ws.Gravity()], check_every=0)
            sim.step(1.0 / 240.0)
            if graph:
                with wp.ScopedCapture(device) as capture:
                    integ.step(sim.system, sim.state.positions, sim.state.velocities, sim._time, 1.0 / 240.0)
                for _ in range(10):
                    wp.capture_launch(capture.graph)
            else:
                for _ in range(10):
                    integ.step(sim.system, sim.state.positions, sim.state.velocities, sim._time, 1.0 / 240.0)
            results.append(sim.state.positions.numpy())
    assert np.array_equal(results[0], results[1])


def heap(count, frames, check_every, shape=SMALL, substeps=4, **params):
    """The donuts scene with integrator=vbd at 1/(60 ``substeps``) s (its ``dt`` that step, as ``warpsim run``
    sets it: the default b_max fits the fall's guess): (scene, deepest vertex [m], most vertex-triangle pairs, fastest
    particle [m/s]); asserts no edge through another torus's triangle on checked frames."""
    cls = get_scene("donuts")
    p = cls.resolve_params({"count": count, **shape, "integrator": "vbd", "dt": 1.0 / (60.0 * substeps), **params})
    scene = cls(p, device=DEVICE)
    worst, most, fastest = 0.0, 0, 0.0
    for frame in range(frames):
        scene.advance(1.0 / 60.0, substeps)
        scene.sim.check_frame(1.0 / 60.0)  # the energy balance: raises on a gain past its margin
        if frame % check_every == check_every - 1 or frame == frames - 1:
            x = scene.sim.state.positions.numpy()
            worst = max(worst, deepest_vertex(x, scene.bodies))
            assert edges_through_other_bodies(x, scene.bodies) == [], frame
            most = max(most, scene.vbd_contact.pair_counts()[0])
            fastest = max(fastest, float(np.linalg.norm(scene.sim.state.velocities.numpy(), axis=1).max()))
    return scene, p, worst, most, fastest


def test_small_heap_keeps_every_edge_out_at_every_frame():
    """4 tori stacked in a narrow box with self contact: every frame, no edge through any triangle it shares
    no vertex with (brute force over all pairs), no vertex deeper than the thickness."""
    cls = get_scene("donuts")
    p = cls.resolve_params({"count": 4, **SMALL, "box": 0.16, "integrator": "vbd", "self_contact": True})
    scene = cls(p, device=DEVICE)
    faces = np.concatenate([b.faces for b in scene.bodies])
    worst = 0.0
    for frame in range(45):
        scene.advance(1.0 / 60.0, 4)
        x = scene.sim.state.positions.numpy()
        assert crossings(x, faces) == 0, frame
        worst = max(worst, deepest_vertex(x, scene.bodies))
    assert worst <= p["thickness"]
    assert max(x[b.surface_indices, 1].mean() for b in scene.bodies) > 0.15  # stacked, not side by side


@pytest.mark.parametrize("rounding", [{"solver_iterations": 8}, {"solver_iterations": 6},
                                      {"solver_iterations": 8, "vbd_detect_every": 3}])
def test_the_scene_heap_holds_over_600_frames(rounding):
    """The donuts scene's 12 tori (10 x 6 vertices and a 5-cell lattice each, so that 600 frames fit the
    CPU) at 1/240 s by VBD, under three roundings (8 and 6 sweeps a step; 8 with searches every 3 sweeps; the
    scene's 12 held too, 75 s of CPU time, benchmarks/RESULTS.md): over
    the scene's 600 frames no edge passes through another torus's triangle (every 10 frames), no vertex goes
    deeper than the thickness, the energy balance never trips (checked every frame), nothing is thrown
    faster than the tori fall, and the heap comes to rest with tori on tori."""
    scene, p, worst, most, fastest = heap(12, 600, 10, **rounding)
    assert most > 100  # a heap in contact ...
    assert worst <= p["thickness"], worst  # ... with no vertex deeper than the thickness
    assert fastest < 5.0, fastest
    assert scene.sim.energy_gain < MARGIN
    assert scene.kinetic_energy() < 0.05  # at rest (about 30 J at the first impacts)
    x = scene.sim.state.positions.numpy()
    assert max(x[b.surface_indices, 1].mean() for b in scene.bodies) > 0.1  # tori lie on tori


def test_the_scene_heap_holds_at_steps_of_a_sixtieth_of_a_second():
    """The same 12 tori at one step of 1/60 s a frame (4x the step fast mass-spring needs: at 1/60 s with 12
    accelerated iterations it let 435 edges through other tori by frame 99 of the same heap, benchmarks/RESULTS.md),
    the most a vertex moves between searches by default the fall's initial guess at that step (69 mm: no guess is cut,
    the fall is not held back): over 600 frames no edge through another torus's triangle (every 10 frames), no vertex
    deeper than the thickness, no energy gain, and the heap at rest with tori on tori."""
    scene, p, worst, most, fastest = heap(12, 600, 10, substeps=1)
    assert scene.stability_warning(1.0 / 60.0, 1) is None
    assert most > 100
    assert worst <= p["thickness"], worst
    assert fastest < 5.0, fastest
    assert scene.sim.energy_gain < MARGIN
    assert scene.kinetic_energy() < 0.05
    x = scene.sim.state.positions.numpy()
    assert max(x[b.surface_indices, 1].mean() for b in scene.bodies) > 0.1


def test_the_tutorials_vbd_command_runs_at_one_step_a_frame(tmp_path):
    """docs/tutorials/bodies.rst: ``warpsim run donuts --frames 60 --set integrator=vbd --fps 60 --substeps 1`` (3
    frames here): no warning before the first step (the default bound fits the fall's guess at that step), one step a
    frame, and its USD written."""
    from pxr import Usd

    from warpsim.cli import main

    out, err = io.StringIO(), io.StringIO()
    usd = tmp_path / "d.usda"
    code = main(["run", "donuts", "--frames", "3", "--set", "integrator=vbd", "--fps", "60", "--substeps", "1",
                 "--out", str(usd)], out=out, err=err)
    assert code == 0, err.getvalue()
    assert "warning" not in err.getvalue(), err.getvalue()
    stage = Usd.Stage.Open(str(usd))
    assert stage.GetEndTimeCode() - stage.GetStartTimeCode() == 3


def test_stability_report_and_scene_options():
    """The stability report says VBD is unconditionally stable with accuracy set by iterations; the
    scene refuses bad VBD options with a line naming them."""
    model = spring_pair()
    sim = ws.Simulator(model, integrator=ws.VBD(), forces=[])
    limit = sim.stability()
    assert limit.dt == float("inf")
    assert "unconditionally stable, accuracy set by iterations" in limit.reason
    cls = get_scene("donuts")
    for key, value, message in (("vbd_detect_every", -1, "vbd_detect_every=-1"),
                                ("vbd_max_displacement", -0.1, "vbd_max_displacement=-0.1"),
                                ("vbd_min_displacement", -0.1, "vbd_min_displacement=-0.1"),
                                ("vbd_min_displacement", 0.01, "at most vbd_max_displacement")):
        with pytest.raises(ValueError, match=message):
            cls(cls.resolve_params({"count": 2, **SMALL, "integrator": "vbd", key: value}), device=DEVICE)
    with pytest.raises(ValueError, match="min_displacement = 0.01 m exceeds max_displacement"):
        ws.VBDContact([[0, 1, 2]], thickness=0.006, min_displacement=0.01)


def test_chebyshev_acceleration_is_reported_not_unconditional_and_a_blow_up_names_it():
    """VBD without Chebyshev acceleration is unconditionally stable; with it the extrapolation can add energy: a
    kicked torus of 1e5 N/m springs at 1/60 s with rho 0.99 and 12 sweeps gains 4,800x its energy in its first step.
    The stability report and a warning before the first step say so, and the energy balance's message names the
    acceleration and its remedy (it said "the energy came from elsewhere ... a smaller step will not help")."""
    from test_fast_mass_spring import kick, torus_model

    model = torus_model(stiffness=1.0e5)
    plain = ws.Simulator(model, integrator=ws.VBD(12), forces=[])
    assert "but not with Chebyshev" not in plain.stability().reason
    assert plain.integrator.energy_cause(1.0 / 60.0) is None
    sim = ws.Simulator(model, integrator=ws.VBD(12, chebyshev_rho=0.99), forces=[])
    assert "but not with Chebyshev acceleration (chebyshev_rho = 0.99)" in sim.stability().reason
    sim.state.velocities.assign(kick(model))
    with pytest.warns(ws.StabilityWarning, match="chebyshev_rho = 0.99"):
        with pytest.raises(ws.SimulationError) as error:
            for _ in range(60):
                sim.frame(1.0 / 60.0)
    message = str(error.value)
    assert "Chebyshev acceleration (chebyshev_rho = 0.99)" in message and "Remedy: chebyshev_rho=0" in message
    assert "will not help" not in message


def test_donuts_by_vbd_say_before_the_first_step_when_the_bound_would_slow_the_fall():
    """A vertex's initial guess moves at most b_max (``vbd_max_displacement``) before the next contact search; a
    longer guess is cut and the fall slowed (next test). It was warned of only past 3 searches x b_max a step, which let
    a 3x longer guess pass. Two tori at one step of 1/60 s a frame: with b_max = 6 mm the scene says so before the
    first step, naming the steps a frame and the b_max that fit the fall's guess (and with those there is no line); by
    default (0: the fall's guess at the scene's step dt, which ``warpsim run`` sets to the step taken) there is none."""
    cls = get_scene("donuts")
    h = 1.0 / 60.0
    scene = cls(cls.resolve_params({"count": 2, **SMALL, "integrator": "vbd", "dt": h,
                                    "vbd_max_displacement": 0.006}), device=DEVICE)
    line = scene.stability_warning(h, 1)
    assert line is not None and "longer than the 6 mm" in line and "slows the fall" in line, line
    guess = float(re.search(r"vbd_max_displacement=([0-9.e-]+)", line).group(1))
    assert guess == scene.guess_step(h) > 0.04  # [m]: 2.9 m/s x 1/60 s + g h^2
    more = int(re.search(r"--substeps (\d+)", line).group(1))
    assert scene.guess_step(h / more) <= 0.006 < scene.guess_step(h / (more - 1))
    for extra, step in (({"vbd_max_displacement": guess}, h), ({}, h), ({}, h / 4)):
        scene = cls(cls.resolve_params({"count": 2, **SMALL, "integrator": "vbd", "dt": step, **extra}),
                    device=DEVICE)
        assert scene.stability_warning(h, round(h / step)) is None
        assert scene.vbd_contact.max_displacement >= scene.guess_step(step)


@pytest.mark.parametrize("b_max, slowed", [(0.006, True), (0.03, False)])
def test_a_falling_torus_whose_guess_the_bound_cuts_is_slowed(b_max, slowed):
    """One torus (24 x 12) released in the air at 3 m/s, far from the walls, at 1/240 s: its initial guess is 12.7 mm
    a step. With b_max = 6 mm the bound cuts it and the sweeps do not carry the torus's translation on (its springs
    hold each vertex to its neighbours' cut positions): measured 16 % slower than backward Euler's free fall after
    20 steps; with b_max = 30 mm it falls as backward Euler, v = v0 + g t, to 1e-3."""
    cls = get_scene("donuts")
    h, v0 = 1.0 / 240.0, 3.0
    scene = cls(cls.resolve_params({"count": 1, "segments": 24, "sides": 12, "lattice_cells": 8, "dt": h,
                                    "integrator": "vbd", "box": 3.0, "vbd_max_displacement": b_max}), device=DEVICE)
    sim = scene.sim
    q = sim.state.positions.numpy()
    q -= (q.mean(0) - np.array([0.0, 2.0, 0.0]))  # in the middle of the box, 2 m up
    sim.state.positions.assign(q)
    sim.state.velocities.assign(np.tile([0.0, -v0, 0.0], (len(q), 1)).astype(np.float32))
    sim.notify_changed("state")
    mass = sim.model.particle_mass.numpy()
    for _ in range(20):
        sim.step(h)
    v = -float((sim.state.velocities.numpy()[:, 1] * mass).sum() / mass.sum())
    free = v0 + 9.81 * 20 * h
    if slowed:
        assert v < 0.9 * free, v
    else:
        assert v == pytest.approx(free, rel=1.0e-3)


def test_bad_input_names_the_item_and_a_fix():
    with pytest.raises(ValueError, match="VBD iterations"):
        ws.VBD(iterations=0)
    with pytest.raises(ValueError, match="VBDContact bound_fraction"):
        ws.VBDContact([[0, 1, 2]], bound_fraction=0.6)
    with pytest.raises(ValueError, match=r"VBDContact faces must have shape \(F, 3\)"):
        ws.VBDContact([[0, 1]])
    with pytest.raises(ValueError, match=r"VBDContact planes\[0\] has a zero normal"):
        ws.VBDContact([[0, 1, 2]], planes=[((0.0, 0.0, 0.0), 0.0)])
    with pytest.raises(ValueError, match="VBD contact is"):
        ws.VBD(contact=object())
    with pytest.raises(ValueError, match=r"VBD max_registers is 48; give 64 \(the compact colour solve\), None "
                                         r"\(the compiler's choice\) or 'auto'"):
        ws.VBD(max_registers=48)
    with pytest.raises(ValueError, match="VBD line_search"):
        ws.VBD(line_search=-1)
    with pytest.raises(ValueError, match="VBD split is 'yes'; give True"):
        ws.VBD(split="yes")
    cls = get_scene("donuts")
    with pytest.raises(ValueError, match=r"vbd_line_search=-1: give an integer >= 0 \(0: every Newton step taken"):
        cls(cls.resolve_params({**SMALL, "count": 2, "integrator": "vbd", "vbd_line_search": -1}), device=DEVICE)
    model = spring_pair()
    with pytest.raises(ValueError, match="VBD body_size = 3 does not divide the model's 2 particles"):
        ws.Simulator(model, integrator=ws.VBD(body_size=3), forces=[])


def test_the_command_line_runs_the_heap_by_vbd(tmp_path):
    """``warpsim run donuts --set integrator=vbd`` writes a cache (small tori, a few frames)."""
    from warpsim.cli import main

    out, err = io.StringIO(), io.StringIO()
    path = tmp_path / "donuts.usda"
    code = main(["run", "donuts", "--frames", "3", "--substeps", "4", "--device", DEVICE, "--out", str(path),
                 "--set", "integrator=vbd", "--set", "count=2", "--set", "segments=10", "--set", "sides=6",
                 "--set", "lattice_cells=5"], out, err)
    assert code == 0, err.getvalue()
    assert path.exists()


def test_worlds_of_a_sweep_each_collide_their_own_tori_and_equal_their_runs_alone():
    """Two worlds of the donuts by VBD (stiffness 150 and 300 N/m) in one batch: each world's tori meet only
    its own (one contact, one BVH for both), and each world gives the bits of its scene run alone (the pair
    lists are sorted, so the shared BVH's traversal order does not enter; a search within a step is skipped
    or run world by world)."""
    from warpsim.worlds.batch import WorldBatch

    cls = get_scene("donuts")
    params = [cls.resolve_params({"count": 2, **SMALL, "integrator": "vbd", "stiffness": k}) for k in (150.0, 300.0)]
    batch = WorldBatch(cls, params, device=DEVICE)
    for _ in range(25):
        batch.advance(1.0 / 60.0, 4)
    x, v = batch.world_slices()
    searches = []
    for w, p in enumerate(params):
        alone = cls(p, device=DEVICE)
        touched = 0
        for _ in range(25):
            alone.advance(1.0 / 60.0, 4)
            touched = max(touched, alone.vbd_contact.pair_counts()[0])
        assert touched > 0  # the tori met
        assert np.array_equal(x[w], alone.sim.state.positions.numpy()), w
        searches.append(alone.vbd_contact.searches_run)
    assert np.abs(x[0] - x[1]).max() > 1e-3
    # searches within a step are skipped world by world (each as its scene run alone), counted per world
    assert batch.sim.integrator.contact.searches_run == sum(searches)


def test_the_viewer_drag_goes_through_the_protocol():
    """A drag spring added to a running VBD heap (``scene.add_drag``, as the viewer does: the integrator
    re-allocates through ``notify_changed("forces")``) lifts the grabbed vertex toward its target, with the
    contact still inside the descent (no edge through another torus's triangle)."""
    cls = get_scene("donuts")
    scene = cls(cls.resolve_params({"count": 2, **SMALL, "integrator": "vbd"}), device=DEVICE)
    for _ in range(20):
        scene.advance(1.0 / 60.0, 4)
    drag = ws.DragSpring(20.0, 0.5)
    scene.add_drag(drag)
    particle = int(scene.bodies[1].surface_indices[0])
    start = scene.sim.state.positions.numpy()[particle].copy()
    drag.grab(particle, start + np.array([0.0, 0.15, 0.0]))
    for _ in range(30):
        scene.advance(1.0 / 60.0, 4)
    x = scene.sim.state.positions.numpy()
    assert x[particle, 1] > start[1] + 0.05  # lifted toward the target
    assert edges_through_other_bodies(x, scene.bodies) == []


def point_triangle_distances(p, a, b, c):
    """Distances [m] from points p (N, 3) to one triangle abc: to its plane where the projection lies
    inside, else to the nearest of its three sides (NumPy oracle)."""
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n)
    h = (p - a) @ n
    x = p - h[:, None] * n
    inside = np.ones(len(p), dtype=bool)
    for u, v in ((a, b), (b, c), (c, a)):
        inside &= np.cross(v - u, x - u) @ n >= 0.0
    sides = [point_segment_distances(p, u, v) for u, v in ((a, b), (b, c), (c, a))]
    return np.where(inside, np.abs(h), np.min(sides, axis=0))


def point_segment_distances(p, u, v):
    t = np.clip((p - u) @ (v - u) / ((v - u) @ (v - u)), 0.0, 1.0)
    return np.linalg.norm(p - (u + t[:, None] * (v - u)), axis=1)


def segment_distance(p1, q1, p2, q2):
    """Distance [m] between two segments: the four end-to-segment distances, or the lines' closest
    points where both fall inside (NumPy oracle)."""
    ends = [point_segment_distances(np.array([x]), u, v)[0] for x, u, v in
            ((p1, p2, q2), (q1, p2, q2), (p2, p1, q1), (q2, p1, q1))]
    d1, d2, r = q1 - p1, q2 - p2, p1 - p2
    A = np.array([[d1 @ d1, -d1 @ d2], [d1 @ d2, -d2 @ d2]])
    if abs(np.linalg.det(A)) > 1e-14:
        s, t = np.linalg.solve(A, [-(d1 @ r), -(d2 @ r)])
        if 0.0 <= s <= 1.0 and 0.0 <= t <= 1.0:
            ends.append(np.linalg.norm(p1 + s * d1 - p2 - t * d2))
    return min(ends)


def test_the_search_lists_every_pair_within_the_radius_and_bounds_by_the_nearest():
    """Two tori 4 mm apart (10 x 6 surfaces, no self contact): each surface
    vertex's list holds exactly the other torus's triangles within the query radius, each edge's list the
    other torus's edges within it (NumPy distances, pairs within 1e-5 m of the radius left out), and each
    vertex's bound is the fraction of the nearest distance its vertex, triangles and edges meet (or b_max)."""
    sim, contact, faces = two_tori(self_contact=False, gap=0.004)
    sim.integrator.prepare(sim.system)
    contact.search(sim.state.positions)
    x = sim.state.positions.numpy().astype(np.float64)
    body = contact._body.numpy()
    surface, r = contact._surface.numpy(), contact.query_radius
    vt, count = contact._vt.numpy().reshape(len(surface), -1), contact._vt_count.numpy()
    distances = np.stack([point_triangle_distances(x[surface], *x[f]) for f in faces], 1)  # (V, F)
    other = body[surface][:, None] != body[faces[:, 0]][None, :]
    listed = 0
    for s in range(len(surface)):
        want = set(np.flatnonzero(other[s] & (distances[s] < r - 1e-5)))
        maybe = set(np.flatnonzero(other[s] & (np.abs(distances[s] - r) <= 1e-5)))
        got = set(vt[s, :count[s]].tolist())
        assert want <= got <= want | maybe, s
        listed += len(got)
    assert listed > 20  # the tori are close
    edges, _, _ = meshtools.edge_topology(faces)
    ee, ecount = contact._ee.numpy().reshape(len(edges), -1), contact._ee_count.numpy()
    near = np.flatnonzero(ecount > 0)
    assert len(near) > 10
    for e in near[:40]:
        i, j = edges[e]
        for f in range(len(edges)):
            k, m = edges[f]
            if body[k] == body[i]:
                assert f not in ee[e, :ecount[e]]
                continue
            d = segment_distance(x[i], x[j], x[k], x[m])
            if abs(d - r) > 1e-5:
                assert (f in ee[e, :ecount[e]]) == (d < r), (e, f, d)
    bound = contact.bound.numpy()
    nearest = np.where(other, distances, np.inf).min(1)
    for s, p in enumerate(surface):
        assert bound[p] <= contact.bound_fraction * nearest[s] + 1e-7  # its own vertex-triangle pairs
    assert bound.max() == pytest.approx(contact.max_displacement)


def test_active_pairs_count_each_particles_pairs_within_the_thickness_by_its_part_in_them():
    """Two tori 3 mm apart (thickness 6 mm, no self contact): ``VBDContact.active_pairs`` gives each particle the
    other torus's triangles within the thickness of it, the other torus's vertices within it of each triangle it is
    a corner of, and the other torus's edges within it of each edge it ends (NumPy distances; particles with a
    distance within 1e-5 m of the thickness left out); interior particles and far vertices have none."""
    sim, contact, faces = two_tori(self_contact=False, gap=0.003)
    sim.integrator.prepare(sim.system)
    contact.search(sim.state.positions)
    got = contact.active_pairs()
    x = sim.state.positions.numpy().astype(np.float64)
    body, surface, r = contact._body.numpy(), contact.surface_particles, contact.thickness
    assert got.shape == (len(x), 3) and not got[np.setdiff1d(np.arange(len(x)), surface)].any()
    distances = np.stack([point_triangle_distances(x[surface], *x[f]) for f in faces], 1)  # (V, F)
    other = body[surface][:, None] != body[faces[:, 0]][None, :]
    within, at_thickness = other & (distances < r), np.abs(distances - r) < 1.0e-5
    want = np.zeros_like(got)
    unsure = np.zeros(len(x), dtype=bool)
    want[surface, 0] = within.sum(1)
    unsure[surface] |= (other & at_thickness).any(1)
    for c in range(3):  # the triangle's side: the other torus's vertices within the thickness of it
        np.add.at(want[:, 1], faces[:, c], within.sum(0))
        np.logical_or.at(unsure, faces[:, c], (other & at_thickness).any(0))
    edges, _, _ = meshtools.edge_topology(faces)
    mid, half = (x[edges[:, 0]] + x[edges[:, 1]]) / 2, np.linalg.norm(x[edges[:, 1]] - x[edges[:, 0]], axis=1) / 2
    near = np.linalg.norm(mid[:, None] - mid[None, :], axis=2) <= half[:, None] + half[None, :] + r  # spheres meet
    for e, f in zip(*np.nonzero(near & (body[edges[:, 0]][:, None] != body[edges[:, 0]][None, :]))):
        (i, j), (k, m) = edges[e], edges[f]
        d = segment_distance(x[i], x[j], x[k], x[m])
        want[[i, j], 2] += int(d < r)
        unsure[[i, j]] |= abs(d - r) < 1.0e-5
    sure = ~unsure
    bad = np.flatnonzero((got != want).any(1) & sure)
    assert not len(bad), (bad, got[bad], want[bad])
    assert (got.sum(0) > 0).all(), got.sum(0)  # the tori touch: every kind of pair met


def test_caps_follow_each_particles_motion_and_the_lists_hold_every_pair_within_its_radius():
    """Caps from motion (``VBDContact.set_motion``, as ``ws.VBD`` sets them at a step): two tori 4 mm apart, the
    upper falling freely at 0.1 m/s, the lower resting on a support (its velocity that of the step before: VBD's
    adaptive guess takes none of g), a step of 1/60 s. Each particle's cap is 4 x its guess's step (|v| h + s g h^2,
    s = 1 falling, 0 resting) within [b_min, b_max]: the upper torus's 17.6 mm, the lower at b_min although g h^2 alone
    is 2.7 mm (4 x 2.7 would be 10.9 mm, the cap of every resting vertex before s); each vertex's list holds
    exactly the other torus's triangles within r_c + C_v + C_T (NumPy distances, pairs within 1e-5 m of their radius
    left out), its bound is at most its cap, and the resting torus's vertices list fewer pairs than with every cap at
    b_max."""
    counts = []
    for moving in (True, False):
        sim, contact, faces = two_tori(self_contact=False, gap=0.004, max_displacement=0.024)
        sim.integrator.prepare(sim.system)
        n, h, g = sim.model.particle_count, 1.0 / 60.0, 9.81
        body = contact._body.numpy()
        qd = np.zeros((n, 3), dtype=np.float32)
        qd[body == 1, 1] = -0.1
        qd_prev = qd.copy()
        qd_prev[body == 1, 1] += g * h  # the upper torus took all of g in its last step, the lower none
        inv_mass = sim.model.particle_inv_mass.numpy()
        f_ext = np.zeros((n, 3), dtype=np.float32)
        f_ext[:, 1] = -g / inv_mass
        arrays = [wp.array(a, dtype=wp.vec3, device=DEVICE) for a in (qd, qd_prev, f_ext, np.zeros((n, 3), np.float32))]
        if moving:
            contact.set_motion(arrays[0], arrays[1], arrays[2], sim.model.particle_inv_mass, arrays[3], h)
        q = sim.state.positions
        contact.search(q)
        cap = contact.cap.numpy().astype(np.float64)
        if moving:
            s = (body == 1).astype(np.float64)  # the share of g each took in its last step
            want = np.clip(4.0 * (np.linalg.norm(qd, axis=1) * h + s * g * h * h), contact.min_displacement, 0.024)
            assert np.allclose(cap, want, rtol=1e-5, atol=1e-9)
            assert cap[body == 0].max() == pytest.approx(contact.min_displacement)
            assert 0.017 < cap[body == 1].min() < 0.018  # 4 x (0.1 h + g h^2) = 17.6 mm
        else:
            assert (cap == np.float32(0.024)).all()
        x = q.numpy().astype(np.float64)
        surface = contact._surface.numpy()
        vt, count = contact._vt.numpy().reshape(len(surface), -1), contact._vt_count.numpy()
        distances = np.stack([point_triangle_distances(x[surface], *x[f]) for f in faces], 1)  # (V, F)
        other = body[surface][:, None] != body[faces[:, 0]][None, :]
        radius = contact.thickness + cap[surface][:, None] + cap[faces].max(1)[None, :]
        for s_ in range(len(surface)):
            want_pairs = set(np.flatnonzero(other[s_] & (distances[s_] < radius[s_] - 1e-5)))
            maybe = set(np.flatnonzero(other[s_] & (np.abs(distances[s_] - radius[s_]) <= 1e-5)))
            got = set(vt[s_, :count[s_]].tolist())
            assert want_pairs <= got <= want_pairs | maybe, s_
        assert (contact.bound.numpy() <= contact.cap.numpy()).all()
        counts.append(int(count[body[surface] == 0].sum()))
    assert 0 < counts[0] < counts[1]  # the resting torus searches a smaller radius


def test_list_overflow_is_counted_per_search_and_says_the_capacity_needed():
    """Two tori 4 mm apart with lists of 2 pairs: ``overflow`` gives the vertex and triangle queries that met
    more pairs within the query radius than that at the last search and ``most_pairs`` the most one met (NumPy
    distances); the edge queries overflow too. Searching again at the same positions gives the same figures:
    they count one search, never pairs summed over searches (that int32 counter wrapped negative at 1,000
    tori on the H200)."""
    capacity = 2
    sim, contact, faces = two_tori(self_contact=False, gap=0.004, capacity=capacity)
    sim.integrator.prepare(sim.system)
    q = sim.state.positions
    contact.search(q)
    x = q.numpy().astype(np.float64)
    body = contact._body.numpy()
    surface, r = contact._surface.numpy(), contact.query_radius
    distances = np.stack([point_triangle_distances(x[surface], *x[f]) for f in faces], 1)  # (V, F)
    other = body[surface][:, None] != body[faces[:, 0]][None, :]
    surely = other & (distances < r - 1e-5)
    maybe = other & (distances <= r + 1e-5)
    over, most = contact.overflow, contact.most_pairs
    for kind, axis in ((0, 1), (1, 0)):  # per vertex, per triangle
        low, high = surely.sum(axis), maybe.sum(axis)
        assert (low > capacity).sum() <= over[kind] <= (high > capacity).sum(), (kind, over)
        assert over[kind] > 0 and low.max() <= most[kind] <= high.max(), (kind, most)
    assert over[2] > 0 and most[2] > capacity
    vt, count = contact._vt.numpy().reshape(len(surface), -1), contact._vt_count.numpy()
    for s in np.flatnonzero(surely.sum(1) > capacity):  # each kept its nearest
        kept = distances[s, vt[s, :count[s]]]
        assert count[s] == capacity and kept.max() <= np.sort(distances[s][other[s]])[capacity - 1] + 1e-6, s
    for _ in range(3):
        contact.search(q)
    assert contact.overflow == over and contact.most_pairs == most


def test_the_sweeps_gather_over_the_pairs_that_can_push_and_give_the_same_bits():
    """After each search every surface vertex keeps the list entries that can still push on it
    (``keep_near_pairs``: by the distances and the step bounds); the sweeps gather over those alone. Two tori
    dropped on each other with self contact: the same bits as gathering over the whole lists (each vertex's
    kept entries past a capacity of 1), and the kept entries are fewer than the listed ones."""
    runs = []
    for near_capacity in (128, 1):
        sim, contact, _ = two_tori(near_capacity=near_capacity)
        kept = listed = whole = 0
        for _ in range(30):
            sim.frame(1.0 / 60.0, 4)
            entries, past = contact.near_stats()
            kept, whole = max(kept, entries), max(whole, past)
            listed = max(listed, contact.pair_counts()[0])
        runs.append((sim.state.positions.numpy(), sim.state.velocities.numpy(), kept, whole))
    assert np.array_equal(runs[0][0], runs[1][0]) and np.array_equal(runs[0][1], runs[1][1])
    assert runs[0][3] == 0 and runs[1][3] > 0  # capacity 1: vertices gathered over the whole lists
    assert listed > 0 and runs[0][2] > 0


@pytest.mark.parametrize("name", ["drape", "cloth"])
def test_cloth_scenes_by_vbd_keep_the_sheet_whole_and_outside_the_sphere(name):
    """``integrator=vbd`` in the cloth scenes (the sheet's self contact, the sphere and the floor inside the
    descent), 1/240 s, 60 frames: no edge of the sheet through any of its triangles it shares no vertex with
    (brute force, every 5 frames), every particle outside the sphere and above the floor, the energy
    balance quiet, and the sheet came to the sphere."""
    cls = get_scene(name)
    p = cls.resolve_params({"integrator": "vbd", "resolution": 12})
    scene = cls(p, device=DEVICE)
    centre = np.array(scene.sphere_center)
    closest = np.inf
    for frame in range(60):
        scene.advance(1.0 / 60.0, 4)
        x = scene.sim.state.positions.numpy()
        gap = float((np.linalg.norm(x - centre, axis=1) - p["sphere_radius"]).min())
        assert gap > 0.0 and x[:, 1].min() > 0.0, frame
        closest = min(closest, gap)
        if frame % 5 == 4:
            assert crossings(x, scene.cloth.triangles) == 0, frame
    assert closest < p["thickness"]  # it lies on the sphere
    assert scene.sim.energy_gain < MARGIN


def test_cloth_by_vbd_says_before_the_first_step_when_the_bound_would_slow_the_fall():
    """The drape's sheet by VBD at one step of 1/60 s a frame: its fall from 1 m reaches 4.4 m/s, a guess of 77 mm a
    step against the 10 mm a vertex may move before the next search (the thickness), so the bound cuts it and the
    sheet falls slowed (measured at full resolution: 1.20 m/s at 0.15 s against free fall's 1.47). The scene says
    so before the first step and names the steps a frame that fit the guess; at those there is no line, and the
    sheet falls as backward Euler, -g t, to 0.5 % until it meets the sphere."""
    cls = get_scene("drape")
    p = cls.resolve_params({"integrator": "vbd", "resolution": 12})
    speeds = {}
    for steps in (1, None):
        scene = cls(p, device=DEVICE)
        if steps is None:
            steps = int(re.search(r"--substeps (\d+)", line).group(1))
        line = scene.stability_warning(1.0 / 60.0, steps)
        if steps == 1:
            assert line is not None and "slows the fall" in line and "longer than the 10 mm" in line, line
        else:
            assert line is None, line
        mass = scene.sim.model.particle_mass.numpy()
        for _ in range(9):
            scene.advance(1.0 / 60.0, steps)
        speeds[steps] = -float(scene.sim.state.velocities.numpy()[mass > 0, 1].mean())
    free = 9.81 * 9 / 60.0
    (one, _), (more, fitted) = sorted(speeds.items())
    assert more > 4 and fitted == pytest.approx(free, rel=5.0e-3), speeds
    assert speeds[one] < 0.9 * free, speeds


def test_a_changed_friction_reaches_the_descent():
    """The viewer's friction slider on a cloth by VBD (``apply_param``): the contact's friction is recorded again
    at the next step, so a frictionless sheet slides off the sphere farther than a rough one."""
    cls = get_scene("drape")
    ends = []
    for friction in (0.0, 2.0):
        scene = cls(cls.resolve_params({"integrator": "vbd", "resolution": 8, "friction": 0.4}), device=DEVICE)
        scene.advance(1.0 / 60.0, 4)
        scene.apply_param("friction", friction)
        assert scene.vbd_contact.friction == friction
        for _ in range(40):
            scene.advance(1.0 / 60.0, 4)
        x = scene.sim.state.positions.numpy()
        ends.append(float(np.linalg.norm(x[:, [0, 2]], axis=1).mean()))  # how far the sheet spread out
    assert ends[0] > ends[1] + 1e-3


def whole_queries(contact, q):
    """The three queries of ``contact`` run whole (``kernels.vbd_contact.WHOLE``: each item its own traversal,
    nothing staged) into new arrays: [(list, distances, count, smallest distance) per kind], overflow."""
    from warpsim.kernels import vbd_contact as K
    C, (tri_bvh, point_bvh, edge_bvh, body_bvh) = contact.capacity, contact._bvhs
    overflow, out = wp.zeros(6, dtype=int, device=DEVICE), []
    for kind, count, bvh, roots in ((K.VERTEX_QUERY, contact.vertex_count, tri_bvh, contact._roots[0]),
                                    (K.TRIANGLE_QUERY, contact.triangle_count, point_bvh, contact._roots[1]),
                                    (K.EDGE_QUERY, contact.edge_count, edge_bvh, contact._roots[2])):
        lists = [wp.zeros(count * C, dtype=int, device=DEVICE), wp.zeros(count * C, dtype=float, device=DEVICE),
                 wp.zeros(count, dtype=int, device=DEVICE), wp.zeros(count, dtype=float, device=DEVICE)]
        wp.launch(K.query_pairs, count, inputs=[
            wp.ones(1, dtype=int, device=DEVICE), int(kind), int(K.WHOLE), body_bvh.id, contact._roots[3],
            contact._groups[3], bvh.id, roots,
            contact._surface, contact._tri, contact._edges, contact._body, q, contact.thickness, contact.cap,
            int(contact.self_contact), C, *lists, overflow, 0, *lists[:3]], device=DEVICE)
        out.append([a.numpy() for a in lists])
    return out, overflow.numpy()


@pytest.mark.parametrize("capacity", [32, 3])
def test_the_staged_lists_are_the_whole_queries_bit_for_bit(capacity):
    """The search stages the triangles' lists from the vertex query and meets each edge pair once (from the
    edge of the lower body, or the lower edge within a body with self contact), then sorts; lists past their
    capacity are queried whole. Two tori with self contact, dropped onto each other: at every frame each list,
    its distances and smallest distance, and the overflow counters are those of the three queries run whole,
    bit for bit (capacity 3: many lists past it, queried whole)."""
    sim, contact, _ = two_tori(gap=0.004, capacity=capacity)
    listed = over = 0
    for _ in range(12):
        sim.frame(1.0 / 60.0, 4)
        q = sim.state.positions
        contact.search(q)
        whole, overflow = whole_queries(contact, q)
        ours = [(contact._vt, contact._distances[0], contact._vt_count, contact._vt_min),
                (contact._tv, contact._distances[1], contact._tv_count, contact._tv_min),
                (contact._ee, contact._distances[2], contact._ee_count, contact._ee_min)]
        for (lst, dist, count, dmin), (w_lst, w_dist, w_count, w_min) in zip(ours, whole):
            assert np.array_equal(count.numpy(), w_count) and np.array_equal(dmin.numpy(), w_min)
            live = (np.arange(capacity)[None, :] < w_count[:, None]).reshape(-1)
            assert np.array_equal(lst.numpy()[live], w_lst[live]) and np.array_equal(dist.numpy()[live], w_dist[live])
            listed += int(w_count.sum())
        assert np.array_equal(contact._overflow.numpy(), overflow)
        over += int(overflow[:3].sum())
    assert listed > 100 and contact._ee_count.numpy().sum() > 0
    assert (over > 0) == (capacity == 3)


@pytest.mark.parametrize("line_search", [0, 4])
@pytest.mark.parametrize("split", [False, True])
def test_each_colour_commits_the_one_before_it_with_the_same_bits(line_search, split):
    """A sweep is one colour solve a colour (``solve_colour``; ``split``: ``solve_free`` over the particles no contact
    can reach, then ``solve_colour`` over the colour's list of the others; the first launch copies the colour before
    it across the two position buffers; with ``line_search`` then the check, ``check_colour``) and one commit: the same
    bits as solving (and checking) each colour into the second buffer and copying it back before the next colour,
    and both buffers hold the same positions after it."""
    from warpsim.kernels import vbd as K
    sim, _, _ = two_tori(gap=0.004)
    integ, q = sim.integrator, sim.state.positions
    integ.line_search, integ.split = line_search, split
    for _ in range(30):
        integ.step(sim.system, q, sim.state.velocities, sim._time, 1.0 / 240.0)
    start = (q.numpy() + np.random.default_rng(5).normal(0.0, 2.0e-4, q.shape + (3,))).astype(np.float32)
    q.assign(start)  # a sweep from here moves every particle (after a step most sit at their bound)
    integ.q_new.assign(start)
    for launch in integ._sweep:
        launch.launch()
    folded = q.numpy()
    assert np.array_equal(folded, integ.q_new.numpy()) and not np.array_equal(folded, start)
    q.assign(start)
    integ.q_new.assign(start)
    offsets, per_colour = integ.colour_offsets, 1 + int(split) + int(line_search > 0)
    assert len(integ._sweep) == per_colour * integ.colour_count + 1
    if split:  # the pressed tori: some particles listed, most free
        assert 0 < integ._listed_count.numpy().sum() < len(q) / 2
    for c in range(integ.colour_count):
        first, count = integ._sweep[per_colour * c], offsets[c + 1] - offsets[c]
        first.set_param_by_name("previous_count", 0)
        first.set_dim(count)
        for launch in integ._sweep[per_colour * c: per_colour * (c + 1)]:  # (free,) solve (and its check)
            launch.set_param_by_name("q", q)
            launch.set_param_by_name("q_out", integ.q_new)
            launch.launch()
        wp.launch(K.commit_colour, count, inputs=[integ.colour_particles, offsets[c], integ.q_new, q], device=DEVICE)
    assert np.array_equal(q.numpy(), folded)


def test_particles_no_contact_can_reach_solved_apart_give_the_same_bits(monkeypatch):
    """``VBD(split=True)``: after each search the particles that can touch a contact before the next one are listed by
    colour (``kernels.vbd.list_contact_particles``: a kept pair, or a plane within the thickness + 3 bounds of the
    reference) and solved (and checked) by the colour solve; the others by ``solve_free``, a thread each over their
    inertia and springs alone. Two tori dropped on each other and on the floor: the same bits as every particle by the
    colour solve (so no particle left out had a contact force), only part of the particles listed, the listed set a
    superset of those ``may_touch`` reaches at each step's end, and with 4 lanes (the listed ones' sums in lanes, the
    free ones' a thread each) within rounding of the unsplit lanes and the same bits run to run."""
    monkeypatch.setattr(wp.config, "enable_cpu_blocks", True)
    runs, listed = {}, []
    for lanes, split in ((1, False), (1, True), (4, False), (4, True), (4, True)):
        sim, _, _ = two_tori(gap=0.004)
        integ = sim.integrator
        integ.lanes, integ.split = lanes, split
        for _ in range(12):
            sim.frame(1.0 / 60.0, 4)
            if split and lanes == 1:
                flags = integ._listed.numpy()
                listed.append(int(flags.sum()))
                reach = wp.zeros(len(flags), dtype=int, device=DEVICE)
                cc = integ.contact
                wp.launch(touches_kernel, len(flags), inputs=[sim.state.positions, cc._slot, cc._near_end, cc._planes,
                                                               cc._spheres, cc.thickness, integ._bound, reach],
                          device=DEVICE)
                assert not (reach.numpy().astype(bool) & ~flags.astype(bool)).any()
        runs.setdefault((lanes, split), []).append(sim.state.positions.numpy())
    assert np.array_equal(runs[(1, False)][0], runs[(1, True)][0])
    assert 0 < min(listed) and max(listed) < len(flags) / 2, listed
    assert np.array_equal(runs[(4, True)][0], runs[(4, True)][1])
    assert np.abs(runs[(4, True)][0] - runs[(4, False)][0]).max() < 1.0e-5  # [m], tori of 0.1 m


@wp.kernel
def touches_kernel(q: wp.array(dtype=wp.vec3), slot: wp.array(dtype=int), near_end: wp.array(dtype=int),
                   planes: wp.array(dtype=wp.vec4), spheres: wp.array(dtype=wp.vec4), radius: float,
                   bound: wp.array(dtype=float), out: wp.array(dtype=int)):
    """``kernels.vbd.may_touch`` of each particle where it is (1 or 0)."""
    p = wp.tid()
    if may_touch(p, q[p], slot, near_end, planes, spheres, radius, bound[p]):
        out[p] = 1


def test_searches_within_a_step_run_when_a_particle_nears_its_bound():
    """A search (opening a step or within it) runs only when some particle has moved more than
    ``renew_fraction`` of its bound since the last search or has some of its initial guess cut (decided on the
    device, no read-back; the first step's opening search always runs): a torus dropped with its lowest point
    6 cm above the floor skips them while it starts to fall (two searches in the first frame's four steps: its
    caps start at ``min_displacement``) and
    once it rests (none at all), and runs them around the impact (guesses cut by the bound near the floor);
    ``renew_fraction=None`` runs every one (two a step); no vertex goes below the floor, the runs repeat bit for
    bit and the skipping run rests where the searching one does."""
    counts, runs = {}, []
    for fraction in (0.5, None, 0.5):
        b = ws.ModelBuilder()
        _, body = small_torus((0.0, 0.1, 0.0), b)
        model = b.finalize(DEVICE)
        contact = ws.VBDContact(body.faces, thickness=0.006, planes=[((0.0, 1.0, 0.0), 0.0)])
        sim = ws.Simulator(model, integrator=ws.VBD(10, contact=contact, renew_fraction=fraction),
                           forces=[ws.Gravity()])
        per_step = []
        for _ in range(40):
            before = contact.searches_run
            sim.frame(1.0 / 60.0, 4)
            per_step.append((contact.searches_run - before) / 4)
            assert sim.state.positions.numpy()[:, 1].min() > 0.0
        counts[fraction] = per_step
        runs.append(sim.state.positions.numpy())
    assert counts[None] == [2.0] * 40  # 10 sweeps, a search every 5: the step's and one within it
    skipped = counts[0.5]
    assert skipped[0] == 0.5 and max(skipped) >= 1.0 and skipped[-5:] == [0.0] * 5, skipped
    assert np.array_equal(runs[0], runs[2])
    assert np.abs(runs[0] - runs[1]).max() < 1.0e-4  # [m]: the same rest


def test_the_size_check_counts_the_pair_lists():
    """The donut scene's memory estimate (checked before anything is built) counts VBD's pair lists:
    ``VBDContact.list_bytes`` is within 10 % of the bytes VBDContact allocates for the heap (capacity
    32 and the sweeps' 128 entries per vertex: 0.67 MB a torus of 24 x 12, 0.67 GB at 1,000 tori)."""
    cls = get_scene("donuts")
    scene = cls(cls.resolve_params({"count": 3, "integrator": "vbd"}), device=DEVICE)
    contact = scene.vbd_contact
    arrays = [v for v in vars(contact).values() if isinstance(v, wp.array)]
    arrays += [a for v in vars(contact).values() if isinstance(v, list) for a in v if isinstance(a, wp.array)]
    allocated = sum(a.capacity for a in arrays)
    faces = scene.torus.faces
    estimate = 3 * ws.VBDContact.list_bytes(len(np.unique(faces)), len(faces), 3 * len(faces) // 2)
    assert 0.9 < allocated / estimate < 1.1, (allocated, estimate)
