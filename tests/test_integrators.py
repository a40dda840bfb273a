"""Integrators: the seed's worked examples, the stability lesson, orders of accuracy, the
pendulum's energy behaviour and period, implicit Euler against a NumPy reference."""

import numpy as np
import pytest
import warp as wp

import warpsim as ws


def ball(device, integrator="semi_implicit_euler", extra=None, floor=True, restitution=0.5, mode="reflect"):
    b = ws.ModelBuilder()
    b.add_particle((0.0, 0.04, 0.0), mass=1.0)
    forces = [ws.Gravity((0.0, -9.81, 0.0))] + ([ws.ConstantForce(extra)] if extra else [])
    colliders = [ws.Plane((0, 1, 0), 0.0, restitution=restitution, mode=mode)] if floor else []
    return ws.Simulator(b.finalize(device), integrator=integrator, forces=forces, colliders=colliders)


def test_seed_ball_first_step(device):
    sim = ball(device)
    sim.step(0.04)
    assert sim.state.velocities.numpy()[0] == pytest.approx([0.0, -0.3924, 0.0], abs=1e-6)
    assert sim.state.positions.numpy()[0] == pytest.approx([0.0, 0.024304, 0.0], abs=1e-6)


def test_seed_ball_second_step_hits_the_floor(device):
    """Free flight would reach y = 0.024304 - 0.04 * 0.7848 = -0.007088 (penetration h = 0.007088);
    the collision reflects it to y = r h and v_y = -r v_y."""
    r = 0.5
    sim = ball(device, restitution=r, mode="seed")
    sim.step(0.04)
    sim.step(0.04)
    h = 0.04 * 0.7848 - 0.024304
    assert sim.state.positions.numpy()[0][1] == pytest.approx(r * h, abs=1e-6)
    assert sim.state.velocities.numpy()[0][1] == pytest.approx(r * 0.7848, abs=1e-6)
    free = ball(device, floor=False)
    free.step(0.04)
    free.step(0.04)
    assert free.state.positions.numpy()[0][1] == pytest.approx(-h, abs=1e-6)


def test_seed_ball_second_step_at_the_time_of_impact(device):
    """Reflect mode cuts step 2 at the contact on the integrator's own parabola
    y(t) = 0.024304 + w t - g t^2 / 2 (w = -0.3924 - g dt / 2, its synchronised velocity): it lands at
    t_c, leaves at -e times the impact speed and finishes the step on the reflected parabola."""
    r, g, dt = 0.5, 9.81, 0.04
    sim = ball(device, restitution=r)
    sim.step(dt)
    sim.step(dt)
    w = -0.3924 - g * dt / 2
    tc = (-w - np.sqrt(w * w + 2 * g * 0.024304)) / -g
    u = -r * (w - g * tc)
    rest = dt - tc
    assert 0.0 < tc < dt
    assert sim.state.positions.numpy()[0][1] == pytest.approx(u * rest - g * rest**2 / 2, abs=1e-6)
    assert sim.state.velocities.numpy()[0][1] == pytest.approx(u - g * rest + g * dt / 2, abs=1e-5)


def test_seed_ball_with_constant_force(device):
    sim = ball(device, extra=(5.0, 0.0, 0.0))
    sim.step(0.04)
    assert sim.state.velocities.numpy()[0] == pytest.approx([0.2, -0.3924, 0.0], abs=1e-6)
    assert sim.state.positions.numpy()[0] == pytest.approx([0.008, 0.024304, 0.0], abs=1e-6)


# ----------------------------------------------------------------------------------------
# The stability lesson on y' = -y: a unit mass under linear drag c = 1 has v' = -v exactly.
# ----------------------------------------------------------------------------------------
def decay(integrator, dt, steps=20):
    b = ws.ModelBuilder()
    b.add_particle((0, 0, 0), vel=(1.0, 0, 0), mass=1.0)
    sim = ws.Simulator(b.finalize("cpu"), integrator=integrator, forces=[ws.Drag(linear=1.0)], max_speed=1e30)
    for _ in range(steps):
        sim.step(dt)
    return sim.state.velocities.numpy()[0][0]


def test_stability_lesson():
    assert abs(decay("explicit_euler", 0.5)) == pytest.approx(0.5 ** 20, rel=1e-4)  # (1 - dt)^n decays
    assert abs(decay("explicit_euler", 1.9)) < 1.0
    assert abs(decay("explicit_euler", 3.0)) == pytest.approx(2.0 ** 20, rel=1e-4)  # |1 - dt| = 2 grows
    assert abs(decay("explicit_euler", 2.1)) > 1.0
    for dt in (0.5, 3.0, 50.0):
        v = decay("implicit_euler", dt)
        assert v == pytest.approx((1.0 / (1.0 + dt)) ** 20, rel=1e-4)  # decays for every dt
        assert 0.0 < v < 1.0


