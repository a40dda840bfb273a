"""Every force against a NumPy reference; springs conserve momentum; Jacobians against finite differences."""

import numpy as np
import pytest
import warp as wp

import warpsim as ws


def random_model(device, n=12, springs=20, seed=0, pinned=(0,)):
    rng = np.random.default_rng(seed)
    b = ws.ModelBuilder()
    for i in range(n):
        mass = 0.0 if i in pinned else rng.uniform(0.5, 2.0)
        b.add_particle(rng.uniform(-1, 1, 3), rng.uniform(-1, 1, 3), mass=mass)
    pairs = set()
    while len(pairs) < springs:
        i, j = rng.choice(n, 2, replace=False)
        pairs.add((min(i, j), max(i, j)))
    for i, j in sorted(pairs):
        b.add_spring(int(i), int(j), stiffness=rng.uniform(10, 100), damping=rng.uniform(0.1, 2.0),
                     rest_length=rng.uniform(0.3, 1.5))
    return b, b.finalize(device)


def eval_force(model, force, q=None, qd=None, t=0.0):
    force.bind(model)
    q = model.particle_q if q is None else q
    qd = model.particle_qd if qd is None else qd
    f = wp.zeros(model.particle_count, dtype=wp.vec3, device=model.device)
    time = wp.array([t], dtype=float, device=model.device)
    force.eval(q, qd, time, 0.0, f)
    return f.numpy().astype(np.float64)


def numpy_state(builder):
    return (np.array(builder.particle_q), np.array(builder.particle_qd), np.array(builder.particle_mass))


def test_gravity_and_constant_force(device):
    b, m = random_model(device)
    x, v, mass = numpy_state(b)
    g = (0.3, -9.81, 1.2)
    assert np.allclose(eval_force(m, ws.Gravity(g)), mass[:, None] * np.array(g), atol=1e-5)
    f = eval_force(m, ws.ConstantForce((5.0, 0.0, -1.0), particles=[2, 5, 5]))
    expected = np.zeros((m.particle_count, 3))
    expected[2] = (5, 0, -1)
    expected[5] = (10, 0, -2)  # listed twice: applied twice
    assert np.allclose(f, expected)


def test_wind_matches_numpy(device):
    b, m = random_model(device)
    x, v, mass = numpy_state(b)
    wind = ws.Wind(direction=(1, 0, 1), speed=4.0, gust_amplitude=0.5, gust_frequency=0.7, turn_amplitude=0.6,
                   turn_frequency=0.3, coefficient=0.2, seed=3)
    for t in (0.0, 0.37, 2.9):
        w = wind.air_velocity(t)
        expected = 0.2 * (w[None, :] - v)
        expected[mass == 0.0] = 0.0
        assert np.allclose(eval_force(m, wind, t=t), expected, atol=1e-4)
    speeds = [np.linalg.norm(wind.air_velocity(t)) for t in np.linspace(0, 10, 200)]
    assert max(speeds) > 4.5 and min(speeds) < 3.5  # gusts really vary the strength
    dirs = [wind.air_velocity(t) / np.linalg.norm(wind.air_velocity(t)) for t in np.linspace(0, 3, 50)]
    assert np.max([np.arccos(np.clip(d @ dirs[0], -1, 1)) for d in dirs]) > 0.5  # and the direction turns


def test_magnets_match_numpy(device):
    b, m = random_model(device)
    x, v, mass = numpy_state(b)
    centers = np.array([[0.2, 0.1, -0.3], [-0.5, 0.4, 0.5]])
    strengths = np.array([2.0, -1.5])
    eps, cutoff = 0.1, 1.2
    expected = np.zeros_like(x)
    for c, s in zip(centers, strengths):
        d = c - x
        r2 = (d * d).sum(1)
        contrib = s * d / ((r2 + eps * eps) ** 1.5)[:, None]
        contrib[r2 >= cutoff * cutoff] = 0.0
        expected += contrib
    expected[mass == 0.0] = 0.0
    got = eval_force(m, ws.Magnets(centers, strengths, softening=eps, cutoff=cutoff))
    assert np.allclose(got, expected, rtol=1e-4, atol=1e-4)
    assert np.any(np.all(got == 0.0, axis=1) & (mass > 0))  # the cutoff removed somebody


