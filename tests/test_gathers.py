"""Fixed-order spring sums (issue 27): the CSR adjacency built at finalize, the per-particle gathers
of spring forces, spring Jacobians and the Baraff-Witkin assembly against the former float-atomic
scatter paths (which they replace by default), and bit equality of repeated runs."""

import numpy as np
import pytest
import warp as wp

import warpsim as ws
from warpsim.cloth.solver import ClothImplicitEuler, ClothSemiImplicitEuler, ClothSimulator
from warpsim.core.model import spring_adjacency

STEPS = 240


def _springy_cloth(device, n=6, extra_springs=0, seed=0):
    """A small cloth grid (structural, shear, bend springs) pinned at one corner, plus
    ``extra_springs`` random long-range springs (a particle then has many springs, and two springs
    may join the same pair)."""
    b = ws.ModelBuilder()
    ws.add_cloth_grid(b, (n, n), (0.5, 0.5), origin=(0.0, 1.0, 0.0), pin=["corner_00"], particle_mass=0.02)
    rng = np.random.default_rng(seed)
    for _ in range(extra_springs):
        i, j = rng.choice(b.particle_count, 2, replace=False)
        b.add_spring(int(i), int(j), stiffness=float(rng.uniform(5.0, 20.0)), damping=0.01)
    return b, b.finalize(device)


def test_csr_adjacency_lists_every_spring_exactly_twice_in_ascending_order():
    b, model = _springy_cloth("cpu", n=5, extra_springs=12)
    pairs = np.asarray(b.spring_indices)
    offsets, springs = model.particle_spring_offsets.numpy(), model.particle_springs.numpy()
    assert offsets[0] == 0 and offsets[-1] == 2 * len(pairs) == len(springs)
    assert np.array_equal(np.bincount(springs, minlength=len(pairs)), np.full(len(pairs), 2))  # exactly twice
    for i in range(model.particle_count):
        row = springs[offsets[i]:offsets[i + 1]]
        assert np.all(np.diff(row) > 0), i  # ascending: a fixed order, no spring twice in a row
        touching = np.flatnonzero((pairs[:, 0] == i) | (pairs[:, 1] == i))
        assert np.array_equal(row, touching), i  # exactly the springs touching i
    # no springs, and particles without springs: empty rows
    offsets, springs = spring_adjacency(np.zeros(0, dtype=np.int32), 3)
    assert np.array_equal(offsets, [0, 0, 0, 0]) and len(springs) == 0


def _force(model, deterministic, q=None, qd=None):
    force = ws.Springs(deterministic=deterministic)
    force.bind(model)
    f = wp.zeros(model.particle_count, dtype=wp.vec3, device=model.device)
    force.eval(model.particle_q if q is None else q, model.particle_qd if qd is None else qd,
               wp.zeros(1, dtype=float, device=model.device), 0.0, f)
    return f.numpy().astype(np.float64)


def test_gathered_spring_forces_equal_a_float64_reference_and_the_scatter(device):
    b, model = _springy_cloth(device, extra_springs=20)
    rng = np.random.default_rng(1)
    q = np.asarray(b.particle_q) + rng.normal(0.0, 0.02, (model.particle_count, 3))
    qd = rng.normal(0.0, 0.3, (model.particle_count, 3))
    qw, qdw = (wp.array(a.astype(np.float32), dtype=wp.vec3, device=device) for a in (q, qd))
    q32, qd32 = q.astype(np.float32).astype(np.float64), qd.astype(np.float32).astype(np.float64)
    expected = np.zeros_like(q)
    for (i, j), k, kd, rest in zip(b.spring_indices, b.spring_stiffness, b.spring_damping, b.spring_rest_length):
        u = q32[i] - q32[j]
        length = np.linalg.norm(u)
        d = u / length
        f = -(k * (length - rest) + kd * np.dot(qd32[i] - qd32[j], d)) * d
        expected[i] += f
        expected[j] -= f
    gathered, scattered = _force(model, True, qw, qdw), _force(model, False, qw, qdw)
    scale = np.abs(expected).max()
    assert np.abs(gathered - expected).max() <= 1e-5 * scale
    assert np.abs(gathered - scattered).max() <= 1e-5 * scale
    assert np.abs(gathered.sum(axis=0)).max() <= 1e-5 * scale  # springs conserve momentum


@pytest.mark.parametrize("integrator", ["implicit_euler", "semi_implicit_euler"])
def test_gathered_spring_jacobians_equal_the_scatter(integrator, device):
    del integrator  # (the same Jacobian serves both; parametrised to run each once per device)
    b, model = _springy_cloth(device, n=4, extra_springs=6)
    rng = np.random.default_rng(2)
    q = wp.array((np.asarray(b.particle_q) + rng.normal(0, 0.03, (model.particle_count, 3))).astype(np.float32),
                 dtype=wp.vec3, device=device)
    qd = wp.array(rng.normal(0, 0.5, (model.particle_count, 3)).astype(np.float32), dtype=wp.vec3, device=device)
    out = []
    for deterministic in (True, False):
        force = ws.Springs(deterministic=deterministic)
        force.bind(model)
        n, m = model.particle_count, force.jacobian_triplet_count()
        diag = wp.zeros(n, dtype=wp.mat33, device=device)
        rows, cols = wp.full(m, -1, dtype=int, device=device), wp.full(m, -1, dtype=int, device=device)
        values = wp.zeros(m, dtype=wp.mat33, device=device)
        force.eval_jacobian(q, qd, None, 0.0, -1e-4, -1e-2, diag, rows, cols, values)
        out.append((diag.numpy(), rows.numpy(), cols.numpy(), values.numpy()))
    (dg, rg, cg, vg), (ds, rs, cs, vs) = out
    assert np.array_equal(rg, rs) and np.array_equal(cg, cs) and (rg >= 0).all()  # every triplet written
    assert np.array_equal(vg, vs)  # one spring's block: the same arithmetic
    assert np.allclose(dg, ds, rtol=1e-6, atol=1e-6 * np.abs(ds).max())  # sums in another order