# ----------------------------------------------------------------------------------------
# Orders of accuracy on the harmonic oscillator x'' = -x (a unit mass on a unit spring).
# ----------------------------------------------------------------------------------------
def oscillator_error(integrator, dt, t_end=1.0):
    b = ws.ModelBuilder()
    b.add_particle((0, 0, 0), mass=0.0)
    b.add_particle((2.0, 0, 0), mass=1.0)
    b.add_spring(0, 1, stiffness=1.0, damping=0.0, rest_length=1.0)
    sim = ws.Simulator(b.finalize("cpu"), integrator=integrator, forces=[])
    n = int(round(t_end / dt))
    for _ in range(n):
        sim.step(dt)
    x = sim.state.positions.numpy()[1][0] - 1.0
    return abs(x - np.cos(n * dt))


@pytest.mark.parametrize("integrator,order", [("explicit_euler", 1), ("semi_implicit_euler", 1),
                                              ("implicit_euler", 1), ("rk2", 2), ("rk4", 4)])
def test_order_of_accuracy(integrator, order):
    dts = (0.1, 0.05) if order < 4 else (0.5, 0.25)
    e1, e2 = (oscillator_error(integrator, dt, t_end=2.0) for dt in dts)
    measured = np.log2(e1 / e2)
    assert measured == pytest.approx(order, abs=0.35)


# ----------------------------------------------------------------------------------------
# Pendulum: energy behaviour per integrator and RK4's period
# ----------------------------------------------------------------------------------------
def pendulum_energy(integrator, steps=300, dt=0.02, angle=1.0):
    run = ws.Pendulum(angle, integrator=integrator, device="cpu").run(steps, dt)
    return run["total"][:, 0] / run["total"][0, 0]


def test_pendulum_energy_per_integrator():
    explicit = pendulum_energy("explicit_euler")
    implicit = pendulum_energy("implicit_euler")
    symplectic = pendulum_energy("semi_implicit_euler")
    rk4 = pendulum_energy("rk4")
    assert explicit[-1] > 2.0 and np.all(np.diff(explicit[::25]) > 0)  # gains energy
    assert implicit[-1] < 0.5 and np.all(np.diff(implicit[::25]) < 0)  # loses it
    assert np.abs(symplectic - 1).max() < 0.05  # stays bounded (oscillates, no drift)
    assert abs(symplectic[-1] - 1) < 0.05 and symplectic.min() < 1.0 < symplectic.max()
    assert np.abs(rk4 - 1).max() < 1e-5  # holds it to high accuracy
    assert np.abs(pendulum_energy("rk2") - 1).max() < 2e-3


def crossing_times(t, q):
    """Times where q crosses zero going up, linearly interpolated."""
    k = np.flatnonzero((q[:-1] < 0) & (q[1:] >= 0))
    return t[k] + (t[k + 1] - t[k]) * (-q[k]) / (q[k + 1] - q[k])


@pytest.mark.parametrize("amplitude", [0.2, 1.5, 2.8])
def test_rk4_period_matches_elliptic_integral(amplitude):
    dt = 0.002
    exact = ws.exact_period(amplitude, 1.0, 9.81)
    run = ws.Pendulum(amplitude, integrator="rk4", device="cpu").run(int(2.2 * exact / dt), dt)
    crossings = crossing_times(run["time"], run["angle"][:, 0])
    period = np.mean(np.diff(crossings))
    assert period == pytest.approx(exact, rel=1e-3)
    small = 2 * np.pi * np.sqrt(1.0 / 9.81)
    if amplitude > 1.0:
        assert exact > 1.1 * small  # the large-amplitude correction is really tested


def test_exact_period_known_values():
    # T / T0 = 2 K(sin(q0/2)) / pi; K(sin 45 deg) = 1.8540746773 (q0 = 90 deg)
    t0 = 2 * np.pi * np.sqrt(1.0 / 9.81)
    assert ws.exact_period(np.pi / 2) / t0 == pytest.approx(2 * 1.8540746773013719 / np.pi, rel=1e-12)
    assert ws.exact_period(1e-6) == pytest.approx(t0, rel=1e-10)