def test_drag_matches_numpy(device):
    b, m = random_model(device)
    x, v, mass = numpy_state(b)
    expected = -(0.3 + 0.7 * np.linalg.norm(v, axis=1))[:, None] * v
    assert np.allclose(eval_force(m, ws.Drag(0.3, 0.7)), expected, atol=1e-5)


def test_springs_match_numpy(device):
    b, m = random_model(device)
    x, v, mass = numpy_state(b)
    expected = np.zeros_like(x)
    for (i, j), L, k, kd in zip(b.spring_indices, b.spring_rest_length, b.spring_stiffness, b.spring_damping):
        u = x[i] - x[j]
        length = np.linalg.norm(u)
        d = u / length
        f = -(k * (length - L) + kd * np.dot(v[i] - v[j], d)) * d
        expected[i] += f
        expected[j] -= f
    got = eval_force(m, ws.Springs())
    assert np.allclose(got, expected, rtol=1e-4, atol=1e-3)
    assert np.allclose(got.sum(0), 0.0, atol=1e-3)  # equal and opposite


@wp.func
def swirl_field(x: wp.vec3, v: wp.vec3, t: float) -> wp.vec3:
    return wp.vec3(-x[2], 0.5 * x[1] * x[1], x[0]) * (1.0 + t) - 0.1 * v


def test_user_force_field(device):
    b, m = random_model(device)
    x, v, mass = numpy_state(b)
    t = 0.25
    expected = np.stack([-x[:, 2], 0.5 * x[:, 1] ** 2, x[:, 0]], 1) * (1 + t) - 0.1 * v
    expected[mass == 0.0] = 0.0
    assert np.allclose(eval_force(m, ws.ForceField(swirl_field), t=t), expected, atol=1e-5)
    with pytest.raises(ValueError, match="@wp.func"):
        ws.ForceField(lambda x, v, t: x)


def test_springs_conserve_linear_momentum(device):
    """Only internal spring forces: total momentum stays at its initial value for every integrator."""
    for integrator in ws.INTEGRATORS:
        b, m = random_model(device, pinned=())
        sim = ws.Simulator(m, integrator=integrator, forces=[])
        mass = m.particle_mass.numpy()[:, None]
        p0 = (mass * sim.state.velocities.numpy()).sum(0)
        for _ in range(50):
            sim.step(0.002)
        p1 = (mass * sim.state.velocities.numpy()).sum(0)
        assert np.allclose(p1, p0, atol=2e-4), integrator


# ----------------------------------------------------------------------------------------
# Jacobians against central finite differences of the forces
# ----------------------------------------------------------------------------------------
def dense_jacobian(model, force, ck, cd, q, qd, t=0.0):
    """Assemble ck df/dx + cd df/dv of ``force`` into a dense (3n, 3n) matrix."""
    force.bind(model)
    n = model.particle_count
    d = model.device
    diag = wp.zeros(n, dtype=wp.mat33, device=d)
    m = force.jacobian_triplet_count()
    rows, cols, vals = (wp.zeros(m, dtype=int, device=d), wp.zeros(m, dtype=int, device=d),
                        wp.zeros(m, dtype=wp.mat33, device=d)) if m else (None, None, None)
    time = wp.array([t], dtype=float, device=d)
    force.eval_jacobian(q, qd, time, 0.0, ck, cd, diag, rows, cols, vals)
    J = np.zeros((3 * n, 3 * n))
    for i, block in enumerate(diag.numpy()):
        J[3 * i:3 * i + 3, 3 * i:3 * i + 3] += block
    if m:
        for r, c, block in zip(rows.numpy(), cols.numpy(), vals.numpy()):
            J[3 * r:3 * r + 3, 3 * c:3 * c + 3] += block
    return J


