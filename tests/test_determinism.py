"""Bit-reproducible stages (issue 27): the fixed-order reductions, the FLIP particle-to-grid gathers
over the cell-sorted particle list, cell ranks and appends in cell order, PBF's iteration control,
the pressure solver's domain sums, the level-set volume, boids' food and marching cubes' output
order. Each converted stage is checked against NumPy or against its former float-atomic path
(within float rounding), and whole runs against a second identical run (bit for bit). Small sizes;
the tests taking ``device`` also run on CUDA when present (where atomics would differ run to run)."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest
import warp as wp

import warpsim as ws
from warpsim.core.reduction import FixedOrderReduction
from warpsim.grid_fluids.flip import FlipLiquid
from warpsim.grid_fluids.levelset import LevelSet
from warpsim.grid_fluids.mac_grid import AIR, FLUID, SOLID, MacGrid
from warpsim.grid_fluids.particles import GridParticles
from warpsim.grid_fluids.pressure import PressureSolver
from warpsim.kernels import grid as KG
from warpsim.particle_fluids.pbf import ParticleFluid, fluid_block

DEV = "cpu"
ROOT = Path(__file__).resolve().parents[1]


# ------------------------------------------------------------------------ fixed-order reductions
@pytest.mark.parametrize("count,slots,group", [(1, 4096, 64), (1000, 4096, 64), (100_003, 256, 8), (77, 1, 2)])
def test_fixed_order_sum_and_max_match_numpy(count, slots, group):
    rng = np.random.default_rng(count)
    values = rng.normal(size=count + 5).astype(np.float32)  # the tail beyond count is ignored
    red = FixedOrderReduction(2, first_max_column=1, slots=slots, group=group, device=DEV)
    total, peak = red.sum_max(wp.array(values, dtype=float, device=DEV), count).numpy()
    ref = values[:count].astype(np.float64)
    assert total == pytest.approx(ref.sum(), rel=1e-5, abs=1e-4 * np.sqrt(count))
    assert peak == ref.max()
    again = red.sum_max(wp.array(values, dtype=float, device=DEV), count).numpy()
    assert again.tobytes() == np.array([total, peak], np.float32).tobytes()


def test_fixed_order_reduction_rejects_bad_sizes():
    with pytest.raises(ValueError, match="columns"):
        FixedOrderReduction(0, device=DEV)
    with pytest.raises(ValueError, match="group"):
        FixedOrderReduction(1, group=1, device=DEV)
    with pytest.raises(ValueError, match="sum_max"):
        FixedOrderReduction(3, device=DEV).sum_max(wp.zeros(4, dtype=float, device=DEV), 4)


def test_pressure_domain_sums_match_numpy():
    g = MacGrid((7, 6, 5), 0.1, open_sides=("+y",), device=DEV)
    rng = np.random.default_rng(3)
    labels = rng.choice([AIR, FLUID, FLUID, SOLID], size=g.shape).astype(np.int32)
    g.labels.assign(labels)
    solver = PressureSolver(g, preconditioner="mg")
    rhs = rng.normal(size=g.cell_count).astype(np.float32)
    solver.rhs.assign(rhs)
    red = solver._domain_reduction
    wp.launch(KG.fluid_sums, red.slots, inputs=[g.labels, g.open_mask, solver.rhs], outputs=[red.partials], device=DEV)
    total, cells, air = red.finish().numpy()
    fluid = labels == FLUID
    # NumPy: AIR faces of FLUID cells, cells beyond the grid SOLID except on the open +y side (AIR)
    padded = np.pad(labels, 1, constant_values=SOLID)
    padded[:, -1, :] = AIR
    faces = 0
    for axis in range(3):
        for shift in (-1, 1):
            neighbour = np.roll(padded, shift, axis=axis)[1:-1, 1:-1, 1:-1]
            faces += np.count_nonzero(fluid & (neighbour == AIR))
    assert cells == fluid.sum() and air == faces
    assert total == pytest.approx(rhs.reshape(g.shape)[fluid].astype(np.float64).sum(), rel=1e-5, abs=1e-5)


def test_level_set_volume_matches_numpy():
    g = MacGrid((20, 18, 16), 0.05, device=DEV)
    ls = LevelSet(g, lambda x: np.linalg.norm(x - 0.45, axis=-1) - 0.3, particle_level_set=False)
    phi = ls.phi.numpy().astype(np.float64)
    eps = 1.5 * g.dx
    x = -phi
    h = np.where(x >= eps, 1.0, np.where(x > -eps, 0.5 * (1 + x / eps + np.sin(np.pi * x / eps) / np.pi), 0.0))
    assert ls.volume() == pytest.approx(h.sum() * g.dx ** 3, rel=1e-6)
    assert ls.volume() == pytest.approx(4.0 / 3.0 * np.pi * 0.3 ** 3, rel=0.02)


# ------------------------------------------------------------------------ cell-sorted particles
def test_cell_ranks_follow_particle_index_within_each_cell():
    g = MacGrid((5, 4, 3), 0.25, device=DEV)
    rng = np.random.default_rng(8)
    n, cap = 300, 320
    P = GridParticles(cap, ["x"], ["alive"], alive="alive", device=DEV)
    x = rng.random((cap, 3)) * np.array(g.upper)
    alive = (rng.random(cap) > 0.2).astype(np.float32)
    P["x"].assign(x.astype(np.float32))
    P["alive"].assign(alive)
    P.count.assign(np.array([n], np.int32))
    counts = wp.zeros(g.shape, dtype=int, device=DEV)
    P.count_cells(g, counts)
    cell = np.minimum((x / g.dx).astype(int), np.array(g.shape) - 1)
    flat = np.ravel_multi_index(cell.T, g.shape)
    live = (np.arange(cap) < n) & (alive != 0)
    rank_ref = np.full(cap, -1)
    seen = {}
    for p in np.flatnonzero(live):
        rank_ref[p] = seen.get(flat[p], 0)
        seen[flat[p]] = rank_ref[p] + 1
    assert np.array_equal(P.rank.numpy(), rank_ref)
    assert np.array_equal(counts.numpy().reshape(-1), np.bincount(flat[live], minlength=g.cell_count))
    half = ((x / g.dx - cell) >= 0.5).astype(int)
    octant = 8 * flat + half[:, 0] + 2 * half[:, 1] + 4 * half[:, 2]
    order = P.sorted_ids.numpy()[: live.sum()]
    assert np.array_equal(order, np.flatnonzero(live)[np.argsort(octant[live], kind="stable")])
    per_octant = np.bincount(octant[live], minlength=8 * g.cell_count)
    assert np.array_equal(P.octant_count.numpy(), per_octant)
    assert np.array_equal(P.octant_start.numpy(), np.concatenate([[0], np.cumsum(per_octant)[:-1]]))


def _flip_pair(shape, device, seed=1):
    """Two FLIP liquids on twin grids with the same particles: the gather path and the atomic one."""
    out = []
    for deterministic in (True, False):
        g = MacGrid(shape, 1.0 / shape[1], device=device)
        f = FlipLiquid(g, reseed_every=0, density_correction=0.0, seed=seed, deterministic=deterministic)
        f.add_box((0.1,) * len(shape), (0.7, 0.6) + ((0.5,) if len(shape) == 3 else ()))
        rng = np.random.default_rng(seed)
        f.particles["v"].assign(rng.normal(size=(f.particles.capacity, 3)).astype(np.float32))
        out.append(f)
    return out


@pytest.mark.parametrize("shape", [(12, 10), (8, 7, 6)])
def test_flip_gathers_equal_the_atomic_scatter(shape, device):
    gather, scatter = _flip_pair(shape, device)
    for f in (gather, scatter):
        f._transfer_to_grid()
    for a, b in zip(gather.grid.faces[: len(shape)], scatter.grid.faces):  # (2D: w stays 0)
        a, b = a.numpy(), b.numpy()
        assert np.abs(b).max() > 0.1
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-6 * np.abs(b).max())
    assert np.array_equal(gather.grid.labels.numpy(), scatter.grid.labels.numpy())
    rho_a, rho_b = gather.measure_density().numpy(), scatter.measure_density().numpy()
    assert rho_b.max() > 1.0
    np.testing.assert_allclose(rho_a, rho_b, rtol=1e-6, atol=1e-6)


def _run_flip(steps, device=DEV):
    g = MacGrid((14, 12), 1.0 / 12, device=device)
    f = FlipLiquid(g, min_per_cell=3, max_per_cell=5)
    f.add_box((0.0, 0.0), (0.5, 0.7))
    for _ in range(steps):
        f.step(1.0 / 60)
    return f


def test_flip_runs_are_bit_identical_and_reseeding_appends_in_cell_order(device):
    a, b = _run_flip(12, device), _run_flip(12, device)
    for name in ("x", "v", "id", "alive"):
        assert a.particles[name].numpy().tobytes() == b.particles[name].numpy().tobytes()
    assert a.particles.count.numpy()[0] == b.particles.count.numpy()[0]
    # a further reseed appends new particles in flat cell order, with consecutive fresh ids
    before = int(a.particles.count.numpy()[0])
    next_id = int(a.next_id.numpy()[0])
    a.min_per_cell, a.max_per_cell = 6, 8
    a.reseed()
    after = int(a.particles.count.numpy()[0])
    live_before = int(np.count_nonzero(a.particles.alive.numpy()[:after] != 0)) - (after - before)
    assert after > live_before
    g = a.grid
    x_new = a.particles["x"].numpy()[live_before:after]
    cells = np.minimum(((x_new - np.array(g.origin)) / g.dx).astype(int), np.array(g.shape) - 1)
    flat = np.ravel_multi_index(cells.T, g.shape)
    assert np.all(np.diff(flat) >= 0)
    assert np.array_equal(a.particles["id"].numpy()[live_before:after], next_id + np.arange(after - live_before))


# ------------------------------------------------------------------------ PBF
def _run_pbf(steps, device=DEV):
    fluid = ParticleFluid(fluid_block((0, 0, 0), (0.2, 0.3, 0.1), 0.025), spacing=0.025,
                          domain=((0, 0, 0), (0.5, 0.5, 0.1)), device=device)
    for _ in range(steps):
        fluid.step(1.0 / 240)
    return fluid


def test_pbf_runs_are_bit_identical_and_its_compression_sums_match_numpy(device):
    a, b = _run_pbf(6, device), _run_pbf(6, device)
    assert a.positions.numpy().tobytes() == b.positions.numpy().tobytes()
    assert a.velocities.numpy().tobytes() == b.velocities.numpy().tobytes()
    assert a._total_iterations.numpy()[0] == b._total_iterations.numpy()[0] > 6
    mean, peak = a.density_error()
    rho = a._density.numpy()[: a.active_count]  # C in float32, as the kernel computes it
    c = np.maximum(rho / np.float32(a.rest_density) - np.float32(1.0), np.float32(0.0))
    assert c.max() > 0.0 and peak == c.max()
    assert mean == pytest.approx(c.astype(np.float64).mean(), rel=1e-6)


# ------------------------------------------------------------------------ marching cubes
def test_marching_cubes_gives_the_same_vertex_and_face_order_every_call(device):
    n = 24
    x = np.linspace(-1.0, 1.0, n)
    X, Y, Z = np.meshgrid(x, x, x, indexing="ij")
    field = (np.sqrt(X ** 2 + (1.3 * Y) ** 2 + Z ** 2) - 0.7 + 0.05 * np.sin(7 * X)).astype(np.float32)
    mesher = ws.MarchingCubes((n, n, n), device=device)
    first = mesher.mesh(wp.array(field, dtype=float, device=device)).numpy()
    for _ in range(2):
        again = ws.MarchingCubes((n, n, n), device=device).mesh(wp.array(field, dtype=float, device=device)).numpy()
        for a, b in zip(first, again):
            assert a.tobytes() == b.tobytes()
    assert len(first[0]) > 100


# ------------------------------------------------------------------------ the checker itself
def _load_checker():
    spec = importlib.util.spec_from_file_location("check_determinism", ROOT / "benchmarks" / "check_determinism.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_check_determinism_finds_the_first_differing_sample(tmp_path):
    pytest.importorskip("pxr")
    from pxr import Sdf, Usd, Vt

    def write(path, bump):
        stage = Usd.Stage.CreateNew(str(path))
        attr = stage.DefinePrim("/world/points", "Points").CreateAttribute("points", Sdf.ValueTypeNames.Point3fArray)
        for frame in range(4):
            pts = np.arange(12, dtype=np.float32).reshape(4, 3) + frame
            if bump and frame >= 2:
                pts[3, 1] = np.nextafter(pts[3, 1], np.float32(100))  # one ulp
            attr.Set(Vt.Vec3fArray.FromNumpy(pts), frame)
        stage.Save()

    write(tmp_path / "a.usda", False)
    write(tmp_path / "b.usda", False)
    write(tmp_path / "c.usda", True)
    check = _load_checker()
    assert check.compare_caches(tmp_path / "a.usda", tmp_path / "b.usda") is None
    frame, prim, attr, index, va, vb = check.compare_caches(tmp_path / "a.usda", tmp_path / "c.usda")
    assert (frame, prim, attr, index) == (2, "/world/points", "points", 3)
    assert va[1] != vb[1]


# ------------------------------------------------------------------------ boids' food
def test_contended_food_goes_to_the_lowest_index_agents_and_never_below_zero(device):
    n = 10
    rng = np.random.default_rng(2)
    p = ws.BoidParams(max_speed=1.0, min_speed=0.1, food_sense_radius=5.0, food_eat_radius=1.0, food_energy=0.1,
                      bite_interval=1.0, separation_radius=0.05, perception_radius=0.1)
    x = rng.uniform(-0.1, 0.1, (n, 3)) + np.array([0.0, 2.0, 0.0])
    v = np.tile([0.1, 0.0, 0.0], (n, 1))
    energy = np.full(n, 0.5)
    energy[1] = p.energy_max  # sated: does not ask
    food = ws.FoodSources([[0.0, 2.0, 0.0], [50.0, 2.0, 0.0]], [3, 7])
    flock = ws.Flock(x, v, params=p, food=food, energy=energy, device=device)
    flock.step(0.01)
    bites = flock.bites.numpy()
    assert bites.tolist() == [1, 0, 1, 1] + [0] * (n - 4)  # agents 0, 2, 3 get the 3 bites
    assert flock.food_amounts.numpy().tolist() == [0, 7]
    e = flock.energy.numpy()
    assert np.all(e[[0, 2, 3]] > e[4:].max())
