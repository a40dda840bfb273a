"""Cloth: builder topology and mass, spring Jacobians vs finite differences, Baraff-Witkin steps
vs a dense NumPy solve, CG tolerance, stability at large steps, energy decay, static equilibrium,
explicit kernels vs NumPy, graph replay, collisions. Device "cpu", small grids."""

import numpy as np
import pytest
import warp as wp

import warpsim as ws
from warpsim.cloth.builder import add_cloth_grid, add_cloth_mesh, grid_springs
from warpsim.cloth.solver import ClothImplicitEuler, ClothSemiImplicitEuler, ClothSimulator, cloth_energy
from warpsim.bodies.colliders import Sphere, TriangleMesh

DEVICE = "cpu"
G = np.array([0.0, -9.81, 0.0])


# ------------------------------------------------------------------------------------------
# NumPy references (float64)
# ------------------------------------------------------------------------------------------
def model_arrays(model):
    return {
        "pairs": model.spring_indices.numpy().reshape(-1, 2).astype(np.int64),
        "rest": model.spring_rest_length.numpy().astype(np.float64),
        "k": model.spring_stiffness.numpy().astype(np.float64),
        "kd": model.spring_damping.numpy().astype(np.float64),
        "mass": model.particle_mass.numpy().astype(np.float64),
        "inv_mass": model.particle_inv_mass.numpy().astype(np.float64),
    }


def np_forces(a, x, v, gravity=G):
    """Spring + gravity forces (n, 3)."""
    f = a["mass"][:, None] * gravity[None, :]
    i, j = a["pairs"][:, 0], a["pairs"][:, 1]
    u = x[i] - x[j]
    l = np.linalg.norm(u, axis=1)
    d = u / l[:, None]
    s = a["k"] * (l - a["rest"]) + a["kd"] * np.einsum("sc,sc->s", v[i] - v[j], d)
    fs = -s[:, None] * d
    np.add.at(f, i, fs)
    np.add.at(f, j, -fs)
    return f


def np_jacobians(a, x, clamp=True):
    """Dense (3n, 3n) K = df/dx (damping's x-derivative dropped) and D = df/dv."""
    n = len(x)
    K = np.zeros((3 * n, 3 * n))
    D = np.zeros((3 * n, 3 * n))
    for (i, j), L, k, kd in zip(a["pairs"], a["rest"], a["k"], a["kd"]):
        u = x[i] - x[j]
        l = np.linalg.norm(u)
        d = u / l
        dd = np.outer(d, d)
        g = 1.0 - L / l
        if clamp:
            g = max(g, 0.0)
        Jx = -k * (dd + g * (np.eye(3) - dd))
        Jv = -kd * dd
        for M, J in ((K, Jx), (D, Jv)):
            M[3 * i:3 * i + 3, 3 * i:3 * i + 3] += J
            M[3 * j:3 * j + 3, 3 * j:3 * j + 3] += J
            M[3 * i:3 * i + 3, 3 * j:3 * j + 3] -= J
            M[3 * j:3 * j + 3, 3 * i:3 * i + 3] -= J
    return K, D


def bsr_dense(A):
    n = A.nrow
    nnz = A.nnz_sync()
    offsets, columns = A.offsets.numpy(), A.columns.numpy()
    values = A.values.numpy()[:nnz].astype(np.float64)
    out = np.zeros((3 * n, 3 * n))
    for r in range(n):
        for b in range(offsets[r], offsets[r + 1]):
            c = columns[b]
            out[3 * r:3 * r + 3, 3 * c:3 * c + 3] += values[b]
    return out


def small_cloth(resolution=(3, 3), pin=("corner_00", "corner_10"), stiffness=None, damping=None, particle_mass=0.1,
                **kwargs):
    b = ws.ModelBuilder()
    cloth = add_cloth_grid(b, resolution, (0.3, 0.3), (0.0, 1.0, 0.0), particle_mass=particle_mass, pin=list(pin or []),
                           stiffness=stiffness, damping=damping, **kwargs)
    return b, cloth


def perturbed(model, seed=0, scale=0.03, vscale=0.5):
    rng = np.random.default_rng(seed)
    x = model.particle_q.numpy().astype(np.float64) + scale * rng.standard_normal((model.particle_count, 3))
    v = vscale * rng.standard_normal((model.particle_count, 3))
    v[model.particle_inv_mass.numpy() == 0.0] = 0.0
    return x, v


def wp_vec3(a):
    return wp.array(np.asarray(a, dtype=np.float32), dtype=wp.vec3, device=DEVICE)


