"""FastMassSpring (``warpsim.core.fast_mass_spring``): backward Euler for copies of one spring body
by local-global iterations with one dense inverse (Liu et al. 2013).

Checked against ImplicitEuler's Newton solution (the same backward Euler step), the method's
descent property (each iteration lowers the step's incremental potential), energy, copies and
input errors; in the donuts scene, the heap at 1/240 s."""

import numpy as np
import pytest
from test_soft_contact_scale import deepest_vertex, edges_through_other_bodies

import warpsim as ws
from warpsim.core.stability import StabilityWarning
from warpsim.scenes import get_scene

UNCONVERGED = pytest.mark.filterwarnings("ignore:FastMassSpring:warpsim.core.stability.StabilityWarning")
"""Tests that run too few iterations on purpose (the warning itself is tested below)."""

DEVICE = "cpu"


def torus_model(copies=1, damping=0.0, stiffness=150.0, spacing=0.3):
    """``copies`` soft tori (10 x 6, lattice 4: 68 particles, 608 springs each) side by side."""
    points, faces = ws.torus_mesh(0.1, 0.04, 10, 6)
    b = ws.ModelBuilder()
    for t in range(copies):
        ws.add_soft_body(b, points + np.array([spacing * t, 0.5, 0.0]), faces, total_mass=1.0, stiffness=stiffness,
                         damping=damping, lattice_cells=4)
    return b.finalize(DEVICE)


