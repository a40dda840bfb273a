"""Contact inside the implicit cloth solve (``warpsim.cloth.contact``, ``kernels/cloth_contact.py``):
the filtered step solves the constrained backward Euler equations (dense NumPy check), Coulomb
friction on an incline (sticks for mu > tan(theta), slides with a = g (sin - mu cos) otherwise),
release when the contact pulls, and the energy of the cloth scene at its full length: no energy
from nowhere where the former projection after the step made 0.3x of the run's scale."""

import numpy as np
import pytest
import warp as wp

import warpsim as ws
from warpsim.cloth.builder import add_cloth_grid
from warpsim.cloth.solver import ClothImplicitEuler, ClothSimulator
from warpsim.scenes import get_scene

DEVICE = "cpu"


def _resting_sheet(resolution=4, height=0.0, friction=0.0):
    b = ws.ModelBuilder()
    add_cloth_grid(b, resolution, 0.4, (-0.2, height, -0.2), u_axis=(1, 0, 0), v_axis=(0, 0, 1), density=0.3,
                   structural=(400.0, 0.02), shear=(100.0, 0.02), bend=(20.0, 0.005), radius=0.0)
    model = b.finalize(DEVICE)
    floor = ws.Plane((0.0, 1.0, 0.0), 0.0, restitution=0.0, friction=friction, mode="project")
    return model, floor


def _dense(A):
    off, col, val = A.offsets.numpy(), A.columns.numpy(), A.values.numpy()
    n = len(off) - 1
    D = np.zeros((3 * n, 3 * n))
    for i in range(n):
        for k in range(off[i], off[i + 1]):
            D[3 * i:3 * i + 3, 3 * col[k]:3 * col[k] + 3] = val[k]
    return D


def test_filtered_step_solves_the_constrained_equations():
    """A sheet lying on the floor, pushed down: every particle is constrained, its new normal velocity
    is 0, and the tangential rows of the unfiltered system A dv = b hold (the constraint impulse is
    along n only, and pushes)."""
    model, floor = _resting_sheet()
    n = model.particle_count
    rng = np.random.default_rng(3)
    v0 = rng.normal(0.0, 0.2, (n, 3)).astype(np.float32)
    v0[:, 1] = -np.abs(v0[:, 1])  # moving into the floor
    state_v = wp.array(v0, dtype=wp.vec3, device=DEVICE)
    integrator = ClothImplicitEuler(cg_tol=1.0e-7, cg_max_iterations=500)
    sim = ClothSimulator(model, integrator, forces=[ws.Gravity()], colliders=[floor], use_graph=False)
    wp.copy(sim.state.velocities, state_v)
    sim.step(1.0 / 60.0)
    contact = integrator._contact
    normals = contact.normal.numpy()
    assert len(contact.constrained()) == n
    np.testing.assert_allclose(normals, np.tile([0.0, 1.0, 0.0], (n, 1)), atol=1e-7)
    v1 = sim.state.velocities.numpy()
    assert np.abs(v1[:, 1]).max() < 1e-6  # inelastic resting contact: v_n = 0
    D, b = _dense(contact.A_plain), contact.rhs_plain.numpy().reshape(-1)
    J = (D @ (v1 - v0).reshape(-1).astype(np.float64) - b).reshape(n, 3)
    scale = np.abs(b).max()
    assert np.abs(J[:, [0, 2]]).max() < 1e-4 * scale  # no tangential constraint force (friction 0)
    assert J[:, 1].min() > 0.0  # the floor pushes
    # the same step without the constraints goes into the floor, and only the projection stops it
    sim2 = ClothSimulator(model, ClothImplicitEuler(cg_tol=1e-7, contact="after"), forces=[ws.Gravity()],
                          use_graph=False)
    wp.copy(sim2.state.velocities, state_v)
    sim2.step(1.0 / 60.0)
    assert sim2.state.velocities.numpy()[:, 1].max() < -0.01


def _incline_particle(mu, theta, steps=120, h=1.0 / 60.0, newton=2):
    b = ws.ModelBuilder()
    n = np.array([-np.sin(theta), np.cos(theta), 0.0])
    b.add_particle(tuple(0.0 * n), mass=0.01, radius=0.0)
    model = b.finalize(DEVICE)
    plane = ws.Plane(tuple(n), 0.0, restitution=0.0, friction=mu, mode="project")
    sim = ClothSimulator(model, ClothImplicitEuler(cg_tol=1e-8, newton_iterations=newton), forces=[ws.Gravity()],
                         colliders=[plane])
    for _ in range(steps):
        sim.frame(h, 1)
    x, v = sim.state.positions.numpy()[0], sim.state.velocities.numpy()[0]
    down = np.array([-np.cos(theta), -np.sin(theta), 0.0])  # down the slope
    return float(x @ down), float(v @ down), float(x @ n)