def finite_difference(model, force, q_np, qd_np, wrt, eps=1e-3, t=0.0):
    n = model.particle_count
    J = np.zeros((3 * n, 3 * n))
    for k in range(3 * n):
        cols = []
        for sign in (1.0, -1.0):
            q2, qd2 = q_np.copy(), qd_np.copy()
            (q2 if wrt == "x" else qd2)[k // 3, k % 3] += sign * eps
            cols.append(eval_force(model, force, wp.array(q2, dtype=wp.vec3, device=model.device),
                                   wp.array(qd2, dtype=wp.vec3, device=model.device), t).reshape(-1))
        J[:, k] = (cols[0] - cols[1]) / (2 * eps)
    return J


@pytest.mark.parametrize("name", ["springs", "drag", "magnets", "wind", "field"])
def test_jacobians_match_finite_differences(name):
    device = "cpu"
    b, m = random_model(device, n=6, springs=8, pinned=())
    x, v, _ = numpy_state(b)
    force = {
        "springs": ws.Springs(exact_jacobian=True),
        "drag": ws.Drag(0.4, 0.9),
        "magnets": ws.Magnets([[0.3, 0.2, 0.1]], [1.5], softening=0.3),
        "wind": ws.Wind(coefficient=0.7),
        "field": ws.ForceField(swirl_field),
    }[name]
    qa = wp.array(x, dtype=wp.vec3, device=device)
    qda = wp.array(v, dtype=wp.vec3, device=device)
    Kx = dense_jacobian(m, force, 1.0, 0.0, qa, qda)
    Dv = dense_jacobian(m, force, 0.0, 1.0, qa, qda)
    fd_x = finite_difference(m, force, x, v, "x")
    fd_v = finite_difference(m, force, x, v, "v")
    if name == "field":  # the solver uses the symmetric part of a user field's Jacobian
        fd_x = 0.5 * (fd_x + fd_x.T)
        fd_v = 0.5 * (fd_v + fd_v.T)
    scale = max(1.0, np.abs(fd_x).max(), np.abs(fd_v).max())
    assert np.abs(Kx - fd_x).max() <= 2e-2 * scale
    assert np.abs(Dv - fd_v).max() <= 2e-2 * scale
    assert np.abs(fd_x).max() + np.abs(fd_v).max() > 0.1  # the force really depends on the state


def test_solver_spring_jacobian_is_symmetric_negative_semidefinite():
    b, m = random_model("cpu", n=8, springs=14, pinned=())
    x, v, _ = numpy_state(b)
    q = wp.array(x, dtype=wp.vec3, device="cpu")
    qd = wp.array(v, dtype=wp.vec3, device="cpu")
    K = dense_jacobian(m, ws.Springs(exact_jacobian=False), 1.0, 0.0, q, qd)
    assert np.allclose(K, K.T, atol=1e-4)
    assert np.linalg.eigvalsh(0.5 * (K + K.T)).max() <= 1e-3
    # in tension with no damping the clamped form equals the exact one
    b2 = ws.ModelBuilder()
    b2.add_particle((0, 0, 0))
    b2.add_particle((1.0, 0.3, -0.2))
    b2.add_spring(0, 1, 50.0, 0.0, rest_length=0.5)
    m2 = b2.finalize("cpu")
    Ke = dense_jacobian(m2, ws.Springs(exact_jacobian=True), 1.0, 0.0, m2.particle_q, m2.particle_qd)
    Kc = dense_jacobian(m2, ws.Springs(exact_jacobian=False), 1.0, 0.0, m2.particle_q, m2.particle_qd)
    assert np.allclose(Ke, Kc, atol=1e-4)
