"""Stability limits (issue 26): stable_dt() against the analytic limit of each integrator's
stability region on a single spring, runs just inside / outside it, and models (grid cloth,
teapot) against the limit found by bisection over runs."""

import math
import warnings

import numpy as np
import pytest

import warpsim as ws
from warpsim.core.stability import stable_step

K, M1, M2 = 100.0, 1.0, 2.0
OMEGA = math.sqrt(K * (1.0 / M1 + 1.0 / M2))  # two masses on one spring: omega^2 = k (1/m1 + 1/m2)
MU = 1.0 / (1.0 / M1 + 1.0 / M2)  # reduced mass


REST = 100.0  # long springs: a stretch of metres stays in the linear regime


def spring_sim(integrator, damping=0.0, pairs=((K, None),)):
    """Two masses M1, M2 per spring, stretched 5 cm along x; ``pairs``: (stiffness, damping or None
    for ``damping``) per spring, the springs far apart and independent."""
    b = ws.ModelBuilder()
    for s, (k, c) in enumerate(pairs):
        z = 10.0 * s
        b.add_particle((0.0, 0.0, z), mass=M1)
        b.add_particle((REST + 0.05, 0.0, z), mass=M2)
        b.add_spring(2 * s, 2 * s + 1, k, damping if c is None else c, rest_length=REST)
    return ws.Simulator(b.finalize("cpu"), integrator=integrator, forces=[], check_every=0, warn_unstable=False)


def zeta_of(damping, k=K):
    return damping / (2.0 * math.sqrt(k * MU))


