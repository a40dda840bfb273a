"""The implicit strand step (``StrandImplicitEuler``) and the strands' stability limits: the
band solve against a dense solve of the same matrix and that matrix against the force kernel's
Jacobians, a released strand converging at first order to the NumPy chain reference, a swinging
strand's energy (never grows; decays as backward Euler predicts for its lowest mode), the hair
scene's tips against the explicit step over 2 s, and ``stable_dt()`` of strands against bisected
limits of every explicit integrator."""

import math

import numpy as np
import pytest
import warp as wp

import warpsim as ws
from warpsim.kernels import strands_implicit as KI
from warpsim.strands import StrandImplicitEuler
from warpsim.strands.stability import band_matrix, band_to_dense, strand_eigenvalues, strand_jacobians

from test_strands import G, strand_energy_np, strand_forces_np

DEVICE = "cpu"


def _strand(direction=(1.0, 0.0, 0.0), segments=6, polyline=None, **kw):
    b = ws.ModelBuilder()
    if polyline is None:
        hair = ws.add_strands(b, [(0.0, 1.0, 0.0)], [direction], segments, length=0.2, mass=1e-3, **kw)
    else:
        hair = ws.add_strands(b, polylines=[polyline], segments=segments, mass=1e-3, **kw)
    return b, hair


def _sim(model, hair, integrator, drag=0.0, roots=True):
    forces = [ws.Gravity(), ws.StrandForce(hair)] + ([ws.Drag(linear=drag)] if drag else [])
    return ws.Simulator(model, integrator=integrator, forces=forces,
                        colliders=[ws.StrandRoots(hair)] if roots else [], warn_unstable=False, check_every=0)


def _assemble(hair, model, q, v, f, h, factor):
    """(A dense over the free vertices' positions, rhs over them, dv (stride, 3)) of the strand's
    implicit step, its twists eliminated (the Schur complement; ``factor`` = 0: the assembled matrix
    and right-hand side, dv untouched; 1: dv the kernel's solution)."""
    data = hair.bind(model)
    st, n = hair.stride, model.particle_count
    blocks = [wp.zeros(st, dtype=wp.mat44d, device=DEVICE) for _ in range(3)]
    rhs = wp.zeros(st, dtype=wp.vec4d, device=DEVICE)
    dv = wp.zeros(n, dtype=wp.vec3, device=DEVICE)
    arr = [wp.array(a.astype(np.float32), dtype=wp.vec3, device=DEVICE) for a in (q, v, f)]
    wp.launch(KI.strand_implicit_solve, 1, inputs=[*arr, model.particle_mass, hair.first, st, data["rest_length"],
                                                   data["bend_rest"], data["stretch_stiffness"], data["bend_stiffness"],
                                                   data["stretch_damping"], data["bend_damping"], data["root_normal"],
                                                   0.0, -1, 0.0, 0.0, h, *blocks, rhs, factor, dv], device=DEVICE)
    P, U1, U2 = (b.numpy()[None] for b in blocks)
    full = band_matrix(P, U1, U2)[0]
    x = np.array([4 * v + c for v in range(2, st) for c in range(3)])
    t = 4 * np.arange(st) + 3
    pinned = [0, 1, 2, 4, 5, 6]  # ghost's and root's x, y, z: decoupled (dv = 0 there)
    assert np.all(full[np.ix_(pinned, x)] == 0.0) and np.all(full[np.ix_(pinned, t)] == 0.0)
    r = rhs.numpy().reshape(-1)
    reduced = r[x] - full[np.ix_(x, t)] @ np.linalg.solve(full[np.ix_(t, t)], r[t])
    return band_to_dense(P, U1, U2, range(2, st))[0], reduced, dv.numpy()[2:].astype(np.float64)