# ------------------------------------------------------------------------------------------
# Builder
# ------------------------------------------------------------------------------------------
def test_grid_topology_mass_and_placement():
    nu, nv = 4, 3
    b = ws.ModelBuilder()
    b.add_particle((5.0, 5.0, 5.0))  # an existing particle shifts the cloth's indices
    cloth = add_cloth_grid(b, (nu, nv), (2.0, 1.5), (1.0, 2.0, 3.0), u_axis=(0, 0, 2), v_axis=(0, -1, 0),
                           density=0.4, pin=["edge_v0", 19], structural=(100.0, 1.0), shear=(50.0, 0.5),
                           bend=(10.0, 0.1))
    rows, cols = nv + 1, nu + 1
    assert cloth.particle_offset == 1 and cloth.particle_count == rows * cols == b.particle_count - 1
    counts = {k: c for k, (_, c) in cloth.springs.items()}
    assert counts == {"structural": nu * rows + nv * cols, "shear": 2 * nu * nv,
                      "bend": (nu - 1) * rows + (nv - 1) * cols}
    first, count = cloth.springs["shear"]
    assert set(b.spring_stiffness[first:first + count]) == {50.0}
    assert set(b.spring_damping[first:first + count]) == {0.5}
    x = np.array(b.particle_q)
    # particle (i, j) at origin + i du u + j dv v, u = +Z (normalised), v = -Y
    assert np.allclose(x[cloth.index(2, 1)], (1.0, 2.0 - 1.5 / nv, 3.0 + 2 * 2.0 / nu))
    # structural rest lengths are the cell sizes, bend twice that
    rest = np.array(b.spring_rest_length)
    s0, sc = cloth.springs["structural"]
    assert np.allclose(sorted(set(np.round(rest[s0:s0 + sc], 9))), [1.5 / nv, 2.0 / nu])
    b0, bc = cloth.springs["bend"]
    assert np.allclose(sorted(set(np.round(rest[b0:b0 + bc], 9))), [3.0 / nv, 4.0 / nu])
    # lumped mass: density * area in all, a cell per interior particle, a quarter per corner
    m = np.array(b.particle_mass[1:])
    pinned = cloth.pinned - 1
    assert set(pinned.tolist()) == set(range(cols)) | {19}
    assert np.all(m[pinned] == 0.0)
    unpinned = ws.ModelBuilder()
    add_cloth_grid(unpinned, (nu, nv), (2.0, 1.5), density=0.4)
    m_all = np.array(unpinned.particle_mass)
    assert np.isclose(m_all.sum(), 0.4 * 2.0 * 1.5)
    free = np.setdiff1d(np.arange(len(m)), pinned)
    assert np.allclose(m[free], m_all[free])
    du, dv = 2.0 / nu, 1.5 / nv
    assert np.isclose(m[cloth.index(2, 1) - 1], 0.4 * du * dv)
    assert np.isclose(m_all[19], 0.4 * du * dv / 4) and np.isclose(m_all[cols], 0.4 * du * dv / 2)
    # triangles: 2 per cell, wound so that the normal is u x v = +Z x -Y = +X
    tri = cloth.triangles
    assert tri.shape == (2 * nu * nv, 3) and tri.min() == 1 and tri.max() == b.particle_count - 1
    normals = np.cross(x[tri[:, 1]] - x[tri[:, 0]], x[tri[:, 2]] - x[tri[:, 0]])
    assert np.all(normals[:, 0] > 0) and np.allclose(normals[:, 1:], 0.0)
    assert np.isclose(0.5 * np.linalg.norm(normals, axis=1).sum(), 2.0 * 1.5)
    assert cloth.face_vertex_indices.min() == 0 and len(cloth.face_vertex_counts) == len(tri)


def test_grid_centered_and_uniform_mass():
    b = ws.ModelBuilder()
    cloth = add_cloth_grid(b, 4, 2.0, (0.0, 1.0, 0.0), centered=True, particle_mass=0.1, pin="corners")
    x = np.array(b.particle_q)
    assert np.allclose(x.mean(axis=0), (0.0, 1.0, 0.0))
    assert np.allclose(x.min(axis=0), (-1.0, 1.0, -1.0)) and np.allclose(x.max(axis=0), (1.0, 1.0, 1.0))
    m = np.array(b.particle_mass)
    assert np.count_nonzero(m == 0.0) == 4 and np.allclose(m[m > 0], 0.1)
    # the benchmark's layout: same springs as Warp's benchmark_cloth.py (per kind)
    pairs = grid_springs(4, 4)
    assert len(pairs["structural"]) == 2 * 4 * 5 and len(pairs["shear"]) == 2 * 16 and len(pairs["bend"]) == 2 * 3 * 5
    assert cloth.spring_count == sum(len(p) for p in pairs.values())


def test_mesh_springs_and_mass():
    # two triangles sharing the diagonal 0-2 of the unit square
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 0, 1], [0, 0, 1]], dtype=float)
    t = np.array([[0, 1, 2], [0, 2, 3]])
    b = ws.ModelBuilder()
    cloth = add_cloth_mesh(b, v, t, density=3.0, pin=[3])
    pairs = np.array(b.spring_indices)
    s0, sc = cloth.springs["structural"]
    assert {tuple(sorted(p)) for p in pairs[s0:s0 + sc]} == {(0, 1), (1, 2), (0, 2), (2, 3), (0, 3)}
    h0, hc = cloth.springs["shear"]
    assert [tuple(sorted(p)) for p in pairs[h0:h0 + hc]] == [(1, 3)]
    assert cloth.springs["bend"][1] == 0
    # a third of each triangle's area (0.5 m^2, 3 kg/m^2) per corner; vertex 3 is pinned
    assert np.allclose(b.particle_mass, [1.0, 0.5, 1.0, 0.0])
    # a mesh of a regular grid: bend springs join skip-one neighbours along straight lines only
    b2 = ws.ModelBuilder()
    grid = add_cloth_grid(b2, (4, 4), (1.0, 1.0))
    b3 = ws.ModelBuilder()
    mesh = add_cloth_mesh(b3, np.array(b2.particle_q), grid.triangles)
    x = np.array(b3.particle_q)
    m0, mc = mesh.springs["bend"]
    for i, j in np.array(b3.spring_indices[m0:m0 + mc]):
        # the midpoint of every bend spring is a particle (its skipped neighbour)
        assert np.min(np.linalg.norm(x - 0.5 * (x[i] + x[j]), axis=1)) < 1e-9


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"resolution": (0, 3)}, "resolution"),
        ({"size": (1.0, -1.0)}, "size"),
        ({"u_axis": (1, 0, 0), "v_axis": (2, 0, 0)}, "parallel"),
        ({"density": 0.0}, "density"),
        ({"pin": ["top"]}, "unknown pin"),
        ({"pin": [99]}, "outside"),
        ({"structural": (-1.0, 0.0)}, "structural stiffness"),
        ({"radius": -0.1}, "radius"),
    ],
)
def test_grid_bad_input(kwargs, match):
    args = {"resolution": (3, 3), "size": (1.0, 1.0)}
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        add_cloth_grid(ws.ModelBuilder(), **args)