@pytest.mark.parametrize("mu", [0.0, 0.2, 0.4, 0.55])
def test_friction_on_an_incline_slides_at_the_coulomb_rate(mu):
    """A particle on a 30 degree slope with mu < tan 30: speed g (sin - mu cos) t down the slope, on
    the plane throughout. The friction drag's coefficient mu N / |v_t| is taken at the Newton
    iterate, so iterations converge to Coulomb's law (measured: 3 iterations within 0.05 %, 2 within
    2.5 %, 1 within 11 % at mu = 0.55, 1/60 s steps)."""
    theta = np.radians(30.0)
    T = 2.0
    s, v, height = _incline_particle(mu, theta, steps=120, newton=3)
    a = 9.81 * (np.sin(theta) - mu * np.cos(theta))
    assert v == pytest.approx(a * T, rel=0.01)
    assert abs(height) < 1e-4


def test_friction_holds_when_the_cone_allows():
    """mu = 0.7 > tan 30 = 0.577: once pressed (the first step has no normal impulse yet) the particle
    holds: below SLIP_FLOOR = 0.1 mm/s friction is viscous, so it creeps at 0.1 mm/s x tan(30) / 0.7
    = 0.083 mm/s at most; frictionless it would move 2.5 m in the second second."""
    s1, v1, _ = _incline_particle(0.7, np.radians(30.0), steps=60)
    s2, v2, height = _incline_particle(0.7, np.radians(30.0), steps=120)
    assert abs(v2) <= 1.0e-4 * np.tan(np.radians(30.0)) / 0.7 * 1.001
    assert abs(s2 - s1) < 1.0e-4 and abs(height) < 1e-4


def test_contact_released_when_it_pulls():
    """A sheet on the floor lifted by an upward force larger than its weight leaves the floor (a
    constraint kept after it pulls would hold the sheet down)."""
    model, floor = _resting_sheet()
    lift = ws.ConstantForce((0.0, 2.0 * 9.81 * float(model.particle_mass.numpy().max()), 0.0))
    sim = ClothSimulator(model, ClothImplicitEuler(), forces=[ws.Gravity(), lift], colliders=[floor])
    for _ in range(30):
        sim.frame(1.0 / 60.0, 1)
    y = sim.state.positions.numpy()[:, 1]
    assert y.min() > 0.1  # rose by g t^2 / 2 = 1.2 m less a step or two of release


def _energy(sim):
    m = sim.model
    q, v = sim.state.positions.numpy().astype(np.float64), sim.state.velocities.numpy().astype(np.float64)
    mass, moving = m.particle_mass.numpy(), m.particle_inv_mass.numpy() > 0
    idx = m.spring_indices.numpy().reshape(-1, 2)
    d = np.linalg.norm(q[idx[:, 0]] - q[idx[:, 1]], axis=1) - m.spring_rest_length.numpy()
    return (0.5 * (mass[moving] * (v[moving] ** 2).sum(1)).sum() + 9.81 * (mass[moving] * q[moving, 1]).sum()
            + 0.5 * (m.spring_stiffness.numpy() * d * d).sum())


def _largest_rise(name, params, frames, integrator_kwargs=None):
    scene = get_scene(name)(params, device=DEVICE)
    sim, t = scene.sim, scene.timing
    if integrator_kwargs:
        sim.integrator = ClothImplicitEuler(**integrator_kwargs)
        sim.integrator.bind_colliders(sim.colliders)
        sim.check_every = 0
    energies = [_energy(sim)]
    for _ in range(frames):
        sim.frame(t.frame_dt, t.steps)
        energies.append(_energy(sim))
    e = np.array(energies)
    return float(np.max(e - np.minimum.accumulate(e))) / e[0], scene


@pytest.mark.parametrize("name", ["cloth", "drape"])
def test_cloth_scenes_lose_energy_at_full_length(name):
    """The scene's mechanical energy never rises above its lowest value so far by more than 1 % of
    the start over its whole default length (120 frames at 1/60 s; resolution lowered, never frames);
    with the contact left to the collider after the step and one Newton iteration (the former
    default) it rose by 20-40 % at full resolution (the energy balance's false alarm)."""
    frames = 120
    rise, scene = _largest_rise(name, {"resolution": 16}, frames)
    assert rise < 0.01, rise
    assert scene.sim.energy_gain < 0.01


def test_projection_after_the_step_gains_energy():
    """The cause, measured: at the full resolution the former contact handling (projection after a
    linearised step) gains energy as the sheet lands on the sphere; the constraints do not."""
    frames = 30
    before, _ = _largest_rise("cloth", {}, frames, {"cg_tol": 1e-4, "contact": "after"})
    after, _ = _largest_rise("cloth", {}, frames)
    assert before > 0.25 and after < 0.01, (before, after)