# ----------------------------------------------------------------------------------------
# Implicit Euler against a float64 NumPy backward-Euler reference (full Newton, dense)
# ----------------------------------------------------------------------------------------
def numpy_backward_euler(x, v, mass, springs, g, h, steps):
    n = len(x)
    free = mass > 0

    def force(x, v):
        f = mass[:, None] * g
        for (i, j), L, k, kd in springs:
            u = x[i] - x[j]
            length = np.linalg.norm(u)
            d = u / length
            fs = -(k * (length - L) + kd * np.dot(v[i] - v[j], d)) * d
            f[i] += fs
            f[j] -= fs
        return f

    for _ in range(steps):
        x0, v0 = x.copy(), v.copy()
        vk = v0.copy()
        for _ in range(30):
            def residual(vflat):
                vv = vflat.reshape(n, 3)
                r = mass[:, None] * (vv - v0) - h * force(x0 + h * vv, vv)
                r[~free] = vv[~free] - v0[~free]
                return r.reshape(-1)
            r0 = residual(vk.reshape(-1))
            J = np.zeros((3 * n, 3 * n))
            for c in range(3 * n):
                e = np.zeros(3 * n)
                e[c] = 1e-7
                J[:, c] = (residual(vk.reshape(-1) + e) - residual(vk.reshape(-1) - e)) / 2e-7
            step = np.linalg.solve(J, -r0)
            vk = vk + step.reshape(n, 3)
            if np.abs(step).max() < 1e-12:
                break
        v = vk
        x = x0 + h * v
    return x, v


@pytest.mark.parametrize("linear_solver", ["warp_cg", "block_cg"])
def test_implicit_euler_matches_numpy_reference(device, linear_solver):
    rng = np.random.default_rng(4)
    b = ws.ModelBuilder()
    b.add_particle((0, 0, 0), mass=0.0)
    for i in range(1, 6):
        b.add_particle((0.3 * i, rng.uniform(-0.1, 0.1), rng.uniform(-0.1, 0.1)), mass=0.2)
        b.add_spring(i - 1, i, stiffness=200.0, damping=0.5, rest_length=0.25)
    b.add_spring(0, 2, stiffness=50.0, damping=0.2)
    g = np.array([0.0, -9.81, 0.0])
    integrator = ws.ImplicitEuler(newton_iterations=20, newton_tol=1e-6, cg_tol=1e-7, linear_solver=linear_solver)
    sim = ws.Simulator(b.finalize(device), integrator=integrator, forces=[ws.Gravity(g)])
    assert integrator.active_linear_solver == linear_solver
    h, steps = 0.05, 6
    for _ in range(steps):
        sim.step(h)
        assert integrator.last_newton_iterations < 20  # converged
    springs = list(zip(b.spring_indices, b.spring_rest_length, b.spring_stiffness, b.spring_damping))
    x_ref, v_ref = numpy_backward_euler(np.array(b.particle_q), np.array(b.particle_qd), np.array(b.particle_mass),
                                        springs, g, h, steps)
    assert np.allclose(sim.state.positions.numpy(), x_ref, atol=2e-4)
    assert np.allclose(sim.state.velocities.numpy(), v_ref, atol=4e-3)
    assert np.all(sim.state.positions.numpy()[0] == 0.0)  # pinned particle stays put


@pytest.mark.parametrize("linear_solver", ["warp_cg", "block_cg"])
def test_implicit_euler_cg_meets_tolerance_and_stays_stable_when_stiff(linear_solver):
    b = ws.ModelBuilder()
    b.add_particle((0, 0, 0), mass=0.0)
    for i in range(1, 20):
        b.add_particle((0.05 * i, 0, 0), mass=0.01)
        b.add_spring(i - 1, i, stiffness=1e5, damping=1.0)
    integrator = ws.ImplicitEuler(newton_iterations=1, cg_tol=1e-6, linear_solver=linear_solver)
    sim = ws.Simulator(b.finalize("cpu"), integrator=integrator)
    for _ in range(30 if linear_solver == "warp_cg" else 60):
        sim.step(1.0 / 60.0)
        assert integrator.last_cg_iterations > 0
        rhs = np.linalg.norm(integrator.rhs.numpy())
        assert integrator.last_cg_residual <= max(1e-6 * rhs, 1e-9) * 1.0001
    x = sim.state.positions.numpy()
    assert np.all(np.isfinite(x))
    # the chain hangs from the pin: every particle lies within the chain's length of it
    assert np.linalg.norm(x, axis=1).max() < 0.05 * 19 * 1.05
    explicit = ws.Simulator(b.finalize("cpu"), integrator="semi_implicit_euler")
    with pytest.raises(ws.SimulationError, match="Remedy"):
        for _ in range(60):
            explicit.step(1.0 / 60.0)