def test_mesh_bad_input():
    v = np.zeros((3, 3))
    v[1, 0] = v[2, 2] = 1.0
    with pytest.raises(ValueError, match="triangles"):
        add_cloth_mesh(ws.ModelBuilder(), v, [[0, 1, 5]])
    with pytest.raises(ValueError, match="repeats"):
        add_cloth_mesh(ws.ModelBuilder(), v, [[0, 1, 1]])
    with pytest.raises(ValueError, match="no triangle"):
        add_cloth_mesh(ws.ModelBuilder(), np.vstack([v, [[5.0, 5.0, 5.0]]]), [[0, 1, 2]])


# ------------------------------------------------------------------------------------------
# Jacobians and the implicit system
# ------------------------------------------------------------------------------------------
def bound_solver(model, forces=(), **options):
    system = ws.ParticleSystem(model, list(forces))
    solver = ClothImplicitEuler(**options)
    solver.prepare(system)
    return solver, system


def fd_jacobian(fun, x, eps=1e-6):
    n = x.size
    J = np.zeros((n, n))
    for c in range(n):
        e = np.zeros(n)
        e[c] = eps
        J[:, c] = (fun((x.reshape(-1) + e).reshape(x.shape)) - fun((x.reshape(-1) - e).reshape(x.shape))).reshape(-1) / (2 * eps)
    return J


def test_spring_jacobians_match_finite_differences():
    b, _ = small_cloth((2, 2), pin=None, structural=(800.0, 3.0), shear=(500.0, 2.0), bend=(90.0, 0.5))
    model = b.finalize(DEVICE)
    a = model_arrays(model)
    x, v = perturbed(model, seed=1, scale=0.04)
    # some springs compressed, some stretched
    l = np.linalg.norm(x[a["pairs"][:, 0]] - x[a["pairs"][:, 1]], axis=1)
    assert np.any(l < a["rest"]) and np.any(l > a["rest"])
    solver, _ = bound_solver(model, [], geometric="full")
    t = wp.zeros(1, dtype=float, device=DEVICE)
    Kx_fd = fd_jacobian(lambda y: np_forces(a, y, v, 0 * G), x)
    Kv_fd = fd_jacobian(lambda w: np_forces(a, x, w, 0 * G), v)
    # the kernels drop damping's position derivative: compare the stiffness part with kd = 0
    a0 = dict(a, kd=np.zeros_like(a["kd"]))
    Kx0_fd = fd_jacobian(lambda y: np_forces(a0, y, v, 0 * G), x)
    for ck, cd, ref in ((1.0, 0.0, None), (0.0, 1.0, Kv_fd)):
        solver.assemble(wp_vec3(x), wp_vec3(v), wp_vec3(v), t, 0.0, ck, cd, 0.0, 0.0, mass_scale=0.0)
        A = bsr_dense(solver.A)
        if ref is None:
            ref = Kx0_fd
            # and the dropped term is exactly what separates it from the full derivative
            assert not np.allclose(A, Kx_fd, atol=1e-2)
        assert np.allclose(A, ref, rtol=1e-4, atol=1e-3 * np.abs(ref).max())
    # b = cf f + cw K w: the force kernel matches NumPy and K w the assembled K
    w = np.random.default_rng(5).standard_normal(x.shape)
    solver.assemble(wp_vec3(x), wp_vec3(v), wp_vec3(w), t, 0.0, 0.0, 0.0, 1.0, 0.0, mass_scale=0.0)
    assert np.allclose(solver.rhs.numpy(), np_forces(a, x, v, 0 * G), rtol=1e-4, atol=1e-3)
    solver.assemble(wp_vec3(x), wp_vec3(v), wp_vec3(w), t, 0.0, 0.0, 0.0, 0.0, 1.0, mass_scale=0.0)
    assert np.allclose(solver.rhs.numpy().reshape(-1), Kx0_fd @ w.reshape(-1), rtol=1e-4, atol=1e-2)


