"""Every solver follows ``warpsim.core.solver.Solver`` (``step(dt)``, ``frame(frame_dt, steps)``,
``state``, ``notify_changed(what)``): each is checked with ``isinstance`` and advanced through the
protocol only, with a physical check of what came out (free fall at g t, a sag-free strand at
rest, heat lifting smoke, boids at their cruising speed, walkers nearing their goals)."""

import numpy as np
import pytest

import warpsim as ws
from warpsim.agents import BoidParams, Crowd, Flock
from warpsim.bodies.colliders import Sphere
from warpsim.cloth import ClothSimulator, add_cloth_grid
from warpsim.core.solver import CHANGES, Solver
from warpsim.grid_fluids import FlipLiquid, LevelSetLiquid, MacGrid, Smoke
from warpsim.particle_fluids.pbf import ParticleFluid, fluid_block
from warpsim.strands import StrandImplicitEuler

CPU = "cpu"
G = 9.81


def _falling_particles():
    b = ws.ModelBuilder()
    b.add_particle((0.0, 1.0, 0.0), mass=1.0)
    b.add_particle((1.0, 1.0, 0.0), mass=2.0)
    return ws.Simulator(b.finalize(CPU), forces=[ws.Gravity()], warn_unstable=False)


def _falling_cloth():
    b = ws.ModelBuilder()
    add_cloth_grid(b, (3, 3), (0.2, 0.2), (0.0, 1.0, 0.0), particle_mass=0.01)
    return ClothSimulator(b.finalize(CPU), forces=[ws.Gravity()], warn_unstable=False)


def _sag_free_strand():
    b = ws.ModelBuilder()
    hair = ws.add_strands(b, [(0.0, 1.0, 0.0)], [(1.0, 0.0, 0.0)], 4, length=0.1, mass=1e-3)
    sim = ws.Simulator(b.finalize(CPU), integrator=StrandImplicitEuler(hair),
                       forces=[ws.Gravity(), ws.StrandForce(hair)], colliders=[ws.StrandRoots(hair)],
                       warn_unstable=False, check_every=0)
    ws.sag_free(sim)
    return sim


def _velocities(solver):
    return solver.state.velocities.numpy().astype(np.float64)


def _check_free_fall(solver, t):
    assert np.allclose(_velocities(solver), [0.0, -G * t, 0.0], atol=1e-5 * G * t)


def test_particles_and_cloth_fall_at_g_t_through_the_protocol():
    for make in (_falling_particles, _falling_cloth):
        solver = make()
        assert isinstance(solver, Solver)
        solver.step(0.01)
        _check_free_fall(solver, 0.01)
        solver.frame(0.1, 10)
        _check_free_fall(solver, 0.11)
        solver.notify_changed("parameters")  # the next frame takes the limit again and continues
        solver.frame(0.1, 4)
        _check_free_fall(solver, 0.21)


def test_a_frame_is_its_steps_bit_for_bit():
    a, b = _falling_particles(), _falling_particles()
    a.frame(0.1, 7)
    for _ in range(7):
        b.step(0.1 / 7)
    assert a.state.positions.numpy().tobytes() == b.state.positions.numpy().tobytes()


def test_the_sag_free_strand_stays_at_rest_through_the_protocol():
    sim = _sag_free_strand()
    assert isinstance(sim, Solver)
    x0 = sim.state.positions.numpy().copy()
    sim.step(1.0 / 240.0)
    sim.frame(1.0 / 60.0, 4)
    assert np.abs(sim.state.positions.numpy() - x0).max() < 1e-4  # a sagging strand drops millimetres
    assert np.ptp(x0[:, 0]) > 0.09  # it is still the horizontal strand


@pytest.mark.parametrize("method", ["pbf", "dfsph"])
def test_a_particle_fluid_block_falls_with_its_weight_through_the_protocol(method):
    fluid = ParticleFluid(fluid_block((-0.05, 0.5, -0.05), (0.05, 0.6, 0.05), 0.025), spacing=0.025,
                          domain=((-1.0, 0.0, -1.0), (1.0, 2.0, 1.0)), method=method, device=CPU)
    assert isinstance(fluid, Solver)
    fluid.step(0.004)
    fluid.frame(0.012, 3)
    # internal corrections are pairwise and cancel; nothing touched a wall: momentum gains M g t
    v = _velocities(fluid).mean(axis=0)
    assert v[1] == pytest.approx(-G * 0.016, rel=1e-3)
    assert np.abs(v[[0, 2]]).max() < 1e-5
    assert fluid.frame_count == 1