def test_band_matrix_is_backward_eulers_and_the_band_solve_is_exact():
    """Straight strand stretched 1 % (no rest curvature: Gauss-Newton bending is the exact Hessian,
    the stretch springs' geometric term is positive): the assembled matrix equals M + h D + h^2 K
    with K, D the central-difference / exact Jacobians of the force kernel; on a curved strand the
    block band elimination equals a dense solve of the assembled matrix (float64)."""
    b, hair = _strand(segments=6, stretch_damping=0.05, bend_damping=2e-3)
    model = b.finalize(DEVICE)
    q = model.particle_q.numpy().astype(np.float64)
    idx = hair.particles()[0]
    q[idx[2:]] = q[idx[1]] + 1.01 * (q[idx[2:]] - q[idx[1]])
    h, m = 1.0 / 240.0, hair.mass[0] / hair.segments
    data = hair.bind(model)
    K, D = strand_jacobians(hair, data, q, [0])
    A, _, _ = _assemble(hair, model, q, np.zeros_like(q), np.zeros_like(q), h, 0)
    expected = m * np.eye(3 * hair.segments) + h * D[0] + h * h * K[0]
    np.testing.assert_allclose(A, expected, atol=2e-3 * np.abs(expected).max())

    arc = np.linspace(0.0, 1.0, 30)
    line = np.stack([0.2 * np.sin(arc), 1.0 - 0.2 * (1.0 - np.cos(arc)), 0.03 * arc], axis=1)
    b, hair = _strand(segments=7, polyline=line)
    model = b.finalize(DEVICE)
    q = model.particle_q.numpy().astype(np.float64)
    rng = np.random.default_rng(3)
    v = rng.normal(size=q.shape) * 0.1
    v[hair.particles()[0][:2]] = 0.0  # pinned ghost and root at rest
    f = rng.normal(size=q.shape) * 1e-3
    A, rhs, _ = _assemble(hair, model, q, v, f, 1.0 / 60.0, 0)
    _, _, dv = _assemble(hair, model, q, v, f, 1.0 / 60.0, 1)
    dense = np.linalg.solve(A, rhs)
    np.testing.assert_allclose(dv.reshape(-1), dense, rtol=1e-5, atol=1e-6 * np.abs(dense).max())


def test_band_matrix_holds_the_bending_frames_coupling_on_a_curl():
    """A helical strand (radius 1 cm, one turn per 5 cm, 24 segments) at its rest shape: bending
    residuals 0 and springs at rest length, so Gauss-Newton is the exact Hessian. The assembled
    matrix, its twists eliminated, equals M + h D + h^2 K with K, D the force kernel's Jacobians:
    the transported frames couple each vertex to every earlier one, and with the twists the
    matrix holds that coupling (K from float32 central differences: 2 % of its largest entry;
    the stiffness ratios lie within 10 % of 1, where the vertex's own frame alone gave up to 8.8
    on the wavy groom)."""
    s = np.linspace(0.0, 0.2, 200)
    line = np.stack([0.01 * np.sin(2 * np.pi * s / 0.05), 1.0 - s, 0.01 * (1 - np.cos(2 * np.pi * s / 0.05))], axis=1)
    b, hair = _strand(segments=24, polyline=line, stretch_damping=0.05, bend_damping=2e-3)
    model = b.finalize(DEVICE)
    q = model.particle_q.numpy().astype(np.float64)
    h, m = 1.0 / 240.0, hair.mass[0] / hair.segments
    K, D = strand_jacobians(hair, hair.bind(model), q, [0])
    A, _, _ = _assemble(hair, model, q, np.zeros_like(q), np.zeros_like(q), h, 0)
    Ka = (A - m * np.eye(len(A)) - h * D[0]) / (h * h)
    np.testing.assert_allclose(Ka, K[0], atol=0.02 * np.abs(K[0]).max())
    ratio = np.linalg.eigvals(np.linalg.solve(Ka, K[0])).real
    assert 0.9 < ratio.min() and ratio.max() < 1.1, (ratio.min(), ratio.max())