def test_clamped_stiffness_is_negative_semidefinite():
    b, _ = small_cloth((2, 2), pin=None, stiffness=1000.0, damping=0.0)
    model = b.finalize(DEVICE)
    a = model_arrays(model)
    x0 = model.particle_q.numpy().astype(np.float64)
    x = x0.mean(0) + 0.6 * (x0 - x0.mean(0))  # every spring compressed to 60 %
    x += 0.01 * np.random.default_rng(2).standard_normal(x.shape)
    t = wp.zeros(1, dtype=float, device=DEVICE)
    eig = {}
    for mode in ("clamped", "full"):
        solver, _ = bound_solver(model, [], geometric=mode)
        solver.assemble(wp_vec3(x), wp_vec3(0 * x), wp_vec3(0 * x), t, 0.0, 1.0, 0.0, 0.0, 0.0, mass_scale=0.0)
        K = bsr_dense(solver.A)
        assert np.allclose(K, K.T, atol=1e-3)
        assert np.allclose(K, np_jacobians(a, x, clamp=(mode == "clamped"))[0], rtol=1e-4, atol=1e-2)
        eig[mode] = np.linalg.eigvalsh(0.5 * (K + K.T))
    scale = np.abs(eig["clamped"]).max()
    assert eig["clamped"].max() <= 1e-5 * scale          # negative semi-definite
    assert eig["full"].max() > 0.05 * scale              # the exact one is indefinite under compression
    # stretched: clamping changes nothing
    xs = x0.mean(0) + 1.3 * (x0 - x0.mean(0))
    Ks = []
    for mode in ("clamped", "full"):
        solver, _ = bound_solver(model, [], geometric=mode)
        solver.assemble(wp_vec3(xs), wp_vec3(0 * xs), wp_vec3(0 * xs), t, 0.0, 1.0, 0.0, 0.0, 0.0, mass_scale=0.0)
        Ks.append(bsr_dense(solver.A))
    assert np.allclose(Ks[0], Ks[1])


@pytest.mark.parametrize("drag", [0.0, 0.3])
def test_one_step_is_baraff_witkin_exactly(drag):
    """(M - h D - h^2 K) dv = h (f0 + h K v0) at (x0, v0), pinned rows/columns removed, then
    v1 = v0 + dv, x1 = x0 + h v1 — against a dense float64 solve (with linear drag -c v on
    the free particles, D gains -c I: other forces enter through their own Jacobians)."""
    b, cloth = small_cloth((3, 2), stiffness=2000.0, damping=4.0)
    model = b.finalize(DEVICE)
    a = model_arrays(model)
    x0, v0 = perturbed(model, seed=3, scale=0.02, vscale=0.3)
    v0[cloth.pinned] = (0.0, 0.0, 0.2)  # kinematic pins keep moving
    h = 1.0 / 30.0
    forces = [ws.Gravity()] + ([ws.Drag(linear=drag)] if drag else [])
    sim = ClothSimulator(model, ClothImplicitEuler(cg_tol=1e-7), forces=forces, use_graph=False)
    sim.state.positions.assign(x0.astype(np.float32))
    sim.state.velocities.assign(v0.astype(np.float32))
    sim.step(h)
    K, D = np_jacobians(a, x0)
    n = model.particle_count
    free3 = np.repeat(a["inv_mass"] > 0, 3)
    D = D - drag * np.diag(free3.astype(float))
    f0 = np_forces(a, x0, v0) - drag * v0 * (a["inv_mass"] > 0)[:, None]
    M = np.kron(np.diag(a["mass"]), np.eye(3))
    A = M - h * D - h * h * K
    rhs = h * (f0.reshape(-1) + h * K @ v0.reshape(-1))
    free = np.repeat(a["inv_mass"] > 0, 3)
    dv = np.zeros(3 * n)
    dv[free] = np.linalg.solve(A[np.ix_(free, free)], rhs[free])
    v1 = v0 + dv.reshape(n, 3)
    x1 = x0 + h * v1
    assert np.allclose(sim.state.velocities.numpy(), v1, atol=2e-4 * np.abs(v1).max())
    assert np.allclose(sim.state.positions.numpy(), x1, atol=1e-5)
    assert np.allclose(sim.state.positions.numpy()[cloth.pinned], x0[cloth.pinned] + h * v0[cloth.pinned], atol=1e-6)
    # it differs from a Newton step of backward Euler linearised at x0 + h v0 (ws.ImplicitEuler)
    ref = ws.Simulator(model, ws.ImplicitEuler(newton_iterations=1, cg_tol=1e-7), forces=[ws.Gravity()])
    ref.state.positions.assign(x0.astype(np.float32))
    ref.state.velocities.assign(v0.astype(np.float32))
    ref.step(h)
    assert not np.allclose(ref.state.velocities.numpy(), v1, atol=2e-4 * np.abs(v1).max())


@pytest.mark.parametrize("linear_solver", ["block_cg", "warp_cg"])
def test_cg_meets_tolerance_every_step(linear_solver):
    b, _ = small_cloth((4, 4), stiffness=1.0e4, damping=2.0)
    model = b.finalize(DEVICE)
    solver = ClothImplicitEuler(cg_tol=1e-5, cg_max_iterations=300, linear_solver=linear_solver, record_history=True)
    sim = ClothSimulator(model, solver, use_graph=False)
    steps = 6 if linear_solver == "warp_cg" else 20
    for _ in range(steps):
        sim.step(1.0 / 60.0)
        # the true residual of the system left in A, b, dv
        A = bsr_dense(solver.A)
        r = solver.rhs.numpy().reshape(-1) - A @ solver.dv.numpy().reshape(-1)
        assert np.linalg.norm(r) <= 2.0 * solver.last_cg_tolerance
        assert np.isclose(solver.last_cg_tolerance, 1e-5 * np.linalg.norm(solver.rhs.numpy()), rtol=1e-3)
    assert len(solver.history) == steps
    for newton, iterations, residual, tolerance in solver.history:
        assert newton == 1 and 0 < iterations < 300 and residual <= tolerance