def _run_springs(device, deterministic, integrator="semi_implicit_euler", steps=STEPS):
    _, model = _springy_cloth(device, extra_springs=10)
    sim = ws.Simulator(model, integrator=integrator,
                       forces=[ws.Gravity(), ws.Springs(deterministic=deterministic)],
                       colliders=[ws.Plane(offset=0.6, restitution=0.2, friction=0.3)])
    for _ in range(steps):
        sim.step(1.0 / 600.0)
    return sim.state.positions.numpy(), sim.state.velocities.numpy()



@pytest.mark.parametrize("integrator", ["semi_implicit_euler", "implicit_euler", "rk4"])
def test_spring_gathers_follow_the_atomics_path_within_a_micrometre_over_240_steps(integrator):
    if integrator == "implicit_euler":  # one Newton iteration a step keeps the test fast
        integrator = ws.ImplicitEuler(newton_iterations=1)
    x_gather, _ = _run_springs("cpu", True, integrator)
    x_scatter, _ = _run_springs("cpu", False, integrator)
    assert np.abs(x_gather - x_scatter).max() <= 1e-6  # [m]
    assert x_gather[:, 1].min() < 0.9  # it moved (fell towards the plane)


def _run_cloth(device, integrator, steps=STEPS):
    _, model = _springy_cloth(device, n=8)
    # wind: a force summed before the springs, so gather and scatter round differently
    sim = ClothSimulator(model, integrator, forces=[ws.Gravity(), ws.Wind(coefficient=0.01)], use_graph=False)
    for _ in range(steps):
        sim.step(1.0 / 240.0 if isinstance(integrator, ClothImplicitEuler) else 1.0 / 1200.0)
    return sim.state.positions.numpy()


@pytest.mark.parametrize("name", ["implicit", "semi_implicit"])
def test_cloth_gathers_follow_the_atomics_path_within_a_micrometre_over_240_steps(name):
    def make(deterministic):
        if name == "implicit":
            return ClothImplicitEuler(deterministic=deterministic)
        return ClothSemiImplicitEuler(mode="scatter", deterministic=deterministic)

    x_gather, x_scatter = _run_cloth("cpu", make(True)), _run_cloth("cpu", make(False))
    assert np.abs(x_gather - x_scatter).max() <= 1e-6  # [m]
    assert x_gather[:, 1].min() < 0.9


def test_two_runs_are_bit_identical(device):
    for run in (lambda: _run_springs(device, True, steps=60)[0],
                lambda: _run_cloth(device, ClothImplicitEuler(), steps=30),
                lambda: _run_cloth(device, ClothSemiImplicitEuler(), steps=60)):
        first, second = run(), run()
        assert first.tobytes() == second.tobytes()


def test_deterministic_must_be_a_bool():
    with pytest.raises(TypeError, match="deterministic"):
        ClothImplicitEuler(deterministic="yes")
    with pytest.raises(TypeError, match="deterministic"):
        ClothSemiImplicitEuler(deterministic=1)
    with pytest.raises(TypeError, match="Springs deterministic"):
        ws.Springs(deterministic=None)


def test_the_cpus_two_pass_gather_gives_the_one_pass_gathers_bits():
    """On the CPU ``ws.Springs`` evaluates each spring once, then sums per particle; on GPUs one
    kernel evaluates springs at both ends. Both sum in the same CSR order: the same bits (broken
    springs skipped in both)."""
    from warpsim.kernels import forces as K

    b, model = _springy_cloth("cpu", extra_springs=15)
    broken = np.zeros(model.spring_count, dtype=np.int32)
    broken[::7] = 1
    model.spring_broken.assign(broken)
    rng = np.random.default_rng(3)
    q = wp.array((np.asarray(b.particle_q) + rng.normal(0, 0.02, (model.particle_count, 3))).astype(np.float32),
                 dtype=wp.vec3, device="cpu")
    qd = wp.array(rng.normal(0, 0.3, (model.particle_count, 3)).astype(np.float32), dtype=wp.vec3, device="cpu")
    seed = wp.array(rng.normal(0, 1.0, (model.particle_count, 3)).astype(np.float32), dtype=wp.vec3, device="cpu")
    two = wp.clone(seed)
    force = ws.Springs()
    force.bind(model)
    force.eval(q, qd, None, 0.0, two)
    one = wp.clone(seed)
    wp.launch(K.eval_springs_gather, model.particle_count,
              inputs=[q, qd, model.spring_indices, model.spring_rest_length, model.spring_stiffness,
                      model.spring_damping, model.spring_broken, model.particle_spring_offsets, model.particle_springs,
                      one], device="cpu")
    assert two.numpy().tobytes() == one.numpy().tobytes()
    assert not np.array_equal(two.numpy(), seed.numpy())