def test_released_strand_converges_at_first_order_to_the_numpy_chain():
    """Ghost and root let go, the strand thrown spinning: the whole chain is solved. Against the
    NumPy semi-implicit chain at h = 1e-4 s, the implicit step's error at 0.2 s halves each time its
    step halves (backward Euler is first order), and its centre of mass moves exactly as v += -g h,
    x += h v (internal forces and their Jacobians cancel in the sum)."""
    b, hair = _strand((1.0, 0.5, 0.0), segments=6, stretch_damping=0.0, bend_damping=0.0)
    idx = hair.particles()[0]
    vm = hair.mass[0] / hair.segments
    for i in idx[:2]:
        b.particle_mass[i] = vm
    model = b.finalize(DEVICE)
    data = hair.bind(model)
    x0 = model.particle_q.numpy().astype(np.float64)[idx]
    # spinning at 15 rad/s about its centre (and a bend): tension and bending work while it falls,
    # slowly enough for the stiff modes not to be excited
    v0 = np.cross(np.array([0.0, 0.0, 15.0]), x0 - x0.mean(axis=0)) + np.array([0.0, 0.0, 0.3]) * np.linspace(
        -1.0, 1.0, len(x0))[:, None] ** 2
    rest = data["rest_length"].numpy().astype(np.float64)
    normal = data["root_normal"].numpy()[0].astype(np.float64)
    ks, kb = hair.stretch_stiffness[0], hair.bend_stiffness[0]
    g = np.array([0.0, -G, 0.0])
    T = 0.2
    x, v = x0.copy(), v0.copy()
    for _ in range(round(T / 1e-4)):
        v = v + 1e-4 * (strand_forces_np(x, v, rest, np.zeros((hair.stride, 3)), ks, kb, 0.0, 0.0, normal) / vm + g)
        x = x + 1e-4 * v
    errors = []
    for h in (2e-3, 1e-3, 5e-4):
        sim = _sim(model, hair, StrandImplicitEuler(hair), roots=False)
        q = model.particle_q.numpy()
        q[idx] = x0.astype(np.float32)
        sim.state.positions.assign(q)
        qd = np.zeros_like(q)
        qd[idx] = v0.astype(np.float32)
        sim.state.velocities.assign(qd)
        n = round(T / h)
        for _ in range(n):
            sim.step(h)
        got = sim.state.positions.numpy()[idx].astype(np.float64)
        np.testing.assert_allclose(got.mean(axis=0), x0.mean(axis=0) + v0.mean(axis=0) * n * h
                                   - np.array([0.0, G, 0.0]) * h * h * n * (n + 1) / 2, atol=2e-6)
        errors.append(float(np.abs(got - x).max()))
    ratios = np.array(errors[1:]) / np.array(errors[:-1])
    assert np.all((0.4 < ratios) & (ratios < 0.6)), errors


def _hanging(damping, drag):
    b, hair = _strand((0.0, -1.0, 0.0), segments=8, stretch_damping=damping, bend_damping=damping / 20.0)
    model = b.finalize(DEVICE)
    sim = _sim(model, hair, StrandImplicitEuler(hair), drag=drag)
    ws.sag_free(sim)
    return model, hair, sim


@pytest.mark.parametrize("damping, drag", [(0.0, 0.0), (0.02, 2e-4)])
def test_swinging_strand_loses_energy_as_backward_euler_predicts(damping, drag):
    """A hanging strand (sag-free: straight down is the equilibrium) swinging in its lowest mode
    with a 5 mm tip amplitude. Backward Euler maps the mode's amplitude by 1 / (1 - h lambda) a
    step (lambda its eigenvalue of the linearised strand, damping and drag included), so its
    energy after n steps is E0 |1 - h lambda|^(-2n): undamped that is (1 + omega^2 h^2)^-n. The
    measured energy above the equilibrium (1/2 v M v + 1/2 dx K dx) follows it within 10 % over
    2 s at 4 steps per 1/60 s frame."""
    model, hair, sim = _hanging(damping, drag)
    data = hair.bind(model)
    x_eq = sim.state.positions.numpy().astype(np.float64)
    K, _ = strand_jacobians(hair, data, x_eq, [0])
    m = hair.mass[0] / hair.segments
    w2, modes = np.linalg.eigh(K[0] / m)
    phi = modes[:, 0].reshape(-1, 3)
    free = hair.free_particles()
    phi *= 5e-3 / np.linalg.norm(phi[-1])
    _, lam = strand_eigenvalues(hair, data, x_eq, drag=drag)
    lam1 = lam[0][np.argmin(np.abs(lam[0]))]
    q = x_eq.copy()
    q[free] += phi
    sim.state.positions.assign(q.astype(np.float32))
    h = 1.0 / 240.0

    def energy():
        dx = (sim.state.positions.numpy().astype(np.float64) - x_eq)[free].reshape(-1)
        v = sim.state.velocities.numpy().astype(np.float64)[free].reshape(-1)
        return 0.5 * m * v @ v + 0.5 * dx @ K[0] @ dx

    e0 = energy()
    per_step = 1.0 / abs(1.0 - h * lam1) ** 2
    if damping == 0.0:
        assert per_step == pytest.approx(1.0 / (1.0 + w2[0] * h * h), rel=1e-3)
    for n in range(1, 481):
        sim.step(h)
        if n % 120 == 0:
            measured, predicted = energy() / e0, per_step ** n
            assert measured == pytest.approx(predicted, rel=0.1), (n, measured, predicted)
    assert predicted < 0.9  # the prediction is not trivially 1


