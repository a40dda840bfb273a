"""Divergence-free SPH (ParticleFluid(method="dfsph"): warpsim.particle_fluids.dfsph, kernels/dfsph.py)
and the dam break against Martin and Moyce (1952) (warpsim.particle_fluids.martin_moyce).

Physics checked: boundary particles continuing the fluid's lattice give the rest density at the
walls; a hydrostatic column (pressure rho g depth, density error small); the dam-break front
against the published table over T = 0 .. 3.1 (the whole span, at a CPU-sized resolution); momentum
of a free-falling block (internal forces pairwise antisymmetric); bit-identical repeat runs; bad
method names refused; no-slip boundary viscosity on the floor only (the side and slab walls free slip).
"""

import numpy as np
import pytest
import warp as wp

from warpsim.particle_fluids import martin_moyce as MM
from warpsim.particle_fluids.dfsph import boundary_lattice, floor_mask
from warpsim.particle_fluids.pbf import ParticleFluid, fluid_block

G = 9.81
CPU = "cpu"


def test_boundary_lattice_is_a_shell_that_continues_the_fluid_lattice():
    s = 0.1
    pts = boundary_lattice((0, 0, 0), (0.4, 0.3, 0.2), s, 2)
    inner = (4, 3, 2)
    assert len(pts) == np.prod(np.add(inner, 4)) - np.prod(inner)  # (n + 2 layers a side)^3 minus the inside
    assert not np.any(np.all((pts > 0) & (pts < (0.4, 0.3, 0.2)), axis=1))  # nothing inside the box
    # every coordinate is a lattice node of the fluid's (i + 1/2) s lattice, continued outward
    np.testing.assert_allclose(np.mod(pts / s - 0.5, 1.0) * (np.mod(pts / s - 0.5, 1.0) < 0.5), 0.0, atol=1e-9)


def test_a_lattice_filling_its_box_sits_at_rest_density_and_stays_put():
    """A block filling its box exactly, no gravity: boundary particles behind all six walls make
    every fluid particle's density rho0 (the wall particles too), so nothing moves."""
    s = 0.05
    f = ParticleFluid(fluid_block((0, 0, 0), (0.3, 0.2, 0.25), s), spacing=s, domain=((0, 0, 0), (0.3, 0.2, 0.25)),
                      gravity=(0.0, 0.0, 0.0), method="dfsph", device=CPU)
    x0 = f.positions.numpy().copy()
    f.step(1.0e-3)
    np.testing.assert_allclose(f.density.numpy(), 1000.0, rtol=2e-5)
    np.testing.assert_allclose(f.positions.numpy(), x0, atol=1e-7)
    assert f.last_iterations == 3  # the minimum: one divergence and two density iterations


def test_hydrostatic_column_density_and_pressure():
    """A 0.3 m column at rest in a box of boundary particles: after 1.5 s at rest (< 0.1 m/s), mean
    compression < 1 %, peak < 2 %, and at least a kernel radius from the walls and the floor the
    pressure within 5 % of rho g depth (bins 2 spacings thick; measured 0.999-1.039). The layer on
    the floor reads higher (1.27): a boundary particle pushes with the fluid particle's own pressure
    only (kappa_i, not kappa_i + kappa_j), so the wall layer carries more kappa for the same force."""
    s, width, height = 0.03, 0.3, 0.3
    f = ParticleFluid(fluid_block((0, 0, 0), (width, height, width), s), spacing=s,
                      domain=((0, 0, 0), (width, height + 0.1, width)), viscosity=0.05, max_dt=1.0 / 240.0,
                      method="dfsph", device=CPU)
    for _ in range(90):
        f.advance(1.0 / 60.0)
    assert f.max_speed_now() < 0.1
    mean, peak = f.density_error()
    assert mean < 0.01 and peak < 0.02, (mean, peak)
    x, p = f.positions.numpy(), f.pressure.numpy()
    inside = np.all((x[:, [0, 2]] > f.h) & (x[:, [0, 2]] < width - f.h), axis=1) & (x[:, 1] > f.h)
    # the depth of rest-density fluid above each particle: the weight above it per unit area / (rho0 g)
    y = x[:, 1]
    above = np.clip((y[None, :] + 0.5 * s - y[:, None]) / s, 0.0, 1.0).sum(axis=1)
    depth = above * f.particle_mass / (1000.0 * width * width)
    checked = 0
    for lo, hi in zip(np.arange(2 * s, height, 2 * s), np.arange(4 * s, height + 2 * s, 2 * s)):
        m = inside & (depth >= lo) & (depth < hi)
        if m.sum() < 4:
            continue
        ratio = p[m].mean() / (1000.0 * G * depth[m].mean())
        assert abs(ratio - 1.0) < 0.05, (lo, hi, ratio)
        checked += 1
    assert checked >= 3