def test_block_cg_matches_warp_cg():
    b, _ = small_cloth((4, 3), stiffness=5.0e3, damping=1.0)
    model = b.finalize(DEVICE)
    out = []
    for linear_solver in ("block_cg", "warp_cg"):
        sim = ClothSimulator(model, ClothImplicitEuler(cg_tol=1e-6, linear_solver=linear_solver), use_graph=False)
        for _ in range(3):
            sim.step(1.0 / 60.0)
        out.append(sim.state.positions.numpy())
    assert np.allclose(out[0], out[1], atol=1e-5)


# ------------------------------------------------------------------------------------------
# Stability, energy, equilibrium
# ------------------------------------------------------------------------------------------
def stiff_cloth():
    """k = 1e5 N/m, 0.1 kg per particle, two corners pinned: omega h ~ 17 at dt = 1/60."""
    b, _ = small_cloth((6, 6), stiffness=1.0e5, damping=1.0, particle_mass=0.1)
    return b.finalize(DEVICE)


def test_stiff_cloth_implicit_stable_explicit_diverges():
    model = stiff_cloth()
    a = model_arrays(model)
    for sim in (ws.Simulator(model, "semi_implicit_euler"), ClothSimulator(model, "semi_implicit_euler")):
        with pytest.raises(ws.SimulationError, match="implicit") as err:
            sim.run(120, frame_dt=1.0 / 60.0, substeps=1)
        assert err.value.frame is not None and err.value.frame < 120
    sim = ClothSimulator(model, "implicit_euler")
    sim.run(120, frame_dt=1.0 / 60.0, substeps=1)
    x = sim.state.positions.numpy().astype(np.float64)
    v = sim.state.velocities.numpy()
    assert np.all(np.isfinite(x)) and np.abs(v).max() < 5.0
    strain = np.linalg.norm(x[a["pairs"][:, 0]] - x[a["pairs"][:, 1]], axis=1) / a["rest"] - 1.0
    assert np.abs(strain).max() < 0.02
    # it hangs below the pinned edge: the free corners fell
    assert x[:, 1].min() < 1.0 - 0.2


@pytest.mark.parametrize("newton_iterations", [1, 3])
def test_energy_decreases_without_forcing(newton_iterations):
    b, _ = small_cloth((5, 5), pin=None, structural=(2000.0, 2.0), shear=(1000.0, 1.0), bend=(200.0, 0.2))
    model = b.finalize(DEVICE)
    x0, v0 = perturbed(model, seed=4, scale=0.03, vscale=1.0)
    sim = ClothSimulator(model, ClothImplicitEuler(newton_iterations=newton_iterations, cg_tol=1e-6), forces=[],
                         use_graph=False)
    sim.state.positions.assign(x0.astype(np.float32))
    sim.state.velocities.assign(v0.astype(np.float32))
    energy = [sum(cloth_energy(model, sim.state.positions, sim.state.velocities)[:2])]
    for _ in range(60):
        sim.step(1.0 / 60.0)
        energy.append(sum(cloth_energy(model, sim.state.positions, sim.state.velocities)[:2]))
    energy = np.array(energy)
    assert np.all(np.diff(energy) <= 1e-6 * energy[0])
    assert energy[-1] < 0.2 * energy[0]


def np_static_curtain(a, x0, free, gravity=G, iterations=50):
    """Newton on f(x) = 0 over the free particles' x, y (a curtain in the XY plane stays in it)."""
    x = x0.copy()
    dofs = np.flatnonzero(np.repeat(free, 3) & np.tile([True, True, False], len(x)))
    for _ in range(iterations):
        f = np_forces(dict(a, kd=0 * a["kd"]), x, 0 * x, gravity).reshape(-1)
        K = np_jacobians(a, x, clamp=False)[0]
        step = np.linalg.solve(K[np.ix_(dofs, dofs)], -f[dofs])
        x.reshape(-1)[dofs] += step
        if np.abs(step).max() < 1e-13:
            break
    return x


def test_hanging_cloth_comes_to_static_equilibrium():
    b = ws.ModelBuilder()
    add_cloth_grid(b, (4, 4), (0.4, 0.4), (0.0, 1.0, 0.0), u_axis=(1, 0, 0), v_axis=(0, -1, 0), particle_mass=0.02,
                   structural=(60.0, 0.5), shear=(30.0, 0.2), bend=(6.0, 0.05), pin=["edge_v0"])
    model = b.finalize(DEVICE)
    a = model_arrays(model)
    free = a["inv_mass"] > 0
    sim = ClothSimulator(model, ClothImplicitEuler(cg_tol=1e-7), use_graph=True)
    sim.run(240, frame_dt=1.0 / 30.0)
    x = sim.state.positions.numpy().astype(np.float64)
    f = np_forces(a, x, 0 * x)[free]
    mg = 0.02 * 9.81
    assert np.abs(f).max() < 2e-3 * mg
    assert np.abs(sim.state.velocities.numpy()).max() < 1e-3
    x_static = np_static_curtain(a, model.particle_q.numpy().astype(np.float64), free)
    assert np.abs(np_forces(a, x_static, 0 * x_static)[free]).max() < 1e-9
    sag = model.particle_q.numpy()[:, 1].min() - x_static[:, 1].min()
    assert sag > 0.01  # gravity visibly stretched it
    assert np.abs(x - x_static).max() < 1e-3 * sag + 2e-6