# ----------------------------------------------------------------------------------------
# Adaptive sub-stepping and blow-up reporting
# ----------------------------------------------------------------------------------------
def test_adaptive_substeps_bound_displacement():
    b = ws.ModelBuilder()
    b.add_particle((0, 0, 0), vel=(30.0, 0, 0), mass=1.0)
    b.add_particle((0, 1, 0), vel=(0.1, 0, 0), mass=1.0)
    sim = ws.Simulator(b.finalize("cpu"), forces=[], adaptive=True, max_displacement=0.05)
    n = sim.step(0.1)
    assert n == 60 and sim.last_substeps == 60  # 30 m/s * 0.1 s / 0.05 m
    assert sim.substep_history == [60]
    assert sim.time == pytest.approx(0.1)
    assert sim.state.positions.numpy()[0][0] == pytest.approx(3.0, rel=1e-5)
    slow = ws.Simulator(b.finalize("cpu"), forces=[], adaptive=True, max_displacement=10.0)
    assert slow.step(0.1) == 1
    capped = ws.Simulator(b.finalize("cpu"), forces=[], adaptive=True, max_displacement=1e-4, max_substeps=8)
    assert capped.step(0.1) == 8


def test_blow_up_names_step_particle_and_remedy():
    b = ws.ModelBuilder()
    b.add_particle((0, 0, 0), mass=0.0)
    b.add_particle((1.0, 0, 0), mass=0.001)
    b.add_particle((2.0, 0, 0), mass=1.0)
    b.add_spring(0, 1, stiffness=1e6, damping=0.0, rest_length=0.9)
    sim = ws.Simulator(b.finalize("cpu"), integrator="explicit_euler", forces=[])
    with pytest.raises(ws.SimulationError) as info:
        sim.run(frames=10, frame_dt=0.05)
    err = info.value
    assert err.particle == 1 and err.frame is not None and err.step >= 1
    message = str(err)
    assert f"frame {err.frame}" in message and "particle 1" in message
    assert "smaller dt" in message and "implicit_euler" in message


def test_every_integrator_runs_every_force(device):
    """Smoke over the whole force set: finite results and momentum bookkeeping stay sane."""

    @wp.func
    def lift(x: wp.vec3, v: wp.vec3, t: float) -> wp.vec3:
        return wp.vec3(0.0, 0.5 * wp.cos(t), 0.0)

    for integrator in ws.INTEGRATORS:
        b = ws.ModelBuilder()
        b.add_particle((0, 1, 0), mass=0.0)
        for i in range(1, 5):
            b.add_particle((0.2 * i, 1, 0), mass=0.5, radius=0.01)
            b.add_spring(i - 1, i, 100.0, 0.5)
        forces = [ws.Gravity(), ws.Wind(), ws.Magnets([[0, 0, 0]], [-0.1]), ws.Drag(0.1, 0.05), ws.ForceField(lift),
                  ws.ConstantForce((0, 0, 1.0), particles=[4])]
        sim = ws.Simulator(b.finalize(device), integrator=integrator, forces=forces, colliders=[ws.Plane()])
        sim.run(frames=5, frame_dt=1 / 60, substeps=4)
        x = sim.state.positions.numpy()
        assert np.all(np.isfinite(x)) and np.all(x[:, 1] >= -1e-6), integrator
        assert sim.time == pytest.approx(5 / 60)


# ----------------------------------------------------------------------------------------
# The Simulator's fused semi-implicit pass against the separate passes it replaces
# ----------------------------------------------------------------------------------------
def _separate_passes_step(sim, h):
    """One Simulator sub-step the way it ran before the passes were fused: copy q_prev, zero f,
    every force in order, the semi-implicit update, the colliders, the clock."""
    from warpsim.core.launch import recording
    from warpsim.kernels import integrate as KI

    st, s = sim.state, sim.system
    wp.copy(sim._q_prev, st.positions)
    st.forces.zero_()
    for f in s.forces:
        with recording(wp.Tape()):  # a tape warpsim sees: every launch goes through plain wp.launch
            f.eval(st.positions, st.velocities, sim._time, 0.0, st.forces)
    wp.launch(KI.step_semi_implicit_euler, s.count,
              inputs=[st.positions, st.velocities, st.forces, s.inv_mass, h, st.positions, st.velocities], device="cpu")
    for c in sim.colliders:
        c.apply(sim.model, st, sim._q_prev, h)
    wp.launch(KI.advance_time, 1, inputs=[sim._time, h], device="cpu")