@pytest.fixture(scope="module")
def dam_break():
    wp.init()
    return MM.run_dam_break("dfsph", res=10, device=CPU)


def test_dam_break_front_within_5_percent_of_martin_moyce_with_the_release_delay(dam_break):
    """Martin and Moyce's n^2 = 2 table (martin_moyce.N2_2_*, Table 2 of the paper), every point with
    0.8 <= T <= 3, the front of the water on the floor, DFSPH at a / spacing = 10, free-slip walls.

    Raw, the instantaneous release leads the experiment: measured +13..+17 % for 1 < T < 1.9 (the
    same lead PBF and FLIP show at every resolution, benchmarks/RESULTS.md), asserted between
    +8 % and +20 % there and within 20 % everywhere. The lead is a start delay: with T shifted by
    the experiment's release delay (martin_moyce.RELEASE_DELAY = 0.2, one number fitted on the
    converged runs of all three methods, not on this one) every point is within 5 % (measured
    3.6 %), the goal of issue 54 with the release delay (raw, it is not met: benchmarks/RESULTS.md)."""
    T, Z = dam_break["T"], dam_break["Z"]
    assert T[-1] >= 3.0 and len(T) == 63  # the whole span: T = 0 .. 3.1
    assert np.all(dam_break["Z_depth"] <= Z + 1e-12)  # the water 0.1 a deep never leads the film on the floor
    tt, raw = MM.deviation(T, Z)
    print("raw Z_sim / Z_exp - 1 at T =", tt, ":", np.round(raw, 3))
    early = (tt > 1.0) & (tt < 1.9)
    assert np.all(raw[early] > 0.08) and np.all(np.abs(raw) < 0.20), raw
    _, delayed = MM.deviation(T + MM.RELEASE_DELAY, Z)
    print(f"with T + {MM.RELEASE_DELAY}:", np.round(delayed, 3))
    assert np.all(np.abs(delayed) < 0.05), delayed
    shift, err = MM.best_shift(T, Z)
    assert 0.1 <= shift <= 0.3 and err < 0.05, (shift, err)


def test_dam_break_surge_runs_at_the_experiments_speed(dam_break):
    """What a start delay leaves alone: the surge's speed dZ/dT over 1.4 <= T <= 3 (a least-squares
    line through the frames, against one through the table's points, 1.30) within 5 % (measured
    +1.3 % at a / spacing = 10, +0.1 % at 20, +4.4 % at 40): the flow after the release is the experiment's."""
    speed, measured = MM.surge_speed(dam_break["T"], dam_break["Z"])
    print(f"dZ/dT {speed:.3f} against {measured:.3f}")
    assert measured == pytest.approx(1.30, abs=0.01)
    assert abs(speed / measured - 1.0) < 0.05