def test_swinging_strand_energy_never_grows():
    """A straight horizontal strand let swing under gravity, no damping: kinetic + gravitational +
    elastic energy (NumPy) never rises from one frame to the next under the implicit step at 1
    step per 1/60 s frame."""
    b, hair = _strand((1.0, 0.0, 0.0), segments=8, stretch_damping=0.0, bend_damping=0.0)
    model = b.finalize(DEVICE)
    sim = _sim(model, hair, StrandImplicitEuler(hair))
    data = hair.bind(model)
    idx = hair.particles()[0]
    rest = data["rest_length"].numpy().astype(np.float64)
    normal = data["root_normal"].numpy()[0].astype(np.float64)
    m = hair.mass[0] / hair.segments

    def energy():
        x = sim.state.positions.numpy().astype(np.float64)[idx]
        v = sim.state.velocities.numpy().astype(np.float64)[idx[2:]]
        return (0.5 * m * (v * v).sum() + m * G * x[2:, 1].sum()
                + strand_energy_np(x, rest, np.zeros((hair.stride, 3)), hair.stretch_stiffness[0],
                                   hair.bend_stiffness[0], normal))

    energies = [energy()]
    for _ in range(120):
        sim.step(1.0 / 60.0)
        energies.append(energy())
    drops = np.diff(energies)
    assert drops.max() <= 1e-7 * abs(energies[0] - min(energies)), drops.max()
    assert energies[0] - energies[-1] > 0.0


@pytest.mark.parametrize("style", ["wavy", "curly"])
def test_curled_grooms_at_32_segments_hold_4_steps_a_frame(style):
    """The hair scene's wavy and curly grooms at 32 segments (head still, sag-free, the strands
    kicked sideways so they swing, their tips at 0.36 m/s): the implicit step
    takes 4 steps per 1/60 s frame (``stable_dt()`` unrestricted) and over 2 s the total energy
    (kinetic + gravitational + elastic, NumPy) never rises from one frame to the next beyond
    float32 rounding (1e-5 of the energy dissipated), and it drops. (With the bending frames'
    coupling left out of the matrix these grooms needed 14-27 steps a frame and grew at 4.)"""
    from warpsim.scenes import get_scene

    scene = get_scene("hair")({"strands": 2, "segments": 32, "style": style, "motion": "still"}, device=DEVICE)
    assert scene.strand_steps(1.0 / 60.0) == 4
    hair, sim = scene.hair, scene.sim
    data = hair.bind(scene.model)
    rest, bend, normal = (data[k].numpy().astype(np.float64) for k in ("rest_length", "bend_rest", "root_normal"))
    m, st, idx = hair.mass / hair.segments, hair.stride, hair.particles()

    def energy():
        x = sim.state.positions.numpy().astype(np.float64)
        v = sim.state.velocities.numpy().astype(np.float64)
        e = 0.0
        for s in range(hair.strand_count):
            xs, vs, k = x[idx[s]], v[idx[s][2:]], slice(s * st, (s + 1) * st)
            e += (0.5 * m[s] * (vs * vs).sum() + m[s] * G * xs[2:, 1].sum()
                  + strand_energy_np(xs, rest[k], bend[k], hair.stretch_stiffness[s], hair.bend_stiffness[s],
                                     normal[s]))
        return e

    free = hair.free_particles()
    x = sim.state.positions.numpy()
    kick = np.zeros_like(x)
    kick[free] = np.array([0.3, 0.0, 0.2], np.float32) * ((0.55 - x[free, 1]) / 0.25)[:, None]
    sim.state.velocities.assign(kick)
    energies = [energy()]
    for _ in range(120):
        scene.advance(1.0 / 60.0, 1)
        energies.append(energy())
    dissipated = energies[0] - min(energies)
    assert dissipated > 0.0
    assert np.diff(energies).max() <= 1e-5 * dissipated, (np.diff(energies).max(), dissipated)