def kick(model, copies=1, seed=0, scale=0.5):
    v = np.random.default_rng(seed).normal(size=(model.particle_count // copies, 3)) * scale
    return np.tile(v, (copies, 1)).astype(np.float32)


def run(integrator, steps, h, copies=1, gravity=9.81, damping=0.0, stiffness=150.0):
    model = torus_model(copies, damping, stiffness)
    sim = ws.Simulator(model, integrator=integrator, forces=[ws.Gravity((0.0, -gravity, 0.0))])
    sim.state.velocities.assign(kick(model, copies))
    for _ in range(steps):
        sim.step(h)
    return sim


def incremental_potential(x, y, mass, springs, rest, k, h):
    """g(x) = |x - y|_M^2 / (2 h^2) + sum k/2 (|x_i - x_j| - L)^2 (undamped springs) [J]."""
    x = x.astype(np.float64)
    stretch = np.linalg.norm(x[springs[:, 0]] - x[springs[:, 1]], axis=1) - rest
    return 0.5 * (mass[:, None] * (x - y) ** 2).sum() / h**2 + 0.5 * (k * stretch**2).sum()


@UNCONVERGED
def test_converged_iterations_are_backward_euler():
    """300 iterations a step give ImplicitEuler's Newton solution (tolerances 1e-9 / 1e-10) to
    within float rounding over 3 large steps (1/60 s, h^2 k / m = 2.6 a spring, random velocities
    of 0.5 m/s); 10 iterations are within 1 cm of it (the method's slow convergence at this step)."""
    h = 1.0 / 60.0
    newton = run(ws.ImplicitEuler(newton_iterations=30, newton_tol=1e-9, cg_tol=1e-10, cg_max_iterations=2000), 3, h)
    x_ref, v_ref = newton.state.positions.numpy(), newton.state.velocities.numpy()
    moved = np.abs(x_ref - newton.model.particle_q.numpy()).max()
    fast = run(ws.FastMassSpring(iterations=300), 3, h)
    assert moved > 0.02  # the tori moved and deformed ...
    assert np.abs(fast.state.positions.numpy() - x_ref).max() < 2e-6  # ... to the same backward Euler positions
    assert np.abs(fast.state.velocities.numpy() - v_ref).max() < 2e-4  # [m/s], divided by h
    few = run(ws.FastMassSpring(iterations=10), 3, h)
    assert 1e-4 < np.abs(few.state.positions.numpy() - x_ref).max() < 0.01
    # Chebyshev acceleration: the same fixed point, reached sooner (measured 40 iterations: 3e-6 m from
    # Newton against 0.7 mm plain; 10: 0.8 mm against 5.2 mm)
    accelerated = {n: np.abs(run(ws.FastMassSpring(iterations=n, chebyshev=True), 3, h).state.positions.numpy()
                             - x_ref).max() for n in (10, 40)}
    assert accelerated[40] < 2e-5
    assert accelerated[10] < 0.3 * np.abs(few.state.positions.numpy() - x_ref).max()


@UNCONVERGED
def test_every_iteration_lowers_the_incremental_potential():
    """One step at 1/60 s from a kicked torus, stopped after 1, 2, ..., 12 iterations: the step's
    incremental potential (with the true spring energy) never rises, and each iterate is below the
    inertial prediction y (the first iterate)."""
    h, values = 1.0 / 60.0, []
    model = torus_model()
    springs = model.spring_indices.numpy().reshape(-1, 2)
    rest, k, mass = (a.numpy().astype(np.float64) for a in (model.spring_rest_length, model.spring_stiffness,
                                                             model.particle_mass))
    x0 = model.particle_q.numpy().astype(np.float64)
    v0 = kick(model).astype(np.float64)
    y = x0 + h * v0 + h * h * np.array([0.0, -9.81, 0.0])
    for iterations in range(1, 13):
        sim = ws.Simulator(torus_model(), integrator=ws.FastMassSpring(iterations=iterations),
                           forces=[ws.Gravity((0.0, -9.81, 0.0))])
        sim.state.velocities.assign(v0.astype(np.float32))
        sim.step(h)
        values.append(incremental_potential(sim.state.positions.numpy(), y, mass, springs, rest, k, h))
    start = incremental_potential(y, y, mass, springs, rest, k, h)
    assert values[0] < start
    assert all(b <= a * (1 + 1e-6) for a, b in zip(values, values[1:])), values
    assert values[-1] < 0.9 * values[0]  # and it keeps falling


def free_torus_energies(stiffness, iterations, h=1.0 / 60.0, seconds=2.0, chebyshev=False):
    """Kinetic + spring energy [J] of a kicked, undamped torus without gravity, every step."""
    model = torus_model(stiffness=stiffness)
    sim = ws.Simulator(model, integrator=ws.FastMassSpring(iterations=iterations, chebyshev=chebyshev), forces=[])
    sim.state.velocities.assign(kick(model))
    springs = model.spring_indices.numpy().reshape(-1, 2)
    rest, k, mass = (a.numpy().astype(np.float64) for a in (model.spring_rest_length, model.spring_stiffness,
                                                             model.particle_mass))

    def energy():
        x, v = (a.numpy().astype(np.float64) for a in (sim.state.positions, sim.state.velocities))
        stretch = np.linalg.norm(x[springs[:, 0]] - x[springs[:, 1]], axis=1) - rest
        return 0.5 * (mass[:, None] * v * v).sum() + 0.5 * (k * stretch**2).sum()

    energies = [energy()]
    for _ in range(round(seconds / h)):
        sim.step(h)
        energies.append(energy())
    assert np.isfinite(sim.state.positions.numpy()).all()
    return np.array(energies)


@UNCONVERGED
def test_energy_at_large_steps():
    """A kicked, undamped torus without gravity at 1/60 s for 2 s (h^2 k / m = 2.8 a spring): with
    50 iterations a step the energy never rises (backward Euler dissipates); with the default 10,
    far from converged, it may rise by under 1 % in a step (measured 0.8 % once) and falls to 6 %.
    At 1e5 N/m (h^2 k / m = 1,900; semi-implicit Euler's limit is about 0.8 ms) the step stays stable
    and the energy ends below its start, but the unconverged iterations do not keep it falling
    (measured: 134x the start energy after the first step with 10 iterations; RESULTS.md). Chebyshev-
    accelerated, 10 iterations at 150 N/m never gain energy; at 1e5 N/m they diverge (1.2e6 J, not run
    here): the warning before the first step says so (``test_too_few_iterations_are_flagged...``)."""
    converged = free_torus_energies(150.0, 50)
    assert converged[0] > 0.1 and (np.diff(converged) <= 0.0).all()
    accelerated = free_torus_energies(150.0, 10, chebyshev=True)  # 10 accelerated iterations: no rise either
    assert (np.diff(accelerated) <= 0.0).all()
    default = free_torus_energies(150.0, 10)
    assert (np.diff(default) / default[:-1]).max() < 0.01 and default[-1] < 0.1 * default[0]
    stiff = free_torus_energies(1.0e5, 10)
    assert stiff[-1] < stiff[0]


@UNCONVERGED
def test_a_copy_among_many_steps_as_if_alone():
    """Three copies of a torus (one inverse, one matrix product for all): copy 0 has the lone
    torus's bits, copy 2 its motion shifted by its offset; two runs give the same bits."""
    P = torus_model().particle_count
    alone = run(ws.FastMassSpring(), 5, 1.0 / 120.0).state.positions.numpy()
    batches = [run(ws.FastMassSpring(body_size=P), 5, 1.0 / 120.0, copies=3).state.positions.numpy() for _ in range(2)]
    assert np.array_equal(batches[0], batches[1])
    assert np.array_equal(batches[0][:P], alone)
    assert np.abs(batches[0][2 * P:] - (alone + np.array([0.6, 0.0, 0.0], np.float32))).max() < 1e-6


def test_bad_models_are_refused_before_the_first_step():
    P = torus_model().particle_count
    model = torus_model(copies=2)
    k = model.spring_stiffness.numpy()
    k[-1] *= 2.0
    model.spring_stiffness.assign(k)
    with pytest.raises(ValueError, match="copy 1 .*stiffnesses"):
        ws.Simulator(model, integrator=ws.FastMassSpring(body_size=P)).step(0.01)
    with pytest.raises(ValueError, match="body_size = 50 does not divide"):
        ws.Simulator(torus_model(), integrator=ws.FastMassSpring(body_size=50)).step(0.01)
    model = torus_model()
    inv = model.particle_inv_mass.numpy()
    inv[3] = 0.0
    model.particle_inv_mass.assign(inv)
    with pytest.raises(ValueError, match="particle 3 is pinned"):
        ws.Simulator(model, integrator=ws.FastMassSpring()).step(0.01)
    with pytest.raises(ValueError, match="iterations"):
        ws.FastMassSpring(iterations=0)


def test_the_scene_heap_at_1_240_s_keeps_vertices_and_edges_out():
    """The donuts scene's 12 tori with ``integrator=fast_mass_spring`` at 1/240 s (4 steps a frame, the
    scene's 12 Chebyshev-accelerated iterations a step, edge pairs without speculative reach; contact
    pushes and the proximal pull inside the iterations, 16
    contact passes after each step): over 45 frames no vertex goes deeper than the thickness into
    another torus and no edge passes through another torus's triangles (checked every 5 frames), no
    vertex is thrown faster than the tori fall, and the tori come to rest on one another. With 10
    iterations 4-10 edges crossed at frames 24, 39 and 44 (benchmarks/RESULTS.md)."""
    cls = get_scene("donuts")
    params = cls.resolve_params({"count": 12, "integrator": "fast_mass_spring", "dt": 1.0 / 240.0})
    scene = cls(params, device=DEVICE)
    worst, most, fastest = 0.0, 0, 0.0
    for frame in range(45):
        scene.advance(1.0 / 60.0, 4)
        most = max(most, scene.contact.contact_count)
        fastest = max(fastest, float(np.linalg.norm(scene.sim.state.velocities.numpy(), axis=1).max()))
        if frame % 5 == 4:
            x = scene.sim.state.positions.numpy()
            worst = max(worst, deepest_vertex(x, scene.bodies))
            assert edges_through_other_bodies(x, scene.bodies) == [], frame
    assert most > 500  # a heap in contact ...
    assert worst <= params["thickness"], worst  # ... with no vertex deeper than the thickness
    # no vertex thrown faster than the tori fall (3.7 m/s): when each contact's impulse was scaled by
    # the pairs within the thickness only, a vertex in 20 speculative pairs got 20 impulses (26 m/s)
    assert fastest < 5.0, fastest
    assert scene.kinetic_energy() < 1.5  # settling (27 J at the first impacts)
    x = scene.sim.state.positions.numpy()
    assert max(x[b.surface_indices, 1].mean() for b in scene.bodies) > 0.1  # tori lie on tori (not squashed flat)


@pytest.mark.parametrize("tile", [32, 64])
def test_tiled_global_step_is_the_matrix_product(tile):
    """The global step's tiled product X = B A^-1 for shapes that are not tile multiples (the
    edges read zeros, the store stays inside): NumPy's product to float rounding."""
    import warp as wp

    from warpsim.kernels import fast_mass_spring as K

    rng = np.random.default_rng(tile)
    B, A = rng.normal(size=(39, 70)).astype(np.float32), rng.normal(size=(70, 70)).astype(np.float32)
    X = wp.full((39, 70), 7.0, dtype=float, device=DEVICE)
    wp.launch_tiled(K.GLOBAL_SOLVE[tile], dim=((39 + tile - 1) // tile, (70 + tile - 1) // tile),
                    inputs=[wp.array(B, device=DEVICE), wp.array(A, device=DEVICE), X], block_dim=K.TILE_THREADS,
                    device=DEVICE)
    assert np.abs(X.numpy() - B.astype(np.float64) @ A).max() < 1e-4


def test_the_tutorial_command_runs(tmp_path):
    """docs/tutorials/bodies.rst: ``warpsim run donuts --set integrator=fast_mass_spring --fps 60
    --substeps 4`` (2 frames here) steps at 1/240 s and writes its USD."""
    import io

    from pxr import Usd

    from warpsim.cli import main

    out, err = io.StringIO(), io.StringIO()
    usd = tmp_path / "d.usda"
    code = main(["run", "donuts", "--frames", "2", "--set", "integrator=fast_mass_spring", "--fps", "60",
                 "--substeps", "4", "--out", str(usd)], out=out, err=err)
    assert code == 0, err.getvalue()
    stage = Usd.Stage.Open(str(usd))
    assert stage.GetEndTimeCode() - stage.GetStartTimeCode() == 2


def test_batched_worlds_step_as_the_scene_alone():
    """Two identical worlds of the donuts scene with ``integrator=fast_mass_spring`` in one batch (one
    inverse for all four tori; each world's tiled SoftContact pushed inside the iterations) give the
    positions of the scene run alone, bit for bit, while the tori touch. (Before the batch handed the
    integrator its tiled contacts, the pushes went to the single world's idle contact.)"""
    from warpsim.worlds.batch import WorldBatch

    cls = get_scene("donuts")
    params = {"count": 2, "segments": 10, "sides": 6, "lattice_cells": 5, "box": 0.16,
              "integrator": "fast_mass_spring", "dt": 1.0 / 240.0}
    batch = WorldBatch(cls, [params, params], device=DEVICE)
    alone = cls(cls.resolve_params(params), device=DEVICE)
    contact = next(c for c in batch.sim.colliders if isinstance(c, ws.SoftContact))
    assert batch.sim.integrator.contacts == [contact]
    touched = 0
    for _ in range(30):
        batch.advance(1.0 / 60.0, 4)
        alone.advance(1.0 / 60.0, 4)
        touched = max(touched, alone.contact.contact_count)
    x, _ = batch.world_slices()
    assert touched > 10
    assert np.array_equal(x[0], x[1]) and np.array_equal(x[0], alone.sim.state.positions.numpy())


def test_contraction_of_one_spring_is_analytic():
    """Two 1 kg particles on a 100 N/m spring at h = 0.1 s: the local step leaves the transverse
    stiffness 2k of the relative mode to the next iteration, so one iteration shrinks the error by
    rho = 2 h^2 k / (m + 2 h^2 k) = 2/3."""
    b = ws.ModelBuilder()
    b.add_particle((0.0, 0.0, 0.0), mass=1.0)
    b.add_particle((1.0, 0.0, 0.0), mass=1.0)
    b.add_spring(0, 1, 100.0, 0.0)
    integrator = ws.FastMassSpring()
    sim = ws.Simulator(b.finalize(DEVICE), integrator=integrator, forces=[])
    integrator.prepare(sim.system)
    assert integrator.contraction(0.1) == pytest.approx(2.0 / 3.0, rel=1e-9)
    assert integrator.contraction(0.01) == pytest.approx(2.0 / 102.0, rel=1e-9)


def test_too_few_iterations_are_flagged_before_the_first_step():
    """The scene's heap at 1/240 s: 10 iterations leave 0.40 of a step's error (the heap lets edges
    through), 20 leave 0.16 (it holds), 6 Chebyshev-accelerated ones 1 / T_6(1 / rho) = 0.14 (it held):
    a StabilityWarning with the count that would do comes before the first step with 10, none
    with the others. A stiff torus (1e5 N/m at 1/60 s), where accelerated iterations diverge, warns."""
    import warnings

    cls = get_scene("donuts")
    for iterations, chebyshev, warned in ((10, False, True), (20, False, False), (6, True, False)):
        params = cls.resolve_params({"count": 12, "integrator": "fast_mass_spring", "dt": 1.0 / 240.0,
                                     "solver_iterations": iterations, "solver_chebyshev": chebyshev})
        scene = cls(params, device=DEVICE)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            scene.sim.step(1.0 / 240.0)
        messages = [str(w.message) for w in caught if issubclass(w.category, StabilityWarning)]
        assert bool(messages) == warned, messages
        if warned:
            assert "10 iterations a step leave 0.4" in messages[0] and "takes 18" in messages[0]
    with pytest.warns(StabilityWarning, match="10 iterations a step leave 0.9"):
        ws.Simulator(torus_model(stiffness=1.0e5), integrator=ws.FastMassSpring(chebyshev=True), forces=[]).step(1.0 / 60.0)


@UNCONVERGED
def test_a_blow_up_from_too_few_iterations_names_them_not_the_colliders():
    """A kicked stiff torus (1e5 N/m at 1/60 s) with 10 Chebyshev-accelerated iterations diverges inside the
    springs' stability limit of FastMassSpring (it has none: the springs are implicit): the energy balance stops it
    and the message names the iterations, with their remedy, instead of "the energy came from elsewhere ... a
    smaller step will not help" (what it said before, wrongly: a smaller step is one of the remedies)."""
    model = torus_model(stiffness=1.0e5)
    sim = ws.Simulator(model, integrator=ws.FastMassSpring(chebyshev=True), forces=[])
    sim.state.velocities.assign(kick(model))
    with pytest.raises(ws.SimulationError) as error:
        for _ in range(120):
            sim.frame(1.0 / 60.0)
    message = str(error.value)
    assert "10 iterations a step leave 0.9" in message and "Remedy: more iterations" in message, message
    assert "will not help" not in message and "a smaller step" in message


@UNCONVERGED
def test_donuts_say_before_the_first_step_when_a_fall_outruns_the_contact():
    """With the SoftContact inside the solve (fast mass-spring, implicit Euler) a pair is listed before the step
    within the thickness + contact_reach (18 mm); a torus falling from 0.81 m meets the heap at 4.0 m/s, 67 mm in a
    step of 1/60 s, so pairs close and cross unseen. The scene says so before the first step, naming the steps a
    frame that keep a step's fall within 18 mm (4), and at those there is no line. The line is true: stepped at
    1/60 s by fast mass-spring the heap ends (after 1 s) with tori through each other (measured: 20 pairs of tori),
    at 4 steps a frame with none (some cross for a while and come apart, frames 20-35)."""
    from test_soft_contact_scale import edges_through_other_bodies

    cls = get_scene("donuts")
    small = {"count": 12, "segments": 10, "sides": 6, "lattice_cells": 5, "solver_chebyshev": True,
             "solver_iterations": 12}
    implicit = cls(cls.resolve_params({**small, "integrator": "implicit_euler"}), device=DEVICE)
    assert "--substeps 4" in implicit.stability_warning(1.0 / 60.0, 1)
    entangled = {}
    for substeps in (1, 4):
        scene = cls(cls.resolve_params({**small, "integrator": "fast_mass_spring"}), device=DEVICE)
        line = scene.stability_warning(1.0 / 60.0, substeps)
        if substeps == 1:
            assert "meets the heap at 3.99 m/s, 66.6 mm in a step of 0.0167 s" in line, line
            assert "--substeps 4 at least, or integrator=vbd" in line, line
        else:
            assert line is None, line
        for _ in range(60):
            scene.advance(1.0 / 60.0, substeps)
        entangled[substeps] = len(edges_through_other_bodies(scene.sim.state.positions.numpy(), scene.bodies))
    assert entangled[1] >= 10 and entangled[4] == 0, entangled


def test_a_drag_spring_gets_the_explicit_limit():
    """FastMassSpring takes forces other than the springs at the step's start, so a particle held by
    a stiff drag spring (k = 1e4 N/m on m = 1/68 kg, undamped) is a semi-implicit Euler oscillator:
    stable for dt <= 2 / omega, omega = sqrt(k / m). The stability check says so (under implicit
    Euler, which solves the drag spring too, it stays unlimited), and a step above the limit gains
    energy without bound while one below it does not (the target 1 mm from the particle)."""
    model = torus_model()
    target = tuple(float(c) for c in model.particle_q.numpy()[0] + np.array([0.0, 1.0e-3, 0.0]))
    m = float(model.particle_mass.numpy()[0])
    omega = np.sqrt(1.0e4 / m)

    def sim_with(integrator):
        drag = ws.DragSpring(stiffness=1.0e4, damping=0.0, particle=0, target=target)
        return ws.Simulator(torus_model(), integrator=integrator, forces=[drag])

    limit = sim_with(ws.FastMassSpring(iterations=30)).stability()
    assert limit.limiting == "particle" and limit.particle == 0
    assert limit.dt == pytest.approx(2.0 / omega, rel=1e-6)
    assert np.isinf(sim_with(ws.ImplicitEuler()).stability().dt)

    def peak_speed(dt, steps=200):
        sim = sim_with(ws.FastMassSpring(iterations=30))
        sim.check_every = 0
        peak = 0.0
        for _ in range(steps):
            sim.step(dt)
            peak = max(peak, float(np.linalg.norm(sim.state.velocities.numpy(), axis=1).max()))
        return peak

    # omega x 1 mm = 0.77 m/s; semi-implicit Euler near its limit swings the speed up to 1 / sqrt(1 - (h omega / 2)^2)
    assert peak_speed(0.8 * limit.dt) < 0.77 / 0.6 * 1.2
    assert not peak_speed(1.3 * limit.dt) < 1.0e3