def test_an_under_dense_block_collapses_later_as_splishsplash_s_setup_does(dam_break):
    """Why a well-known SPH code (SPlisHSPlasH, DFSPH) stays within ~7 % of the table where the
    rest-density column leads by ~16 %: its fluid particles get 0.8 of a lattice cell's mass
    (``FluidModel::initMasses``: "to prevent pressure at the beginning"), so its block starts at
    0.8 rho0 and, the pressure clamped at >= 0, is soft until packed to rest density. The same
    setting here (``mass_fraction=0.8``): the interior starts at 0.80-0.83 rho0 after one frame (the cubic kernel sums a
    lattice to exactly 1 / s^3), no particle reaches rho0 in the first frames, and the front
    trails the rest-density block's at T = 1.2 by several points (measured a/10: raw worst +7.5 %
    against +16.3 %; a/20 +6.7 % against +17.7 %, benchmarks/RESULTS.md). Not a remedy: it removes
    a fifth of the column's stiffness, not the experiment's release."""
    soft = MM.run_dam_break("dfsph", res=10, device=CPU, mass_fraction=0.8, t_end=1.3)
    f = soft["fluid"]
    assert f.particle_mass == pytest.approx(0.8 * dam_break["fluid"].particle_mass, rel=1e-12)
    first = MM.run_dam_break("dfsph", res=10, device=CPU, mass_fraction=0.8, t_end=0.05)["fluid"]
    rho = first.density.numpy() / first.rest_density
    x = first.positions.numpy()
    interior = (x[:, 0] > 0.05) & (x[:, 0] < 0.15) & (x[:, 1] > 0.05) & (x[:, 1] < 0.3)
    assert interior.sum() > 20 and np.all((rho[interior] > 0.78) & (rho[interior] < 0.85)), rho[interior]
    assert rho.max() < 1.0
    z_soft = np.interp(1.2, soft["T"], soft["Z"])
    z_rest = np.interp(1.2, dam_break["T"], dam_break["Z"])
    z_exp = np.interp(1.2, *MM.table(0.2, 0.4))
    print(f"Z(1.2): rest density {z_rest:.3f}, 0.8 rho0 {z_soft:.3f}, measured {z_exp:.3f}")
    assert z_soft < z_rest - 0.05 * z_exp and z_soft > z_exp  # later, and still ahead of the experiment
    with pytest.raises(ValueError, match="mass_fraction"):
        ParticleFluid(fluid_block((0, 0, 0), (0.1, 0.1, 0.1), 0.05), spacing=0.05, mass_fraction=3.0, device=CPU)


def test_floor_front_is_the_water_on_the_floor_not_spray():
    """floor_front: the edge of the film joined to the wall; a drop ahead of a dry stretch, or a
    particle above the floor band, is not the front; a one-bin hole in the film is."""
    s = 0.1
    film = [[0.05 + s * k, 0.05, 0.0] for k in range(6)]  # wet bins 0..5
    assert MM.floor_front(np.array(film), s) == pytest.approx(0.6)
    drop = film + [[1.25, 0.05, 0.0]]  # two dry bins, then a drop
    assert MM.floor_front(np.array(drop), s) == pytest.approx(0.6)
    holed = [p for k, p in enumerate(film) if k != 3]  # one dry bin inside the film
    assert MM.floor_front(np.array(holed), s) == pytest.approx(0.6)
    airborne = film + [[0.95, 0.35, 0.0]]  # above the two-spacing band
    assert MM.floor_front(np.array(airborne), s) == pytest.approx(0.6)
    slab = np.array([[0.05 + s * k, 0.05, z] for k in range(4) for z in (0.0, 0.1, 0.2)] + [[0.45, 0.05, 0.0]])
    assert MM.floor_front(slab, s, layers=3) == pytest.approx(0.4)  # one of three layers: spray
    assert MM.tip_front(slab, s) == pytest.approx(0.5)


