"""Plane collisions after integration: reflection h' = r h, v_n' = -r v_n, Coulomb friction that
never reverses the tangential velocity, position correction, arbitrary normals, boxes of walls."""

import numpy as np
import pytest

import warpsim as ws


def one_particle(device, pos, vel, plane, radius=0.0):
    b = ws.ModelBuilder()
    b.add_particle(pos, vel, mass=1.0, radius=radius)
    return ws.Simulator(b.finalize(device), integrator="explicit_euler", forces=[], colliders=[plane])


@pytest.mark.parametrize("mode", ["reflect", "project"])
def test_reflection_and_position_correction(device, mode):
    r, dt = 0.6, 0.1
    sim = one_particle(device, (0, 0.05, 0), (0, -1.0, 0), ws.Plane(restitution=r, mode=mode))
    sim.step(dt)  # free flight would end at y = -0.05: penetration h = 0.05
    y = sim.state.positions.numpy()[0][1]
    assert y == pytest.approx(r * 0.05 if mode == "reflect" else 0.0, abs=1e-7)
    assert sim.state.velocities.numpy()[0] == pytest.approx([0, r * 1.0, 0], abs=1e-7)


def test_radius_offsets_the_contact(device):
    sim = one_particle(device, (0, 0.15, 0), (0, -1.0, 0), ws.Plane(restitution=0.0, mode="project"), radius=0.1)
    sim.step(0.1)
    assert sim.state.positions.numpy()[0][1] == pytest.approx(0.1, abs=1e-7)


def test_coulomb_friction_reduces_and_never_reverses(device):
    r, mu = 0.5, 0.2
    sim = one_particle(device, (0, 0.05, 0), (2.0, -1.0, 0), ws.Plane(restitution=r, friction=mu))
    sim.step(0.1)
    v = sim.state.velocities.numpy()[0]
    assert v[0] == pytest.approx(2.0 - mu * (1 + r) * 1.0, abs=1e-6)  # |dv_t| = mu |dv_n|
    assert v[1] == pytest.approx(r, abs=1e-6)
    sticky = one_particle(device, (0, 0.05, 0), (0.3, -1.0, 0.4), ws.Plane(restitution=r, friction=10.0))
    sticky.step(0.1)
    v = sticky.state.velocities.numpy()[0]
    assert v[0] == 0.0 and v[2] == 0.0  # stopped, not reversed
    assert v[1] == pytest.approx(r, abs=1e-6)


def test_sliding_block_stops_where_coulomb_says(device):
    """A particle resting on the floor under gravity and sliding at v0 stops after
    v0^2 / (2 mu g) metres (friction impulse mu (1 + r) |v_n| per step with r = 0 is mu g dt)."""
    mu, g, v0, dt = 0.4, 9.81, 2.0, 1e-3
    b = ws.ModelBuilder()
    b.add_particle((0, 0, 0), (v0, 0, 0), mass=1.0)
    sim = ws.Simulator(b.finalize(device), forces=[ws.Gravity((0, -g, 0))],
                       colliders=[ws.Plane(restitution=0.0, friction=mu, mode="project")])
    for _ in range(int(1.2 * v0 / (mu * g) / dt)):
        sim.step(dt)
    x, v = sim.state.positions.numpy()[0], sim.state.velocities.numpy()[0]
    assert v[0] == 0.0
    assert x[0] == pytest.approx(v0 ** 2 / (2 * mu * g), rel=0.01)
    assert x[1] == pytest.approx(0.0, abs=1e-6)


def test_tilted_plane(device):
    n = np.array([1.0, 2.0, -0.5])
    n /= np.linalg.norm(n)
    offset = 0.3
    x0 = offset * n + 0.02 * n
    v0 = -3.0 * n + np.array([0.0, 0.0, 0.0])
    sim = one_particle(device, x0, v0, ws.Plane(n * 7.0, offset, restitution=0.5))  # unnormalised on purpose
    sim.step(0.02)  # free flight ends 0.04 below the surface
    x, v = sim.state.positions.numpy()[0], sim.state.velocities.numpy()[0]
    assert np.dot(n, x) - offset == pytest.approx(0.5 * 0.04, abs=1e-6)
    assert v == pytest.approx(1.5 * n, abs=1e-5)


def test_box_of_walls_keeps_particles_inside(device):
    rng = np.random.default_rng(1)
    b = ws.ModelBuilder()
    for _ in range(64):
        b.add_particle(rng.uniform(-0.9, 0.9, 3) + (0, 1, 0), rng.normal(0, 8.0, 3), mass=1.0, radius=0.02)
    box = ws.Box((-1, 0, -1), (1, 2, 1), restitution=0.9)
    sim = ws.Simulator(b.finalize(device), forces=[ws.Gravity()], colliders=[box])
    mass_energy = []
    for _ in range(200):
        sim.step(1e-3)
        x = sim.state.positions.numpy()
        assert np.all(x >= np.array([-1, 0, -1]) + 0.02 - 1e-5) and np.all(x <= np.array([1, 2, 1]) - 0.02 + 1e-5)
        v = sim.state.velocities.numpy()
        mass_energy.append(0.5 * (v * v).sum() + 9.81 * x[:, 1].sum())
    assert mass_energy[-1] < mass_energy[0]  # restitution < 1 only removes energy


def test_pinned_particles_ignore_colliders(device):
    b = ws.ModelBuilder()
    b.add_particle((0, -0.5, 0), mass=0.0)
    sim = ws.Simulator(b.finalize(device), colliders=[ws.Plane()])
    sim.step(0.01)
    assert sim.state.positions.numpy()[0][1] == pytest.approx(-0.5)