# ------------------------------------------------------------------------------------------
# Explicit kernels, graph replay, collisions
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("mode", ["scatter", "gather", "owner", "lanes"])
def test_semi_implicit_kernels_match_numpy(mode):
    b, cloth = small_cloth((4, 3), stiffness=500.0, damping=2.0)
    model = b.finalize(DEVICE)
    a = model_arrays(model)
    x, v = perturbed(model, seed=6, scale=0.01, vscale=0.2)
    v[cloth.pinned] = (0.1, 0.0, 0.0)
    h = 1.0 / 600.0
    sim = ws.Simulator(model, ClothSemiImplicitEuler(mode))
    sim.state.positions.assign(x.astype(np.float32))
    sim.state.velocities.assign(v.astype(np.float32))
    free = (a["inv_mass"] > 0)[:, None]
    for _ in range(10):
        sim.step(h)
        f = np_forces(a, x, v)
        v = v + h * free * a["inv_mass"][:, None] * f
        x = x + h * v
    assert np.allclose(sim.state.positions.numpy(), x, atol=1e-5)
    assert np.allclose(sim.state.velocities.numpy(), v, atol=1e-3)
    # the force handed back to the Simulator is the one at the start of the last step
    assert np.allclose(sim.state.forces.numpy(), f, rtol=1e-3, atol=1e-3)


def test_owner_mode_gives_the_scatter_modes_bits():
    """"owner" (each spring evaluated once by its lower end, written to both CSR entries) sums in
    the scatter mode's order: the same bits after captured frames with wind, a floor and a
    sphere, with springs whose first end is the higher index and distinct parameters, changed in
    place half way (both read the model's arrays)."""
    def run(mode):
        b, _ = small_cloth((6, 5), stiffness=400.0, damping=1.0)
        b.spring_indices = [(int(j), int(i)) for i, j in np.asarray(b.spring_indices).reshape(-1, 2)]
        b.spring_stiffness = list(np.random.default_rng(2).uniform(300.0, 500.0, b.spring_count))
        sim = ClothSimulator(b.finalize(DEVICE), ClothSemiImplicitEuler(mode),
                             forces=[ws.Gravity(), ws.Wind(coefficient=0.02)],
                             colliders=[ws.Plane(offset=0.9, restitution=0.0, friction=0.3),
                                        Sphere((0.15, 0.95, 0.15), 0.04, restitution=0.0, friction=0.3)])
        for frame in range(20):
            if frame == 10:
                sim.model.spring_stiffness.assign(0.5 * sim.model.spring_stiffness.numpy())
            sim.frame(1.0 / 60.0, 16)
        return sim.state.positions.numpy(), sim.state.velocities.numpy(), sim.integrator.mode

    x_owner, v_owner, mode = run(None)
    x_scatter, v_scatter, _ = run("scatter")
    assert mode == "owner"  # the CPU default
    assert x_owner.tobytes() == x_scatter.tobytes() and v_owner.tobytes() == v_scatter.tobytes()
    assert 0.88 < x_owner[:, 1].min() < 0.95  # it fell onto the floor, which held it


@pytest.mark.parametrize("distinct", [False, True])
def test_gather_adjacency_layouts_match_numpy(distinct):
    """The gather kernel packs (other end, parameter kind) into 4 bytes when there are at most
    256 distinct (rest, k, kd) triples, else stores them per entry; both step like NumPy."""
    b, _ = small_cloth((10, 10), stiffness=400.0, damping=1.0)
    if distinct:  # one stiffness per spring: 600 distinct triples
        b.spring_stiffness = list(np.random.default_rng(7).uniform(300.0, 500.0, b.spring_count))
    model = b.finalize(DEVICE)
    a = model_arrays(model)
    integrator = ClothSemiImplicitEuler("gather")
    sim = ClothSimulator(model, integrator, use_graph=False)
    assert integrator.adjacency.dtype == (wp.vec4 if distinct else wp.uint32)
    x, v = model.particle_q.numpy().astype(np.float64), np.zeros((model.particle_count, 3))
    h = 1.0 / 600.0
    sim.frame(5 * h, 5)
    free = (a["inv_mass"] > 0)[:, None]
    for _ in range(5):
        v = v + h * free * a["inv_mass"][:, None] * np_forces(a, x, v)
        x = x + h * v
    assert np.allclose(sim.state.positions.numpy(), x, atol=1e-5)


@pytest.mark.parametrize("integrator, substeps", [("semi_implicit_euler", 5), ("implicit_euler", 2)])
def test_graph_frames_match_eager_steps(integrator, substeps):
    b, _ = small_cloth((5, 5), stiffness=800.0, damping=1.0)
    model = b.finalize(DEVICE)
    out = []
    for use_graph in (False, True):
        sim = ClothSimulator(model, integrator, colliders=[ws.Plane(offset=0.9, restitution=0.0, friction=0.3)],
                             use_graph=use_graph)
        frames = []
        sim.run(4, frame_dt=1.0 / 60.0, substeps=substeps, callback=lambda f, s, times=frames: times.append(s.time))
        out.append(sim.state.positions.numpy())
        assert np.allclose(frames, np.arange(1, 5) / 60.0) and sim.step_count == 4 * substeps
        assert np.isclose(float(sim._time.numpy()[0]), 4 / 60.0)
    assert np.allclose(out[0], out[1], atol=1e-6)
    assert out[1][:, 1].min() >= 0.9 - 1e-5