def test_depth_front_does_not_count_a_film_thinner_than_its_depth():
    """depth_front: the water at least ``depth`` deep (count * s / layers per bin), joined to the
    wall; a film one particle thick ahead of a column three particles high is the floor front, not
    the depth front at two spacings; a one-bin hole is bridged; and the dam break reports it."""
    s = 0.1
    deep = [[0.05 + s * k, 0.05 + s * j, 0.0] for k in range(4) for j in range(3)]  # 3 high: bins 0..3
    film = [[0.05 + s * k, 0.05, 0.0] for k in range(4, 8)]  # 1 high: bins 4..7
    x = np.array(deep + film)
    assert MM.floor_front(x, s) == pytest.approx(0.8)
    assert MM.depth_front(x, s, 2 * s) == pytest.approx(0.4)
    assert MM.depth_front(x, s, s) == pytest.approx(0.8)
    assert MM.depth_front(np.array(deep + film) + [0.3, 0, 0], s, 2 * s, origin=0.3) == pytest.approx(0.7)
    holed = np.array([p for p in deep if not 0.1 < p[0] < 0.2] + film)  # bin 1 dry
    assert MM.depth_front(holed, s, 2 * s) == pytest.approx(0.4)
    slab = np.concatenate([x + [0, 0, z] for z in (0.0, 0.1, 0.2)])  # 3 layers deep: the same depths
    assert MM.depth_front(slab, s, 2 * s, layers=3) == pytest.approx(0.4)


def test_dam_break_keeps_its_density(dam_break):
    """Mean compression (measured at every frame) below 1 %; every particle inside the box."""
    assert dam_break["compression"].max() < 0.01, dam_break["compression"].max()
    f = dam_break["fluid"]
    x = f.positions.numpy()
    lo, hi = f.domain
    assert np.all(x >= lo) and np.all(x <= hi)


def test_a_lifting_gate_holds_the_column_above_its_edge():
    """Moving boundary particles: a gate at x = a lifted at 1 m/s lets water out only beneath its
    lower edge (every particle past the gate lies below the edge's height, U t + a spacing), and it
    does let it out (the front has passed the gate)."""
    r = MM.run_dam_break("dfsph", res=10, gate_speed=1.0, t_end=0.6, device=CPU)
    f, a, s = r["fluid"], 0.2, 0.02
    x = f.positions.numpy()
    past = x[:, 0] > a + 2.0 * s  # beyond the gate's two layers
    assert past.sum() > 0 and r["Z"][-1] > 1.2
    assert np.all(x[past & (x[:, 0] < a + 3.0 * s), 1] < 1.0 * f.time + 2.0 * s)


def test_repeat_runs_are_bit_identical():
    """Two runs of the same dam break (10 frames) give the same bits: fixed-order gathers, no float atomics."""
    runs = []
    for _ in range(2):
        a, s = 0.2, 0.02
        f = ParticleFluid(fluid_block((0, 0, 0), (a, 2 * a, 3 * s), s), spacing=s,
                          domain=((0, 0, 0), (5 * a, 2.5 * a, 3 * s)), method="dfsph", device=CPU)
        for _ in range(10):
            f.advance(1.0 / 60.0)
        runs.append((f.positions.numpy().tobytes(), f.velocities.numpy().tobytes(), f.total_iterations))
    assert runs[0] == runs[1]


def test_free_fall_momentum_matches_gravity():
    """No walls: the pressure, SPH viscosity and XSPH are pairwise antisymmetric, so the total
    momentum changes by exactly M g t while the block deforms."""
    s = 0.02
    x0 = fluid_block((-0.05, -0.05, -0.05), (0.05, 0.05, 0.05), s, jitter=0.1, seed=2) * 0.9
    v0 = np.random.default_rng(0).normal(0.0, 0.3, x0.shape)
    f = ParticleFluid(x0, v0, spacing=s, viscosity=0.1, kinematic_viscosity=1e-3, method="dfsph", device=CPU)
    p0 = f.momentum()
    for _ in range(10):
        f.step(1.0 / 500.0)
    expected = p0 + f.total_mass * np.array([0.0, -G, 0.0]) * f.time
    np.testing.assert_allclose(f.momentum(), expected, atol=2e-5 * f.total_mass)