@pytest.mark.parametrize("case", ["default", "gravity_first", "gravity_later"])
def test_fused_semi_implicit_step_is_bit_identical_to_separate_passes(case):
    def make():
        b = ws.ModelBuilder()
        ws.add_cloth_grid(b, (5, 5), (0.5, 0.5), origin=(0.0, 1.0, 0.0), pin=["corner_00"], particle_mass=0.02)
        forces = {"default": None,
                  "gravity_first": [ws.Gravity(), ws.Wind(coefficient=0.02), ws.Drag(0.01, 0.01)],
                  "gravity_later": [ws.Wind(coefficient=0.02), ws.Gravity((0.0, -3.0, 1.0))]}[case]
        colliders = [] if case == "default" else [ws.Plane(offset=0.8, restitution=0.3, friction=0.2)]
        return ws.Simulator(b.finalize("cpu"), forces=forces, colliders=colliders)

    fused, separate = make(), make()
    assert fused.integrator.fuses(fused.system)
    h = 1.0 / 600.0
    for k in range(240):
        if k == 120:  # gravity changed between steps (as the scenes' set_gravity does) takes effect at once
            for sim in (fused, separate):
                next(f for f in sim.forces if isinstance(f, ws.Gravity)).g = (0.5, -20.0, 0.0)
        fused.step(h)
        _separate_passes_step(separate, h)
    for name in ("positions", "velocities", "forces"):
        assert np.array_equal(getattr(fused.state, name).numpy(), getattr(separate.state, name).numpy()), name
    assert np.array_equal(fused._time.numpy(), separate._time.numpy())
    assert fused.state.positions.numpy()[:, 1].min() < 0.9  # it fell
    if case != "default":
        assert fused.state.positions.numpy()[:, 1].min() >= 0.8 - 1e-6  # and the plane held it


@pytest.mark.parametrize("check_every", [1, 4])
def test_fused_blow_up_test_reports_the_step_speed_crosses_the_bound(check_every):
    # v_k = k h a = 0.1 k m/s: |v| first exceeds max_speed = 1.05 m/s after step 11; the test runs
    # on steps that are multiples of check_every
    b = ws.ModelBuilder()
    b.add_particle((0, 0, 0), mass=1.0)
    sim = ws.Simulator(b.finalize("cpu"), forces=[ws.ConstantForce((1.0, 0.0, 0.0))], max_speed=1.05,
                       check_every=check_every)
    with pytest.raises(ws.SimulationError) as info:
        for _ in range(30):
            sim.step(0.1)
    expected = 11 if check_every == 1 else 12
    assert info.value.step == expected == sim.step_count and info.value.particle == 0


def test_fused_blow_up_test_equals_find_blow_up():
    """The fused pass's one-comparison test flags exactly the particles find_blow_up flags."""
    from warpsim.kernels import integrate as KI

    inf, nan, big = np.inf, np.nan, 3.0e38
    x = np.array([[inf, 0, 0], [nan, 0, 0], [0, 0, 0], [0, 0, 0], [big, big, 0], [0, 0, 0], [0, 0, 0], [0, 0, 0],
                  [0, -inf, 0]], dtype=np.float32)
    v = np.array([[0, 0, 0], [0, 0, 0], [inf, 0, 0], [0, nan, 0], [0, 0, 0], [2.0, 0, 0], [1.5, 1.5, 0],
                  [big, big, big], [0, 0, 0]], dtype=np.float32)
    expected = [0, 0, 0, 0, 7, 7, 0, 0, 0]  # 7: not flagged (finite 3e38 position; |v| = 2.0 is not above 2.0)
    for i in range(len(x)):
        flags = []
        for fused in (True, False):
            q = wp.array(x[i:i + 1], dtype=wp.vec3, device="cpu")
            qd = wp.array(v[i:i + 1], dtype=wp.vec3, device="cpu")
            bad = wp.full(1, 7, dtype=int, device="cpu")
            if fused:  # h = 0 and f = 0: the state is tested as it is
                f = wp.zeros(1, dtype=wp.vec3, device="cpu")
                none = wp.zeros(0, dtype=wp.vec3, device="cpu")
                wp.launch(KI.step_particles_semi_implicit, 1,
                          inputs=[f, wp.ones(1, dtype=float), wp.ones(1, dtype=float), wp.vec3(), 0.0, q, qd, none,
                                  none, wp.zeros(0, dtype=float), 1, 2.0, bad], device="cpu")
            else:
                wp.launch(KI.find_blow_up, 1, inputs=[q, qd, 2.0, bad], device="cpu")
            flags.append(int(bad.numpy()[0]))
        assert flags == [expected[i], expected[i]], (i, flags)