@pytest.mark.parametrize("integrator", ["implicit_euler", "semi_implicit_euler"])
def test_cloth_on_plane_friction(integrator):
    """A flat sheet sliding on the floor: without friction the floor only pushes normally, so the
    horizontal momentum stays; with Coulomb friction it stops."""
    speeds = {}
    for mu in (0.0, 0.8):
        b = ws.ModelBuilder()
        add_cloth_grid(b, (4, 4), (0.4, 0.4), (0.0, 0.02, 0.0), particle_mass=0.01, stiffness=100.0, damping=0.1,
                       velocity=(1.0, 0.0, 0.0))
        model = b.finalize(DEVICE)
        sim = ClothSimulator(model, integrator, colliders=[ws.Plane(restitution=0.0, friction=mu, mode="project")])
        sim.run(30, frame_dt=1.0 / 60.0, substeps=1 if integrator == "implicit_euler" else 8)
        x, v = sim.state.positions.numpy(), sim.state.velocities.numpy()
        assert x[:, 1].min() >= -1e-6
        m = model.particle_mass.numpy()
        speeds[mu] = (m[:, None] * v).sum(0)[0] / m.sum()
    assert speeds[0.0] == pytest.approx(1.0, abs=0.02)
    assert speeds[0.8] < 0.05


@pytest.mark.parametrize("integrator", ["implicit_euler", "semi_implicit_euler"])
def test_cloth_drapes_on_sphere_with_thickness(integrator):
    """A sheet dropped on a sphere: no particle ever comes closer to the surface than the
    thickness offset, the sheet's centre rests on top at r + thickness and its corners hang down
    past the equator."""
    r, thickness, c = 0.2, 0.02, np.array([0.0, 0.3, 0.0])
    b = ws.ModelBuilder()
    cloth = add_cloth_grid(b, (8, 8), (0.6, 0.6), (0.0, 0.6, 0.0), centered=True, particle_mass=0.005,
                           structural=(50.0, 0.05), shear=(20.0, 0.02), bend=(5.0, 0.01))
    model = b.finalize(DEVICE)
    sphere = Sphere(tuple(c), r, restitution=0.0, friction=0.8, thickness=thickness)
    sim = ClothSimulator(model, integrator, colliders=[sphere, ws.Plane(restitution=0.0, friction=0.8)])
    closest = []
    sim.run(90, frame_dt=1.0 / 60.0, substeps=1 if integrator == "implicit_euler" else 10,
            callback=lambda f, s: closest.append((np.linalg.norm(s.state.positions.numpy() - c, axis=1) - r).min()))
    assert min(closest) >= thickness - 1e-4
    x = sim.state.positions.numpy()
    top = x[cloth.index(4, 4)]
    assert np.allclose(top, c + (0.0, r + thickness, 0.0), atol=2e-3)
    assert 0.05 < x[:, 1].min() < c[1]


def test_cloth_rests_on_triangle_mesh():
    """A thin two-triangle floor at y = 0.25 (a TriangleMesh, thickness 0.01): the sheet lands
    and lies flat at 0.26 m."""
    quad = np.array([[-1.0, 0.25, -1.0], [1.0, 0.25, -1.0], [1.0, 0.25, 1.0], [-1.0, 0.25, 1.0]])
    mesh = TriangleMesh(quad, [[0, 2, 1], [0, 3, 2]], restitution=0.0, friction=0.5, thickness=0.01)
    b = ws.ModelBuilder()
    add_cloth_grid(b, (5, 5), (0.5, 0.5), (0.0, 0.5, 0.0), centered=True, particle_mass=0.01, stiffness=100.0,
                   damping=0.1)
    model = b.finalize(DEVICE)
    sim = ClothSimulator(model, "implicit_euler", colliders=[mesh])
    sim.run(60, frame_dt=1.0 / 60.0)
    y = sim.state.positions.numpy()[:, 1]
    assert np.allclose(y, 0.26, atol=1e-3)
    assert np.abs(sim.state.velocities.numpy()).max() < 1e-2


@pytest.mark.parametrize("how", ["motion", "set_transform"])
def test_moving_colliders_match_eager_frames(how):
    """A sphere on a ``motion`` path (frames then run eagerly) or moved by ``set_transform``
    between frames (graphs re-captured): the captured-frame simulator gives the eager result
    (collider poses are launch parameters a graph would freeze)."""
    b, _ = small_cloth((4, 4), stiffness=300.0, damping=0.5)
    model = b.finalize(DEVICE)
    out = []
    for use_graph in (False, True):
        if how == "motion":
            sphere = Sphere((0.15, 0.85, -0.15), 0.08, friction=0.2, motion=lambda t: ((0.0, 0.5 * t, 0.0), None))
        else:
            sphere = Sphere((0.15, 0.9, -0.15), 0.08, friction=0.2)
        sim = ClothSimulator(model, "implicit_euler", colliders=[sphere], use_graph=use_graph)
        for frame in range(8):
            if frame == 4 and how == "set_transform":
                sphere.set_transform((0.0, 0.05, 0.0))
            sim.frame(1.0 / 60.0, 2)
        out.append(sim.state.positions.numpy())
        if how == "motion":
            assert np.isclose(sphere.time, 8 / 60.0)  # its clock advanced every sub-step
        assert np.isclose(sim.time, 8 / 60.0)
    assert np.allclose(out[0], out[1], atol=1e-6)
    free = ClothSimulator(model, "implicit_euler", use_graph=False)
    free.run(8, frame_dt=1.0 / 60.0, substeps=2)
    assert np.abs(out[1] - free.state.positions.numpy()).max() > 0.02  # the sphere did push the cloth