def test_a_first_step_beyond_the_cfl_limit_is_said_before_it_runs():
    """step(dt) with dt above the CFL-limited step (here max_dt, 5 ms) warns before the first step;
    advance() sub-steps inside the limit and says nothing."""
    x = fluid_block((0, 0, 0), (0.1, 0.2, 0.06), 0.02)
    f = ParticleFluid(x, spacing=0.02, domain=((0, 0, 0), (0.5, 0.25, 0.06)), method="dfsph", device=CPU)
    with pytest.warns(RuntimeWarning, match=r"dt = 0.02 s exceeds the CFL-limited step 0.005 s"):
        f.step(0.02)
    quiet = ParticleFluid(x, spacing=0.02, domain=((0, 0, 0), (0.5, 0.25, 0.06)), method="dfsph", device=CPU)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        quiet.advance(1.0 / 60.0)
    assert quiet.last_substeps >= 4


def test_bad_method_and_boundary_are_refused():
    x = fluid_block((0, 0, 0), (0.1, 0.1, 0.1), 0.05)
    with pytest.raises(ValueError, match=r"method='sph'.*method='pbf'.*method='dfsph'"):
        ParticleFluid(x, spacing=0.05, method="sph", device=CPU)
    with pytest.raises(ValueError, match=r"boundary='mesh'.*'particles'.*'volume'"):
        ParticleFluid(x, spacing=0.05, method="dfsph", boundary="mesh", device=CPU)
    from warpsim.scenes import get_scene

    for scene in ("dam_break", "pour"):  # warpsim run SCENE --set method=sph
        with pytest.raises(ValueError, match=r"method='sph' is not one of pbf, dfsph"):
            get_scene(scene).resolve_params({"method": "sph"})
        assert get_scene(scene).resolve_params({"method": "dfsph"})["method"] == "dfsph"


def test_martin_moyce_tables_follow_the_aspect_ratio():
    """The n^2 = 2 table for a column twice as tall as wide (the scene's 0.2 x 0.4 m), the square
    column's for n^2 = 1; T = n t sqrt(g / a) (sqrt(2 g / a) for n^2 = 2); other ratios refused."""
    assert MM.table(0.2, 0.4)[0] is MM.N2_2_T and MM.table(0.1, 0.1)[0] is MM.N2_1_T
    assert MM.time_scale(0.2, 0.4) == pytest.approx(np.sqrt(2.0 * G / 0.2))
    with pytest.raises(ValueError, match="n\\^2 = height/width = 1.5"):
        MM.table(0.4, 0.6)
    # both series run toward Ritter's inviscid front Z = 1 + 2T from below
    for t, z in (MM.table(1, 2), MM.table(1, 1)):
        assert np.all(z < 1.0 + 2.0 * t) and np.all(np.diff(z) > 0) and np.all(np.diff(t) > 0)


def sliding_layer(no_slip, boundary_viscosity, frames=6):
    """A layer 4 particles high and 3 deep (a slab between front and back walls) 0.8 m long, sliding
    along +x at 1 m/s over the floor, after ``frames`` / 60 s: the mean vx of the particles that
    started in its middle (0.3 m, where the ends' collapse has not arrived) in the bottom layer and
    in the top layer; the top layer's centres 3.5 spacings above the floor, beyond the reach of the
    floor's boundary particles (kernel support 2 spacings, the first boundary layer half a spacing
    below the floor)."""
    s = 0.02
    x = fluid_block((0, 0, 0), (0.8, 4 * s, 3 * s), s)
    v = np.tile([1.0, 0.0, 0.0], (len(x), 1))
    f = ParticleFluid(x, v, spacing=s, domain=((0, 0, 0), (1.2, 0.3, 3 * s)), method="dfsph", no_slip=no_slip,
                      boundary_viscosity=boundary_viscosity, device=CPU)
    for _ in range(frames):
        f.advance(1.0 / 60.0)
    middle = (x[:, 0] > 0.25) & (x[:, 0] < 0.55)  # indices stay with their particles (no sorting)
    bottom, top = middle & (x[:, 1] < s), middle & (x[:, 1] > 3 * s)
    v = f.velocities.numpy()
    return v[bottom, 0].mean(), v[top, 0].mean(), f


