"""Bad input fails early with a ValueError that names the item and the fix."""

import math

import numpy as np
import pytest

import warpsim as ws


def two_particles():
    b = ws.ModelBuilder()
    b.add_particle((0, 0, 0))
    b.add_particle((1, 0, 0))
    return b


@pytest.mark.parametrize("mass,match", [(-1.0, "particle 0 has mass -1.0"), (math.nan, "particle 0 has mass nan")])
def test_bad_mass(mass, match):
    with pytest.raises(ValueError, match=match):
        ws.ModelBuilder().add_particle((0, 0, 0), mass=mass)


def test_non_finite_position_and_velocity():
    b = ws.ModelBuilder()
    b.add_particle((0, 0, 0))
    with pytest.raises(ValueError, match="particle 1 position is not finite"):
        b.add_particle((0, math.inf, 0))
    with pytest.raises(ValueError, match="particle 1 velocity is not finite"):
        b.add_particle((0, 0, 0), vel=(math.nan, 0, 0))
    with pytest.raises(ValueError, match="3 components"):
        b.add_particle((0, 0))


def test_non_finite_state_at_simulator_start():
    model = two_particles().finalize("cpu")
    q = model.particle_q.numpy()
    q[1, 2] = np.nan
    model.particle_q.assign(q)
    with pytest.raises(ValueError, match="particle 1 has a non-finite position"):
        ws.Simulator(model)


def test_bad_springs():
    b = two_particles()
    with pytest.raises(ValueError, match="spring 0 joins particle 1 to itself"):
        b.add_spring(1, 1, 10.0, 0.0)
    with pytest.raises(ValueError, match=r"spring 0: particle j=5 is out of range \[0, 2\)"):
        b.add_spring(0, 5, 10.0, 0.0)
    with pytest.raises(ValueError, match="spring 0 has stiffness -3"):
        b.add_spring(0, 1, -3.0, 0.0)
    with pytest.raises(ValueError, match="rest length"):
        b.add_spring(0, 1, 3.0, 0.0, rest_length=-1.0)
    assert b.add_spring(0, 1, 3.0) == 0 and b.spring_rest_length[0] == pytest.approx(1.0)


def test_bad_dt_and_integrator():
    sim = ws.Simulator(two_particles().finalize("cpu"))
    for dt in (0.0, -0.1, math.nan, math.inf):
        with pytest.raises(ValueError, match="dt must be > 0"):
            sim.step(dt)
    with pytest.raises(ValueError) as info:
        ws.Simulator(two_particles().finalize("cpu"), integrator="verlet")
    message = str(info.value)
    assert "unknown integrator 'verlet'" in message
    for name in ("explicit_euler", "semi_implicit_euler", "implicit_euler", "rk2", "rk4"):
        assert name in message


def test_bad_forces_and_colliders():
    model = two_particles().finalize("cpu")
    with pytest.raises(ValueError, match="particle index 7 is out of range"):
        ws.Simulator(model, forces=[ws.ConstantForce((1, 0, 0), particles=[0, 7])])
    with pytest.raises(ValueError, match=r"forces\[1\] is str"):
        ws.Simulator(model, forces=[ws.Gravity(), "wind"])
    with pytest.raises(ValueError, match="restitution 1.5"):
        ws.Plane(restitution=1.5)
    with pytest.raises(ValueError, match="mode 'bounce'"):
        ws.Plane(mode="bounce")
    with pytest.raises(ValueError, match="non-zero"):
        ws.Plane(normal=(0, 0, 0))
    with pytest.raises(ValueError, match="upper"):
        ws.Box((0, 0, 0), (1, -1, 1))
    with pytest.raises(ValueError, match="softening"):
        ws.Magnets([[0, 0, 0]], [1.0], softening=0.0)
    with pytest.raises(ValueError, match="Drag linear"):
        ws.Drag(linear=-1.0)
    with pytest.raises(ValueError, match="max_displacement"):
        ws.Simulator(model, adaptive=True)
    with pytest.raises(ValueError, match="length <= 0"):
        ws.Pendulum([0.1, 0.2], length=[1.0, 0.0], device="cpu")