def stretch_history(sim, dt, steps=10_000):
    """Largest |stretch| [m] of each spring at 10 checkpoints over ``steps`` steps (inf once non-finite)."""
    worst = np.zeros(sim.model.spring_count)
    for _ in range(10):
        for _ in range(steps // 10):
            sim.step(dt)
        x = sim.state.positions.numpy().reshape(-1, 2, 3).astype(np.float64)
        stretch = np.abs(np.linalg.norm(x[:, 1] - x[:, 0], axis=1) - REST)
        worst = np.maximum(worst, np.where(np.isfinite(stretch), stretch, np.inf))
    return worst


def amplitude_after(integrator, damping, dt, steps=10_000):
    return float(stretch_history(spring_sim(integrator, damping), dt, steps)[0])


CASES = [  # integrator, damping [N s/m], analytic limit x omega
    ("semi_implicit_euler", 0.0, 2.0),
    ("rk4", 0.0, 2.0 * math.sqrt(2.0)),
    ("explicit_euler", 2.0, 2.0 * zeta_of(2.0)),
    ("rk2", 2.0, None),  # RK2's region edge on the damped ray: checked by the runs only
    ("rk4", 60.0, None),  # real eigenvalues: 2.785 / |lambda|max, below
]


@pytest.mark.parametrize("integrator,damping,analytic", CASES)
def test_single_spring_limit_matches_theory_and_runs(integrator, damping, analytic):
    limit = spring_sim(integrator, damping).stable_dt()
    if integrator == "rk4" and damping == 60.0:
        zeta = zeta_of(damping)
        assert zeta > 1.0
        lam = OMEGA * (zeta + math.sqrt(zeta * zeta - 1.0))
        analytic = 2.785 * OMEGA / lam
    if analytic is not None:
        assert limit == pytest.approx(analytic / OMEGA, rel=0.05)
    # One run of 10,000 steps of dt = 0.95 x the limit: spring 0 is the one above; spring 1 is
    # (1.1 / 0.95)^2 stiffer with (1.1 / 0.95) x the damping (the same damping ratio), so the same
    # step is 1.1 x its own limit.
    scale = 1.1 / 0.95
    sim = spring_sim(integrator, pairs=((K, damping), (K * scale**2, damping * scale)))
    per_spring = sim.stability().per_spring()
    assert per_spring[0] == pytest.approx(limit, rel=1e-4)
    assert per_spring[1] == pytest.approx(limit / scale, rel=1e-3)
    worst = stretch_history(sim, 0.95 * limit)
    # bounded: semi-implicit Euler's orbit is an ellipse stretched by 1 / sqrt(1 - (h omega / 2)^2) (3.2x at
    # 0.95 of the limit), the others decay; beyond the limit the stretch grows without bound
    assert worst[0] <= 10 * 0.05
    assert worst[1] > 100 * 0.05


def test_semi_implicit_damping_lowers_the_limit():
    # 2 / (omega (zeta + sqrt(1 + zeta^2))), from the Jury conditions of the step matrix
    zeta = zeta_of(20.0)
    assert spring_sim("semi_implicit_euler", 20.0).stable_dt() == pytest.approx(
        2.0 / (OMEGA * (zeta + math.sqrt(1.0 + zeta * zeta))), rel=0.05)


def test_explicit_euler_undamped_has_no_stable_step_and_says_why():
    sim = spring_sim("explicit_euler")
    limit = sim.stability()
    assert limit.dt == 0.0
    assert "no stable step" in limit.reason
    sim.warn_unstable = True
    with pytest.warns(ws.StabilityWarning, match="unstable for explicit_euler.*no stable step"):
        sim.step(1e-4)
    assert amplitude_after("explicit_euler", 0.0, 0.01, steps=2000) > 0.1  # grows at any step


def test_implicit_euler_unrestricted_and_bounded():
    sim = spring_sim("implicit_euler")
    assert sim.stable_dt() == math.inf
    for _ in range(200):
        sim.step(10.0 / OMEGA)
    x = sim.state.positions.numpy().astype(np.float64)
    assert abs(np.linalg.norm(x[1] - x[0]) - REST) <= 0.05


def test_stable_step_regions():
    assert stable_step("rk4", 1.0, 0.0) == pytest.approx(2.0 * math.sqrt(2.0), rel=1e-6)
    assert stable_step("rk4", 1.0, 1.0) == pytest.approx(2.785, rel=1e-3)  # real axis
    assert stable_step("rk2", 1.0, 0.0) == 0.0
    assert stable_step("rk2", 1.0, 1.0) == pytest.approx(2.0, rel=1e-6)
    assert stable_step("explicit_euler", 2.0, 0.3) == pytest.approx(0.3, rel=1e-9)
    assert stable_step("implicit_euler", 1e6, 0.0) == math.inf


def test_limit_names_the_stiffest_spring_and_skips_pins():
    b = ws.ModelBuilder()
    b.add_particle((0.0, 0.0, 0.0), mass=0.0)  # pinned: excluded
    b.add_particle((0.0, -1.0, 0.0), mass=1.0)
    b.add_particle((0.0, -2.0, 0.0), mass=0.01)
    b.add_spring(0, 1, 1.0e4, 0.0)
    b.add_spring(1, 2, 50.0, 0.0)
    b.add_particle((3.0, 0.0, 0.0), mass=1.0)
    b.add_particle((4.0, 0.0, 0.0), mass=1.0)
    b.add_spring(3, 4, 10.0, 0.0)
    sim = ws.Simulator(b.finalize("cpu"), forces=[], warn_unstable=False)
    limit = sim.stability()
    # springs alone: 1e4/1 = 1e4 and 50 (1 + 100) = 5050 rad^2/s^2; coupled chain: eigenvalue of M^-1 K
    mk = np.array([[1.0e4 + 50.0, -50.0], [-50.0 / 0.01, 50.0 / 0.01]])
    exact = math.sqrt(max(np.linalg.eigvals(mk).real))
    assert limit.omega_max == pytest.approx(exact, rel=1e-3)
    assert limit.omega_bound >= limit.omega_max * (1 - 1e-6)
    assert limit.dt == pytest.approx(2.0 / exact, rel=1e-3)
    assert limit.limiting == "spring" and limit.index == 0 and limit.stiffness == 1.0e4
    assert limit.per_spring()[2] == pytest.approx(2.0 / math.sqrt(20.0))
    assert np.argmin(limit.per_spring()) == 0
    assert limit.per_particle()[0] == math.inf  # the pin
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        sim.warn_unstable = True
        sim.step(0.5 * limit.dt)  # inside: no warning


def test_pendulum_limit():
    p = ws.Pendulum([0.1, 0.2], length=[1.0, 0.25], integrator="semi_implicit_euler", device="cpu")
    limit = p.stability()
    assert limit.limiting == "pendulum" and limit.index == 1
    assert limit.dt == pytest.approx(2.0 / math.sqrt(9.81 / 0.25))
    assert ws.Pendulum(0.1, integrator="explicit_euler", device="cpu").stable_dt() == 0.0


def _blows_up(make_sim, dt, steps):
    """True when a run of ``steps`` steps of ``dt`` from a small random velocity field reaches a
    speed of 1 m/s (100x the start) or a non-finite state: the linear instability of the stiffest mode."""
    sim = make_sim()
    for _ in range(steps):
        sim.step(dt)
    v = np.abs(sim.state.velocities.numpy())
    return not (np.isfinite(v).all() and v.max() < 1.0)


def _bisect_limit(make_sim, guess, steps, iterations=6):
    lo, hi = 0.5 * guess, 2.0 * guess
    assert not _blows_up(make_sim, lo, steps) and _blows_up(make_sim, hi, steps)
    for _ in range(iterations):
        mid = math.sqrt(lo * hi)
        if _blows_up(make_sim, mid, steps):
            hi = mid
        else:
            lo = mid
    return math.sqrt(lo * hi)


def _jiggled(model, integrator="semi_implicit_euler"):
    sim = ws.Simulator(model, integrator=integrator, forces=[], check_every=0, warn_unstable=False)
    v = np.random.default_rng(1).normal(0.0, 0.01, (model.particle_count, 3))
    v[model.particle_inv_mass.numpy() == 0.0] = 0.0
    sim.state.velocities.assign(v.astype(np.float32))
    return sim


def test_grid_cloth_limit_matches_bisection():
    def make():
        b = ws.ModelBuilder()
        ws.add_cloth_grid(b, resolution=(6, 6), size=(0.5, 0.5), particle_mass=0.01, pin=[0, 6])
        return _jiggled(b.finalize("cpu"))

    predicted = make().stable_dt()
    assert 0.0 < predicted < math.inf
    empirical = _bisect_limit(make, predicted, steps=1500)
    assert predicted == pytest.approx(empirical, rel=0.2)


@pytest.mark.parametrize("stiffness", [40.0, 80.0])
def test_teapot_limit_matches_bisection(stiffness):
    from warpsim.scenes import get_scene

    scene = get_scene("teapot")({"resolution": "3", "stiffness": stiffness}, device="cpu")

    def make():
        return _jiggled(scene.model)

    limit = make().stability()
    assert limit.limiting == "spring"
    assert limit.omega_bound >= limit.omega_max
    empirical = _bisect_limit(make, limit.dt, steps=1500)
    assert limit.dt == pytest.approx(empirical, rel=0.2)


def test_batched_worlds_have_one_limit_each():
    from warpsim.scenes import get_scene
    from warpsim.worlds.batch import WorldBatch

    cls = get_scene("springs")
    worlds = [{"count": 4, "stiffness": k} for k in (100.0, 400.0, 1600.0)]
    batch = WorldBatch(cls, worlds, device="cpu")
    per_world = batch.stable_dt()
    alone = [cls(w, device="cpu").stability().dt for w in worlds]
    np.testing.assert_allclose(per_world, alone, rtol=1e-3)
    assert per_world[0] == pytest.approx(2.0 * per_world[1], rel=0.05)  # omega ~ sqrt(k)
    from warpsim.scenes.timing import resolve_timing

    batch.use_timing(resolve_timing(cls, batch.params[0], substeps=1))  # the step as given
    assert batch.stability_warning(1.5 * per_world[1], 1).startswith("2 of 3 worlds step above their stability limit")


def test_per_world_picks_equal_a_loop_over_worlds():
    """warpsim.core.segments (particle_limits' per-world picks, issue 50): the first largest /
    smallest value of each world's particles as np.argmax / np.argmin over the world picks it,
    -1 for an empty world or one holding a NaN; any_per_world as .any() per world."""
    from warpsim.core.segments import any_per_world, first_extreme

    rng = np.random.default_rng(5)
    for trial in range(200):
        W, n = int(rng.integers(1, 7)), int(rng.integers(0, 25))
        world = rng.integers(0, W, n)
        values = rng.integers(0, 4, n).astype(float)  # ties: the first wins
        if n and trial % 3 == 0:
            values[rng.integers(0, n)] = np.nan
        if n and trial % 4 == 0:
            values[rng.integers(0, n)] = np.inf
        order = np.argsort(world, kind="stable")
        start = np.searchsorted(world[order], np.arange(W + 1))
        flags = values > 1.5
        anyw = any_per_world(flags, order, start)
        for largest, pick in ((True, np.argmax), (False, np.argmin)):
            index, extreme = first_extreme(values, order, start, largest)
            for w in range(W):
                mine = order[start[w]:start[w + 1]]
                assert anyw[w] == bool(flags[mine].any())
                if not len(mine) or np.isnan(values[mine]).any():
                    assert index[w] == -1 and np.isnan(extreme[w])
                    continue
                assert index[w] == mine[pick(values[mine])] and extreme[w] == values[index[w]]