def test_grid_fluids_through_the_protocol():
    hot = Smoke(MacGrid((8, 12), 0.1, open_sides=("+y",), device=CPU), temperature_buoyancy=1.0)
    hot.add_source((0.3, 0.1), (0.5, 0.3), density=0.0, temperature=1.0)
    still = Smoke(MacGrid((8, 12), 0.1, open_sides=("+y",), device=CPU), temperature_buoyancy=1.0)
    for smoke in (hot, still):
        assert isinstance(smoke, Solver)
        smoke.step(0.01)
        smoke.frame(0.02, 2)
        smoke.notify_changed("parameters")
    assert hot.state.v.numpy().max() > 0.0  # heat lifts
    assert np.abs(still.state.v.numpy()).max() == 0.0  # no heat, no density: nothing moves
    assert hot.time == pytest.approx(0.03)

    def grid():
        return MacGrid((16, 16), 1.0 / 16, device=CPU)

    def blob(x):
        return np.linalg.norm(x[..., :2] - 0.5, axis=-1) - 0.15

    flip = FlipLiquid(grid(), reseed_every=0, density_correction=0.0)
    flip.add_sdf(blob)
    levelset = LevelSetLiquid(grid(), blob)
    for liquid in (flip, levelset):
        assert isinstance(liquid, Solver)
        liquid.step(0.002)
        liquid.frame(0.004, 2)
        v = liquid.state.v.numpy()
        # a free blob falls freely: the fastest face moves at g t (uniform gravity is divergence-free)
        assert -v.min() == pytest.approx(G * 0.006, rel=1e-3)


def test_agents_through_the_protocol():
    rng = np.random.default_rng(3)
    x = rng.uniform(0.0, 10.0, (40, 3))
    v = rng.normal(0.0, 1.0, (40, 3))
    flock = Flock(x, v, params=BoidParams(max_speed=2.0, min_speed=2.0, max_force=4.0, perception_radius=3.0),
                  bounds=((0, 0, 0), (10, 10, 10)), wrap=True, device=CPU)
    crowd = Crowd(np.array([[0.0, 0.0, 0.0], [3.0, 0.0, 0.0]]), np.array([[8.0, 0.0, 0.0], [3.0, 0.0, 8.0]]),
                  terrain=ws.Terrain.flat(0.0), device=CPU)
    before = crowd.distance_to_goals()
    for agents in (flock, crowd):
        assert isinstance(agents, Solver)
        agents.step(0.05)
        agents.frame(0.5, 10)
        agents.notify_changed("parameters")
    assert np.allclose(np.linalg.norm(flock.velocities.numpy(), axis=1), 2.0, rtol=1e-4)  # cruising speed
    assert (crowd.distance_to_goals() < before - 0.1).all()


@pytest.mark.parametrize("what", ["velocity", "", None, 3])
def test_notify_changed_names_what_it_accepts(what):
    for solver in (_falling_particles(), Flock(np.zeros((1, 3)), device=CPU)):
        with pytest.raises(ValueError, match="notify_changed") as err:
            solver.notify_changed(what)
        assert all(c in str(err.value) for c in CHANGES)


def test_frame_checks_its_arguments():
    sim = _falling_particles()
    with pytest.raises(ValueError, match="frame_dt"):
        sim.frame(0.0, 1)
    with pytest.raises(ValueError, match="steps"):
        sim.frame(0.1, 0)


def test_adding_a_force_reallocates_through_notify_changed():
    sim = _falling_particles()
    buffers = sim.integrator.f
    sim.add_force(ws.ConstantForce((0.0, G, 0.0)))  # cancels gravity on particle 0 (1 kg)
    assert sim.integrator.f is not buffers
    sim.step(0.1)
    v = _velocities(sim)
    assert np.allclose(v[0], 0.0, atol=1e-6) and v[1, 1] == pytest.approx(-G * 0.1 / 2.0, rel=1e-6)