def test_no_slip_on_the_floor_only_slows_the_fluid_at_the_floor_not_at_the_slab_walls():
    """boundary_viscosity nu_b = 0.01 m^2/s with no_slip="floor": the boundary particles behind the
    floor hold the bottom layer of a sliding layer back, while the slab's front and back walls, which
    every particle touches (3 particles deep), stay free slip, so the top layer (out of the floor's
    reach) keeps its speed; with no_slip="all" the same viscosity on every wall slows the top layer as
    much as the bottom one (a Hele-Shaw cell: the -37 % of benchmarks/RESULTS.md); nu_b = 0: free slip
    everywhere. Measured after 0.1 s, bottom / top: free slip 0.996 / 1.000 m/s, floor 0.035 / 1.001,
    all 0.002 / 0.407."""
    free_bottom, free_top, f = sliding_layer("all", 0.0)
    floor_bottom, floor_top, g = sliding_layer("floor", 0.01)
    all_bottom, all_top, _ = sliding_layer("all", 0.01)
    print(f"bottom / top vx: free {free_bottom:.3f} / {free_top:.3f}, floor {floor_bottom:.3f} / "
          f"{floor_top:.3f}, all {all_bottom:.3f} / {all_top:.3f}")
    assert free_bottom > 0.98 and free_top > 0.98
    assert floor_bottom < 0.3  # the floor holds the layer on it back
    assert floor_top > 0.98  # ... the free-slip slab walls do not hold the top layer back
    assert all_bottom < 0.3 and all_top < 0.6
    # the floor's boundary particles come first and are the only no-slip ones
    b = g._dfsph
    floor = floor_mask(b.boundary_points, *g.domain, g.gravity)
    count = int(floor.sum())
    assert b.no_slip_count == count and np.all(floor[:count]) and not np.any(floor[count:])
    assert f._dfsph.no_slip_count == f._dfsph.boundary_count


def test_floor_mask_follows_gravity_and_bad_no_slip_is_refused():
    """The floor is the wall gravity points at (edges and corners included): -y for (0, -g, 0), +x
    for (g, 0, 0); no_slip needs DFSPH's boundary particles and a known value."""
    pts = boundary_lattice((0, 0, 0), (0.4, 0.3, 0.2), 0.1, 2)
    down = floor_mask(pts, (0, 0, 0), (0.4, 0.3, 0.2), (0.0, -G, 0.0))
    assert down.sum() == 2 * (4 + 4) * (2 + 4) and np.all(pts[down, 1] < 0) and np.all(pts[~down, 1] > 0)
    east = floor_mask(pts, (0, 0, 0), (0.4, 0.3, 0.2), (G, 0.0, 0.0))
    assert east.sum() == 2 * (3 + 4) * (2 + 4) and np.all(pts[east, 0] > 0.4)
    with pytest.raises(ValueError, match="gravity is zero"):
        floor_mask(pts, (0, 0, 0), (0.4, 0.3, 0.2), (0.0, 0.0, 0.0))
    x = fluid_block((0, 0, 0), (0.1, 0.1, 0.1), 0.05)
    box = ((0, 0, 0), (0.2, 0.2, 0.2))
    with pytest.raises(ValueError, match="no_slip='wall'.*'all', 'floor'"):
        ParticleFluid(x, spacing=0.05, domain=box, method="dfsph", no_slip="wall", device=CPU)
    with pytest.raises(ValueError, match="no_slip='floor'.*needs method='dfsph'"):
        ParticleFluid(x, spacing=0.05, domain=box, no_slip="floor", device=CPU)
    with pytest.raises(ValueError, match="no_slip='floor' needs boundary='particles'"):
        ParticleFluid(x, spacing=0.05, domain=box, method="dfsph", boundary="volume", no_slip="floor",
                      device=CPU)