def test_solver_bad_input():
    with pytest.raises(ValueError, match="newton_iterations"):
        ClothImplicitEuler(newton_iterations=0)
    with pytest.raises(ValueError, match="geometric"):
        ClothImplicitEuler(geometric="exact")
    with pytest.raises(ValueError, match="linear_solver"):
        ClothImplicitEuler(linear_solver="lu")
    with pytest.raises(ValueError, match="mode"):
        ClothSemiImplicitEuler("fused")
    b, _ = small_cloth((2, 2))
    model = b.finalize(DEVICE)
    with pytest.raises(ValueError, match="unknown integrator"):
        ClothSimulator(model, "backward_euler")
    sim = ClothSimulator(model, "implicit_euler")
    with pytest.raises(ValueError, match="substeps"):
        sim.frame(1.0 / 60.0, 0)
    with pytest.raises(ValueError, match="dt"):
        sim.frame(-1.0, 1)


def run_example(name, args, tmp_path):
    import os
    import subprocess
    import sys
    from pathlib import Path

    script = Path(__file__).resolve().parents[1] / "examples" / name
    result = subprocess.run([sys.executable, str(script), *args], cwd=tmp_path, env=dict(os.environ, WARP_QUIET="1"),
                            capture_output=True, text=True, timeout=600, check=False)
    assert result.returncode == 0, result.stderr[-3000:]
    return result


def test_example_cloth_implicit(tmp_path):
    """The example compares both integrators at dt = 1/60: semi-implicit diverges, implicit runs
    and reports CG iterations within tolerance."""
    result = run_example("cloth_implicit.py", ["--frames", "4", "--resolution", "6", "--stiffness", "1e5",
                                               "--out", "c.usda"], tmp_path)
    assert "semi-implicit Euler at dt = 0.0166667 s diverged" in result.stdout
    rows = [line.split() for line in result.stdout.splitlines() if line.strip()[:1].isdigit()]
    assert [int(r[0]) for r in rows] == [1, 2, 3, 4]
    assert all(0 < int(r[1]) and float(r[2]) <= float(r[3]) for r in rows)
    assert (tmp_path / "c.usda").exists()


def test_example_cloth_drape(tmp_path):
    result = run_example("cloth_drape.py", ["--frames", "10", "--resolution", "6", "--out", "d.usda"], tmp_path)
    rows = [line.split() for line in result.stdout.splitlines() if line.strip()[:1].isdigit()]
    assert [int(r[0]) for r in rows] == [10] and float(rows[0][2]) >= 0.01 - 1e-4
    from warpsim.usd.validate import validate_cache

    assert validate_cache(str(tmp_path / "d.usda")) == []


def test_cloth_scenes_registered_and_checked():
    from warpsim.scenes import get_scene

    for name in ("cloth", "drape"):
        scene_cls = get_scene(name)
        assert set(scene_cls.params["integrator"].choices) == {"implicit_euler", "semi_implicit_euler", "vbd"}
        with pytest.raises(ValueError, match="resolution"):
            scene_cls({"resolution": 0}, device=DEVICE)
    scene = get_scene("cloth")({"resolution": 3, "integrator": "semi_implicit_euler"}, device=DEVICE)
    assert isinstance(scene.sim.integrator, ClothSemiImplicitEuler) and scene.steps_per_substep == 40
    assert len(scene.cloth.pinned) == 2 and scene.cloth.triangles.shape == (18, 3)


@pytest.mark.parametrize("integrator, substeps", [("semi_implicit_euler", 4), ("implicit_euler", 1)])
@pytest.mark.parametrize("use_graph", [False, True])
def test_frames_allocate_nothing(integrator, substeps, use_graph, monkeypatch):
    """After the first frame (buffers, graph), stepping allocates no device memory: every host
    allocation on the CPU device goes through its allocator, counted here."""
    b, _ = small_cloth((4, 4), stiffness=500.0, damping=1.0)
    model = b.finalize(DEVICE)
    sim = ClothSimulator(model, integrator, colliders=[ws.Plane(offset=0.9), Sphere((0.1, 0.8, -0.1), 0.1)],
                         use_graph=use_graph)
    for _ in range(2):
        sim.frame(1.0 / 60.0, substeps)
    allocator = wp.get_device(DEVICE).default_allocator
    sizes = []
    allocate = allocator.allocate
    monkeypatch.setattr(allocator, "allocate", lambda size: sizes.append(size) or allocate(size))
    wp.zeros(4, dtype=float, device=DEVICE)
    assert sizes == [16]  # the counter sees allocations
    sizes.clear()
    for _ in range(3):
        sim.frame(1.0 / 60.0, substeps)
    monkeypatch.undo()
    assert sizes == []