def test_a_collider_clock_set_places_a_moving_shape_at_its_pose():
    sphere = Sphere((0.0, 0.0, 0.0), 0.1, motion=lambda t: ((0.0, 2.0 * t, 0.0), None))
    sphere.set_clock(0.75)
    assert sphere.clock == 0.75 and sphere.time == 0.75
    assert np.allclose(sphere.world_pose()[0], [0.0, 1.5, 0.0])
    sphere.clock = 0.25
    assert np.allclose(sphere.world_pose()[0], [0.0, 0.5, 0.0])
    with pytest.raises(ValueError, match="clock"):
        sphere.set_clock(float("nan"))
    before, after = sphere.advance_pose(0.25)  # what a step of apply does to the pose and clock
    assert sphere.clock == 0.5 and np.allclose(before.p, [0.0, 0.5, 0.0]) and np.allclose(after.p, [0.0, 1.0, 0.0])


def test_a_restored_teapot_paddle_continues_bit_for_bit():
    """The scene restores the moving paddle's clock through ``set_clock`` (no private edits)."""
    from warpsim.scenes import get_scene

    cls = get_scene("teapot")
    params = {"resolution": "3", "obstacle": "paddle"}
    full, part = cls(params, device=CPU), cls(params, device=CPU)
    for _ in range(3):
        full.advance(1.0 / 60.0, 2)
        part.advance(1.0 / 60.0, 2)
    saved = part.checkpoint()
    resumed = cls(params, device=CPU)
    resumed.restore(saved)
    assert resumed.obstacle.clock == full.obstacle.clock > 0.0
    for _ in range(2):
        full.advance(1.0 / 60.0, 2)
        resumed.advance(1.0 / 60.0, 2)
    assert np.array_equal(np.concatenate(resumed.obstacle.world_pose()), np.concatenate(full.obstacle.world_pose()))
    assert resumed.sim.state.positions.numpy().tobytes() == full.sim.state.positions.numpy().tobytes()


def test_a_pendulum_lengthened_in_place_swings_at_its_new_period():
    amplitude = 0.3
    pendulum = ws.Pendulum([amplitude, amplitude], length=[1.0, 1.0], integrator="rk4", device=CPU)
    assert isinstance(pendulum, Solver)
    pendulum.length.assign(np.array([1.0, 4.0], np.float32))
    pendulum.notify_changed("parameters")  # without it the second one keeps g / 1 m
    periods = [ws.exact_period(amplitude, length) for length in (1.0, 4.0)]
    pendulum.frame(periods[1] / 2.0, 150)
    angle = pendulum.state.angle.numpy()
    assert angle[1] == pytest.approx(-amplitude, abs=1e-4)  # half its period: at the far side
    assert angle[0] == pytest.approx(amplitude, abs=1e-4)  # T(1 m) = T(4 m) / 2: back where it started


def test_a_pendulum_restored_from_its_checkpoint_continues_bit_for_bit():
    full, part = (ws.Pendulum([0.3, 1.0], integrator="rk4", device=CPU) for _ in range(2))
    for p in (full, part):
        p.frame(0.1, 10)
    resumed = ws.Pendulum([0.0, 0.0], integrator="rk4", device=CPU)
    resumed.restore(part.checkpoint())
    for p in (full, resumed):
        p.frame(0.1, 10)
    assert resumed.angle.numpy().tobytes() == full.angle.numpy().tobytes() and resumed.time == full.time
    with pytest.raises(ValueError, match="angle has 2 values for 1"):
        ws.Pendulum([0.0], device=CPU).restore(part.checkpoint())


def test_the_hair_frame_follows_the_protocol():
    """The hair scene's frame driver (``HairFrame``): a frame through the protocol equals the
    scene's own frame bit for bit, with the head turning."""
    from warpsim.scenes import get_scene

    params = {"strands": 4, "segments": 6, "still": 0.0, "motion": "turn", "sag_free": False}
    a, b = (get_scene("hair")(params, device=CPU) for _ in range(2))
    assert isinstance(a.frame, Solver)
    n = a.frame_steps(1.0 / 60.0, 1)
    for _ in range(3):
        a.frame.frame(1.0 / 60.0, n)
        b.advance(1.0 / 60.0, 1)
    a.frame.notify_changed("parameters")
    a.frame.frame(1.0 / 60.0, n)
    b.advance(1.0 / 60.0, 1)
    assert a.frame.state.positions.numpy().tobytes() == b.sim.state.positions.numpy().tobytes()
    assert np.array_equal(np.concatenate(a.head.world_pose()), np.concatenate(b.head.world_pose()))
    assert a.sim.step_count == 4 * n