@pytest.mark.parametrize("style", ["straight", "curly"])
def test_hair_tips_follow_the_explicit_step(style):
    """The hair scene (straight and curly grooms) with the head turning and nodding from t = 0:
    tips of the implicit step (4 steps per 1/60 s frame) against the explicit step at half its stable step over 2 s. Backward
    Euler damps a mode of frequency omega by exp(-omega^2 h t / 2) in amplitude (per step
    1 / sqrt(1 + omega^2 h^2)) and lags its phase by about omega^3 h^2 t / 3; for the strands'
    slowest mode (omega_1 from the linearised strand) over t = 2 s and a tip excursion A (the
    explicit run's largest), the tips may differ by A (1 - exp(-omega_1^2 h t / 2) + omega_1^3 h^2
    t / 3); twice that is the tolerance (the head drives the strands continually, which keeps
    the gap below the free decay)."""
    from warpsim.scenes import get_scene

    params = {"strands": 6, "segments": 8, "still": 0.0, "motion": "turn_nod", "style": style}
    implicit = get_scene("hair")(params, device=DEVICE)
    explicit = get_scene("hair")({**params, "solver": "explicit"}, device=DEVICE)
    assert implicit.strand_steps(1.0 / 60.0) == 4
    tips = implicit.hair.tip_particles()
    x0 = implicit.sim.state.positions.numpy()[tips].copy()
    gap = excursion = 0.0
    for _ in range(120):
        implicit.advance(1.0 / 60.0, 1)
        explicit.advance(1.0 / 60.0, 1)
        a = implicit.sim.state.positions.numpy()[tips]
        e = explicit.sim.state.positions.numpy()[tips]
        gap = max(gap, float(np.linalg.norm(a - e, axis=1).max()))
        excursion = max(excursion, float(np.linalg.norm(e - x0, axis=1).max()))
    data = implicit.hair.bind(implicit.model)
    _, lam = strand_eigenvalues(implicit.hair, data, implicit.model.particle_q.numpy())
    w1 = float(np.abs(lam).min())
    h, t = 1.0 / 240.0, 2.0
    tolerance = 2.0 * excursion * (1.0 - math.exp(-w1 * w1 * h * t / 2.0) + w1 ** 3 * h * h * t / 3.0)
    assert excursion > 0.05  # the head moved the hair
    assert gap < tolerance, (gap, tolerance, excursion, w1)


def _curved_strand(integrator):
    arc = np.linspace(0.0, 1.0, 40)
    line = np.stack([0.15 * np.sin(1.2 * arc), 1.0 - 0.15 * (1.0 - np.cos(1.2 * arc)), 0.02 * arc], axis=1)
    b, hair = _strand(segments=6, polyline=line, stretch_damping=0.02, bend_damping=1e-3)
    model = b.finalize(DEVICE)
    sim = _sim(model, hair, integrator, drag=2e-4)
    ws.sag_free(sim)
    return hair, sim


def _grows(integrator, dt, steps):
    """True when a 10 um perturbation of the sag-free strand grows over ``steps`` steps of dt."""
    hair, sim = _curved_strand(integrator)
    free = hair.free_particles()
    x0 = sim.state.positions.numpy().copy()
    x = x0.copy()
    x[free] += (1e-5 * np.random.default_rng(0).normal(size=(len(free), 3))).astype(np.float32)
    sim.state.positions.assign(x)
    amplitude = []
    for k in range(steps):
        sim.step(dt)
        if k % (steps // 10) == steps // 10 - 1:
            a = float(np.abs(sim.state.positions.numpy()[free] - x0[free]).max())
            if not math.isfinite(a) or a > 1e-2:
                return True
            amplitude.append(a)
    return amplitude[-1] > 1.5 * amplitude[len(amplitude) // 2]


@pytest.mark.parametrize("integrator", ["semi_implicit_euler", "explicit_euler", "rk2", "rk4"])
def test_stable_dt_knows_strands(integrator):
    """A curved sag-free strand with stretch and bending dampers and air drag: the simulation's own
    limit (a perturbation grows above it and decays below) lies between ``stable_dt()`` / 1.05 and
    ``stable_dt()`` / 0.8, i.e. the estimate is never more than 5 % above it nor more than 20 %
    below. (Explicit Euler's lightly damped modes grow slowly just above its limit, 2 zeta^2 per
    step per unit of relative excess: it runs longer.)"""
    _, sim = _curved_strand(integrator)
    estimate = sim.stable_dt()
    assert sim.stability().limiting == "strand"
    steps = 8000 if integrator == "explicit_euler" else 800
    assert not _grows(integrator, estimate / 1.05, steps)
    assert _grows(integrator, estimate / 0.8, steps)


def test_implicit_step_is_unrestricted():
    hair, sim = _curved_strand("semi_implicit_euler")
    implicit = _sim(sim.model, hair, StrandImplicitEuler(hair), drag=2e-4)
    assert math.isinf(implicit.stable_dt())
    assert math.isfinite(sim.stable_dt())
