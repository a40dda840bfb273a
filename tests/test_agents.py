"""Flocking and crowds (warpsim.agents): every rule against a NumPy brute-force reference, and
each behaviour measured: polarization, nearest-neighbour distances, radius of gyration,
segregation, food bookkeeping, rest cycles, drafting savings, slope rules, falls, recovery,
scenes and USD output. All on the CPU."""

import math

import numpy as np
import pytest
import warp as wp

from warpsim.agents import reference as R
from warpsim.agents import (
    AgentState,
    BoidParams,
    Crowd,
    Flock,
    FoodSources,
    Obstacles,
    Terrain,
    WalkerParams,
    nearest_distances,
    polarization,
    radius_of_gyration,
    same_group_fraction,
)

CPU = "cpu"
FLYING, RESTING, WALKING, CLIMBING, FALLEN, LANDING = (int(s) for s in AgentState)


def unit_rows(rng, n, speed):
    v = rng.normal(0.0, 1.0, (n, 3))
    return speed * v / np.linalg.norm(v, axis=1, keepdims=True)


def run(agents, steps, dt, record=None):
    out = []
    for _ in range(steps):
        agents.step(dt)
        if record is not None:
            out.append(record(agents))
    return out


# --------------------------------------------------------------------------------------
# Rules: hash grid == O(n^2) NumPy
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("wrap", [True, (True, False, True), False])
def test_rules_match_brute_force(wrap):
    rng = np.random.default_rng(7)
    n, L = 300, 10.0
    x = rng.uniform(0.0, L, (n, 3))
    v = rng.normal(0.0, 2.0, (n, 3))
    v[:5] = 0.0  # no heading: sees all around
    species = rng.integers(0, 2, n)
    params = [BoidParams(perception_radius=2.0, separation_radius=0.8, separation_radius_other=1.2, fov_deg=250.0,
                         min_distance=0.4, min_distance_other=0.5, draft_weight=1.0, draft_saving=0.3),
              BoidParams(perception_radius=1.5, separation_radius=0.5, fov_deg=360.0, max_speed=5.0, max_force=4.0)]
    state = np.where(rng.uniform(size=n) < 0.1, RESTING, FLYING)
    flock = Flock(x, v, species, params, bounds=((0, 0, 0), (L, L, L)), wrap=wrap, terrain=Terrain.flat(-5.0),
                  state=state, device=CPU)
    flock.eval_rules(lookahead=0.05)
    ref = R.neighbour_rules(flock.positions.numpy(), v, species, species, state, flock.rule_values, flock.box,
                            lookahead=0.05)
    got = {"separation": flock.separation, "alignment": flock.alignment, "cohesion": flock.cohesion,
           "draft": flock.draft, "push": flock.push, "benefit": flock.benefit, "neighbours": flock.neighbour_counts}
    for key, arr in got.items():
        a = arr.numpy()
        scale = max(1.0, float(np.abs(ref[key]).max()))
        assert np.abs(a - ref[key]).max() <= 2e-5 * scale, key
    # the test exercises every rule, the field of view and the periodic images
    assert (ref["neighbours"] > 0).sum() > n // 2 and (ref["benefit"] > 0.5).any() and np.abs(ref["push"]).max() > 0
    assert np.all(flock.separation.numpy()[state == RESTING] == 0.0)
    # the cell-grid candidate pairs (the benchmark's NumPy reference) give the same rules
    grid = R.neighbour_rules(flock.positions.numpy(), v, species, species, state, flock.rule_values, flock.box,
                             pairs=R.grid_pairs(flock.positions.numpy(), flock.cell_size, flock.box), lookahead=0.05)
    for key in ref:
        assert np.allclose(grid[key], ref[key], atol=1e-12), key


def test_field_of_view_and_species_filtering():
    # agent 0 heads +x; 1 ahead (same species), 2 behind (same species), 3 ahead (other species)
    x = np.array([[0.0, 0, 0], [1.0, 0, 0], [-1.0, 0, 0], [0.3, 0, 0.8]])
    v = np.array([[1.0, 0, 0], [0.0, 0, 1.0], [0.0, 1.0, 0], [-1.0, 0, 0]])
    p = BoidParams(perception_radius=2.0, separation_radius=1.5, fov_deg=180.0, max_speed=2.0, max_force=100.0,
                   min_speed=0.0)
    flock = Flock(x, v, [0, 0, 0, 1], [p, p], device=CPU)
    flock.eval_rules()
    ali = flock.alignment.numpy()[0]
    coh = flock.cohesion.numpy()[0]
    sep = flock.separation.numpy()[0]
    # only agent 1 is seen (2 is behind, 3 is another species): steer to its velocity and position
    assert np.allclose(ali, 2.0 * np.array([0, 0, 1.0]) - v[0], atol=1e-6)
    assert np.allclose(coh, 2.0 * np.array([1.0, 0, 0]) - v[0], atol=1e-6)
    # separation from 1 (same species, 1 m) and 3 (other species), not from 2 (behind); limited
    d3 = x[3] - x[0]
    r3 = np.linalg.norm(d3)
    expected = p.max_force * ((1 - 1 / 1.5) * np.array([-1.0, 0, 0]) - (1 - r3 / 1.5) * d3 / r3)
    expected *= min(1.0, p.max_force / np.linalg.norm(expected))
    assert np.allclose(sep, expected, atol=1e-4)
    assert flock.neighbour_counts.numpy()[0] == 1
    # agent 3 sees only other species: its alignment and cohesion are exactly zero
    assert np.all(flock.alignment.numpy()[3] == 0.0) and np.all(flock.cohesion.numpy()[3] == 0.0)


def test_step_matches_numpy_reference():
    rng = np.random.default_rng(3)
    n, L = 200, 12.0
    x = rng.uniform(0.0, L, (n, 3))
    v = unit_rows(rng, n, 3.0)
    p = BoidParams(max_speed=4.0, min_speed=1.0, max_force=6.0, perception_radius=2.5, separation_radius=1.0,
                   min_distance=0.3, fov_deg=270.0, boundary_weight=1.5)
    flock = Flock(x, v, params=p, bounds=((0, 0, 0), (L, L, L)), wrap=(True, False, True), margin=2.0, device=CPU)
    xr, vr = flock.positions.numpy().astype(np.float64), v.copy()
    kind = np.zeros(n, dtype=int)
    weights = (p.separation_weight, p.alignment_weight, p.cohesion_weight, p.boundary_weight, 2.0)
    for _ in range(5):
        flock.step(0.02)
        xr, vr = R.boids_step(xr, vr, kind, flock.rule_values, weights, p.min_speed, 0.02, flock.box)
    dx = flock.positions.numpy() - xr
    dx -= L * np.round(dx / L) * np.array([1, 0, 1])
    assert np.abs(dx).max() < 1e-4
    assert np.abs(flock.velocities.numpy() - vr).max() < 1e-3


# --------------------------------------------------------------------------------------
# Emergent behaviour
# --------------------------------------------------------------------------------------
def test_alignment_raises_polarization():
    rng = np.random.default_rng(2)
    n, L = 200, 10.0
    x = rng.uniform(0.0, L, (n, 3))
    v = unit_rows(rng, n, 2.0)
    box = {"bounds": ((0, 0, 0), (L, L, L)), "wrap": True, "device": CPU}
    phi0 = polarization(v)
    assert phi0 < 3 * 0.92 / math.sqrt(n)  # random headings
    aligned = Flock(x, v, params=BoidParams(max_speed=2.0, min_speed=2.0, max_force=4.0, perception_radius=3.0,
                                            separation_weight=0.0, cohesion_weight=0.0, fov_deg=360.0), **box)
    control = Flock(x, v, params=BoidParams(max_speed=2.0, min_speed=2.0, max_force=4.0, perception_radius=3.0,
                                            separation_weight=0.0, cohesion_weight=0.0, alignment_weight=0.0), **box)
    phis = run(aligned, 150, 0.05, lambda f: polarization(f.velocities.numpy()))
    run(control, 150, 0.05)
    assert phis[-1] > 0.95
    assert phis[-1] > phis[20] > phi0  # rises
    assert polarization(control.velocities.numpy()) < 3 * 0.92 / math.sqrt(n)
    assert np.allclose(np.linalg.norm(aligned.velocities.numpy(), axis=1), 2.0, rtol=1e-4)


def test_separation_keeps_distance():
    rng = np.random.default_rng(4)
    n, L, r_sep = 100, 10.0, 1.0
    x = rng.uniform(0.0, L, (n, 3))
    v = rng.normal(0.0, 1.0, (n, 3))
    mins = {}
    for w in (3.0, 0.0):
        p = BoidParams(max_speed=2.0, min_speed=1.0, max_force=6.0, perception_radius=2.0, separation_radius=r_sep,
                       separation_weight=w, fov_deg=360.0)
        flock = Flock(x, v, params=p, bounds=((0, 0, 0), (L, L, L)), wrap=True, device=CPU)
        run(flock, 60, 0.05)
        mins[w] = min(run(flock, 100, 0.05, lambda f: nearest_distances(f.positions.numpy(), f.box).min()))
    assert mins[3.0] > 0.4 * r_sep
    assert mins[0.0] < 0.05 * r_sep  # without separation, cohesion and alignment collapse the flock


def test_cohesion_shrinks_radius_of_gyration():
    rng = np.random.default_rng(5)
    n = 100
    x = rng.uniform(-10.0, 10.0, (n, 3))
    rg = {}
    for w in (1.0, 0.0):
        p = BoidParams(max_speed=3.0, min_speed=0.0, max_force=3.0, perception_radius=8.0, separation_radius=0.5,
                       cohesion_weight=w, alignment_weight=0.0, fov_deg=360.0)
        flock = Flock(x, np.zeros((n, 3)), params=p, device=CPU)
        rg[w] = run(flock, 100, 0.05, lambda f: radius_of_gyration(f.positions.numpy()))
    rg0 = radius_of_gyration(x)
    assert rg[1.0][-1] < 0.4 * rg0
    assert rg[1.0][-1] < rg[1.0][30] < rg0
    assert abs(rg[0.0][-1] - rg0) < 0.05 * rg0


def test_species_segregate():
    rng = np.random.default_rng(6)
    n, L = 150, 12.0
    species = np.repeat(np.arange(3), n // 3)
    x = rng.uniform(0.0, L, (n, 3))
    v = unit_rows(rng, n, 2.0)
    p = BoidParams(max_speed=3.0, min_speed=1.5, max_force=5.0, perception_radius=3.0, separation_radius=0.6,
                   separation_radius_other=2.0, fov_deg=300.0)
    flock = Flock(x, v, species, [p, p, p], bounds=((0, 0, 0), (L, L, L)), wrap=True, device=CPU)
    before = same_group_fraction(x, species, box=flock.box)
    run(flock, 300, 0.05)
    after = same_group_fraction(flock.positions.numpy(), species, box=flock.box)
    assert before < 0.45  # random mixture: about 1/3
    assert after > 0.85


# --------------------------------------------------------------------------------------
# Food, energy, resting, drafting
# --------------------------------------------------------------------------------------
def test_food_is_consumed_exactly():
    rng = np.random.default_rng(8)
    n = 50
    p = BoidParams(max_speed=3.0, min_speed=1.0, food_sense_radius=20.0, food_eat_radius=0.5, food_energy=0.01,
                   bite_interval=0.2, perception_radius=1.0, separation_radius=0.3)
    amounts = np.array([30, 40, 0])
    food = FoodSources([[0, 0, 0], [5, 0, 0], [2, 0, 2]], amounts)
    energy = np.full(n, 0.2)
    energy[:10] = p.energy_max  # sated agents do not eat
    flock = Flock(rng.uniform(-3, 8, (n, 3)), rng.normal(0, 1, (n, 3)), params=p, food=food, energy=energy,
                  device=CPU)
    history = run(flock, 120, 0.05, lambda f: (f.food_amounts.numpy().copy(), f.bites.numpy().sum()))
    for left, eaten in history:
        assert (left >= 0).all()
        assert amounts.sum() - left.sum() == eaten  # counts drop by exactly what was eaten
    left, eaten = history[-1]
    bites = flock.bites.numpy()
    assert 0 < eaten
    assert left[2] == 0 and (bites[:10] == 0).all()
    assert np.allclose(flock.energy.numpy()[10:], 0.2 + 0.01 * bites[10:], atol=1e-5)
    run(flock, 200, 0.05)  # demand exceeds supply: everything is eaten, never more
    assert (flock.food_amounts.numpy() == 0).all() and flock.bites.numpy().sum() == amounts.sum()


def test_food_attracts_hungry_agents():
    n = 20
    rng = np.random.default_rng(9)
    x = np.stack([rng.uniform(8, 10, n), np.zeros(n), rng.uniform(-1, 1, n)], axis=1)
    v = np.tile([0.0, 0.0, 1.0], (n, 1))
    d = {}
    for sense in (15.0, 0.0):
        p = BoidParams(max_speed=2.0, min_speed=0.5, food_sense_radius=sense, separation_radius=0.2,
                       alignment_weight=0.0, cohesion_weight=0.0)
        f = Flock(x, v, params=p, food=FoodSources([[0, 0, 0]], 1000), energy=np.full(n, 0.5), device=CPU)
        run(f, 100, 0.05)
        d[sense] = np.linalg.norm(f.positions.numpy(), axis=1).mean()
    assert d[15.0] < 2.0  # hungry agents that sense the food gather at it
    assert d[0.0] > 8.0  # those that cannot sense it fly on


def test_goal_seeking_flyers_reach_their_goal():
    rng = np.random.default_rng(10)
    n = 30
    x = rng.uniform(-20.0, -10.0, (n, 3))
    p = BoidParams(max_speed=4.0, min_speed=0.0, max_force=4.0, goal_weight=1.0, separation_radius=0.4,
                   alignment_weight=0.0, cohesion_weight=0.0)
    flock = Flock(x, np.zeros((n, 3)), params=p, goals=(10.0, 5.0, 0.0), device=CPU)
    d0 = np.linalg.norm(x - [10.0, 5.0, 0.0], axis=1)
    run(flock, 300, 0.05)
    d = np.linalg.norm(flock.positions.numpy() - [10.0, 5.0, 0.0], axis=1)
    assert d0.min() > 20.0 and d.max() < 5.0
    assert np.linalg.norm(flock.velocities.numpy(), axis=1).max() <= p.max_speed * (1 + 1e-5)


def test_energy_rest_cycle():
    p = BoidParams(max_speed=3.0, min_speed=2.0, drain_rate=0.5, energy_max=1.0, land_threshold=0.2, rest_time=1.0,
                   descent_speed=1.5, takeoff_speed=2.0)
    dt = 0.02
    flock = Flock([[0, 3, 0], [50, 4, 0]], [[2, 0, 0], [0, 0, 2]], params=p, terrain=Terrain.flat(0.5), device=CPU)
    rec = run(flock, 450, dt, lambda f: (f.state.numpy().copy(), f.energy.numpy().copy(), f.positions.numpy().copy()))
    state = np.array([r[0] for r in rec])
    energy = np.array([r[1] for r in rec])
    pos = np.array([r[2] for r in rec])
    t = dt * np.arange(1, len(rec) + 1)
    for a in range(2):
        s = state[:, a]
        change = np.flatnonzero(np.diff(s) != 0) + 1
        kinds = [(int(s[c - 1]), int(s[c])) for c in change]
        assert kinds[:4] == [(FLYING, LANDING), (LANDING, RESTING), (RESTING, FLYING), (FLYING, LANDING)]
        land, touch, up, land2 = (t[c] for c in change[:4])
        # lands when energy reaches the threshold: (1 - 0.2) / 0.5 s of flight
        assert abs(land - 1.6) <= 1.5 * dt and abs(energy[change[0], a] - 0.2) <= 0.5 * dt + 1e-6
        assert abs(pos[change[1], a, 1] - 0.5) < 1e-6  # rests on the ground
        assert abs((up - touch) - p.rest_time) <= dt + 1e-9  # rests for the set time
        assert abs(energy[change[2], a] - 1.0) < 1e-6  # takes off refreshed
        assert abs((land2 - up) - 1.6) <= 1.5 * dt  # and flies the same time again
        resting = s == RESTING
        assert np.all(np.linalg.norm(np.diff(pos[:, a], axis=0), axis=1)[resting[1:] & resting[:-1]] == 0.0)


def test_drafting_saves_energy():
    dt, steps = 0.05, 200
    p = BoidParams(max_speed=6.0, min_speed=4.0, max_force=5.0, perception_radius=4.0, separation_radius=0.3,
                   alignment_weight=0.0, cohesion_weight=0.0, draft_weight=1.0, draft_saving=0.3, drain_rate=1.0,
                   energy_max=20.0, land_threshold=0.0, fov_deg=270.0)
    # leader, follower starting 3 m behind and 1.5 m aside, lone flyer far away
    x = np.array([[0.0, 0, 0], [-3.0, 0, 1.5], [0.0, 0, 100.0]])
    v = np.tile([5.0, 0, 0], (3, 1))
    flock = Flock(x, v, params=p, terrain=Terrain.flat(-100.0), device=CPU)
    benefit = run(flock, steps, dt, lambda f: f.benefit.numpy()[1])
    used = p.energy_max - flock.energy.numpy()
    lone = p.drain_rate * dt * steps
    assert abs(used[2] - lone) < 2e-3 and abs(used[0] - lone) < 2e-3  # nobody ahead: full drain
    assert used[1] < 0.85 * lone  # the follower drafts
    assert np.mean(benefit[-50:]) > 0.8  # and has settled in the upwash slot
    rel = flock.positions.numpy()[1] - flock.positions.numpy()[0]
    assert abs(-rel[0] - p.draft_back) < 0.1 and abs(np.hypot(rel[1], rel[2]) - p.draft_side) < 0.1
    assert abs(used[1] - p.drain_rate * dt * np.sum(1.0 - p.draft_saving * np.array(benefit))) < 2e-3


# --------------------------------------------------------------------------------------
# Obstacles
# --------------------------------------------------------------------------------------
def _box_mesh(half):
    c = np.array([[(1 if (i >> k) & 1 else -1) for k in range(3)] for i in range(8)], dtype=float) * half
    quads = [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]]
    return c, [[q[0], q[1], q[2]] for q in quads] + [[q[0], q[2], q[3]] for q in quads]


@pytest.mark.parametrize("kind", ["sphere", "plane", "mesh"])
def test_obstacles_are_avoided(kind):
    rng = np.random.default_rng(0)
    n = 40
    x = np.stack([rng.uniform(-12, -8, n), rng.uniform(-1.5, 1.5, n), rng.uniform(-1.5, 1.5, n)], axis=1)
    v = np.tile([3.0, 0, 0], (n, 1))
    obstacles = {"sphere": Obstacles(spheres=[((0, 0, 0), 2.0)]), "plane": Obstacles(planes=[((-1, 0, 0), -1.0)]),
                 "mesh": Obstacles(meshes=[_box_mesh(1.0)])}[kind]
    # the mesh query agrees with the analytic box distance
    probe = np.array([[3.0, 0, 0], [0.5, 0, 0], [2.0, 2.0, 0]])
    if kind == "mesh":
        assert np.allclose(obstacles.distance(probe), [2.0, -0.5, math.sqrt(2.0)], atol=1e-5)
    clearance = {}
    for w in (2.0, 0.0):
        p = BoidParams(max_speed=3.0, min_speed=2.0, max_force=6.0, avoid_weight=w, avoid_distance=2.0,
                       body_radius=0.2, perception_radius=1.0, separation_radius=0.5)
        flock = Flock(x, v, params=p, obstacles=obstacles, device=CPU)
        clearance[w] = min(run(flock, 120, 0.05, lambda f: obstacles.distance(f.positions.numpy()).min()))
    assert clearance[0.0] >= 0.2 - 1e-4  # never inside, even without steering (position correction)
    assert clearance[2.0] > 0.6  # steering keeps them well clear


# --------------------------------------------------------------------------------------
# Terrain and ground agents
# --------------------------------------------------------------------------------------
def bilinear(h, spacing, origin, x, z):
    fx = np.clip((x - origin[0]) / spacing, 0, h.shape[0] - 1)
    fz = np.clip((z - origin[1]) / spacing, 0, h.shape[1] - 1)
    i = np.minimum(fx.astype(int), h.shape[0] - 2)
    k = np.minimum(fz.astype(int), h.shape[1] - 2)
    u, w = fx - i, fz - k
    return ((1 - u) * (1 - w) * h[i, k] + u * (1 - w) * h[i + 1, k] + (1 - u) * w * h[i, k + 1]
            + u * w * h[i + 1, k + 1])


def test_terrain_sampling():
    rng = np.random.default_rng(1)
    h = rng.uniform(0.0, 2.0, (7, 5))
    terrain = Terrain.from_heights(h, 0.5, origin=(-1.0, 2.0))
    pts = np.stack([rng.uniform(-2, 3, 200), np.zeros(200), rng.uniform(1, 5, 200)], axis=1)
    s = terrain.sample(pts)
    assert np.allclose(s[:, 0], bilinear(h, 0.5, (-1.0, 2.0), pts[:, 0], pts[:, 2]), atol=1e-5)
    eps = 1e-3
    inside = (pts[:, 0] > -1 + eps) & (pts[:, 0] < 2 - eps) & (pts[:, 2] > 2 + eps) & (pts[:, 2] < 4 - eps)
    num = (bilinear(h, 0.5, (-1.0, 2.0), pts[:, 0] + eps, pts[:, 2]) -
           bilinear(h, 0.5, (-1.0, 2.0), pts[:, 0] - eps, pts[:, 2])) / (2 * eps)
    near_edge = np.abs(np.mod(pts[:, 0] + 1, 0.5) - 0.25) > 0.25 - 2 * eps
    ok = inside & ~near_edge
    assert np.allclose(s[ok, 1], num[ok], atol=1e-2)
    # a planar ramp as a triangle mesh gives the same heights and slopes as its height field
    ramp = Terrain.from_function(lambda x, z: 0.3 * x - 0.1 * z + 1.0, (0, 0), (4, 4), 1.0)
    mesh = Terrain.from_mesh(*ramp.mesh())
    q = np.stack([rng.uniform(0.1, 3.9, 50), np.zeros(50), rng.uniform(0.1, 3.9, 50)], axis=1)
    a, b = ramp.sample(q), mesh.sample(q)
    assert np.allclose(a, b, atol=1e-4)
    assert np.allclose(b[:, 1:], [0.3, -0.1], atol=1e-4)
    # walkers on the mesh terrain follow its surface (a 30 % rise is still walked, 0.3 <= max_slope)
    crowd = Crowd([[0.5, 0, 2.0]], [[3.5, 0, 2.0]], params=WalkerParams(max_slope=0.35), terrain=mesh, device=CPU)
    ys = run(crowd, 60, 0.05, lambda c: c.positions.numpy()[0].copy())
    for y in ys:
        assert abs(y[1] - (0.3 * y[0] - 0.1 * y[2] + 1.0)) < 1e-4
    assert ys[-1][0] > 2.5 and crowd.state.numpy()[0] == WALKING


def ramp_terrain():
    """Flat, a walkable 20 % ramp, flat, a 100 % (too steep) ramp, flat."""
    xs, hs = [0, 5, 10, 15, 17, 30], [0, 0, 1, 1, 3, 3]
    return Terrain.from_function(lambda x, z: np.interp(x, xs, hs) + 0.0 * z, (0, -5), (30, 5), 0.5), xs, hs


def test_walkers_follow_slope_rules():
    terrain, xs, hs = ramp_terrain()
    rng = np.random.default_rng(0)
    n, dt = 20, 0.05
    x = np.stack([rng.uniform(0.5, 3, n), np.zeros(n), rng.uniform(-4, 4, n)], axis=1)
    goal = x.copy()
    goal[:, 0] = 28.0
    p = WalkerParams(max_speed=1.4, fall_rate=1.0, recovery_time=0.5, climb_speed=0.3, personal_radius=0.8,
                     personal_distance=0.5)
    crowd = Crowd(x, goal, params=p, terrain=terrain, bounds=((0, -10, -5), (30, 10, 5)), device=CPU)
    rec = run(crowd, 700, dt, lambda c: (c.state.numpy().copy(), c.positions.numpy().copy()))
    S = np.array([r[0] for r in rec])
    X = np.array([r[1] for r in rec])
    h = np.interp(X[..., 0], xs, hs)
    assert (X[..., 1] - h).min() > -1e-4  # never below the terrain
    run_ = np.hypot(*(np.diff(X[..., [0, 2]], axis=0)).transpose(2, 0, 1))
    rise = np.abs(np.diff(h, axis=0))
    walking = (S[1:] == WALKING) & (run_ > 1e-5)
    assert (rise[walking] / run_[walking]).max() <= p.max_slope + 1e-3  # never walks steeper than max_slope
    on_gentle_ramp = (X[1:, :, 0] > 5.2) & (X[1:, :, 0] < 9.8) & (X[:-1, :, 0] > 5.2) & (X[:-1, :, 0] < 9.8)
    assert (S[1:][on_gentle_ramp] == WALKING).all() and on_gentle_ramp.sum() > 100  # 20 % is walked
    climbing = S[1:] == CLIMBING
    assert climbing.sum() > 100
    speed_along = np.sqrt(run_ ** 2 + rise ** 2) / dt
    assert speed_along[climbing].max() <= p.climb_speed * 1.001 + 1e-4  # climbs slowly
    assert (S == FALLEN).any() and (S[-1] != FALLEN).any()
    # each fall: a particle under gravity while airborne, then lies recovery_time, then walks
    episodes = 0
    for a in range(n):
        for t in range(2, len(S) - 1):
            if S[t, a] == FALLEN and S[t - 1, a] == FALLEN and S[t - 2, a] == FALLEN:
                airborne = all(X[k, a, 1] > np.interp(X[k, a, 0], xs, hs) + 1e-3 for k in (t - 2, t - 1))
                if airborne and X[t, a, 1] > np.interp(X[t, a, 0], xs, hs) + 1e-3:
                    acc = (X[t, a, 1] - 2 * X[t - 1, a, 1] + X[t - 2, a, 1]) / dt ** 2
                    assert abs(acc - p.gravity[1]) < 1e-2 * 9.81
        lying = (S[:, a] == FALLEN) & np.r_[False, np.all(np.diff(X[:, a], axis=0) == 0, axis=1)]
        starts = np.flatnonzero(lying & ~np.r_[False, lying[:-1]])
        for s0 in starts:
            up = s0 + np.flatnonzero(S[s0:, a] != FALLEN)
            if len(up):
                # the agent stopped at step s0 - 1 and lies from there until it gets up
                assert abs((up[0] - (s0 - 1)) * dt - p.recovery_time) <= dt + 1e-9
                assert S[up[0], a] in (WALKING, CLIMBING)
                episodes += 1
    assert episodes >= 5


def test_personal_space_between_strangers():
    # two files of strangers walk head-on through each other, and one family of 4 walks along
    n = 12
    z = np.arange(n) - 0.5 * (n - 1)
    x = np.concatenate([np.stack([np.full(n, -6.0), np.zeros(n), z], 1),
                        np.stack([np.full(n, 6.0), np.zeros(n), z + 0.15], 1)])
    goals = x * [-1, 1, 1]
    result = {}
    for personal in (True, False):
        p = WalkerParams(max_speed=1.3, personal_radius=1.2 if personal else 0.0,
                         personal_distance=0.6 if personal else 0.0, group_radius=0.0, min_distance=0.0)
        crowd = Crowd(x, goals, params=p, device=CPU)
        dists = run(crowd, 600, 0.05, lambda c: nearest_distances(c.positions.numpy()).min())
        result[personal] = (min(dists), (crowd.distance_to_goals() < 1.0).mean())
    assert result[True][0] > 0.8 * 0.6 and result[True][1] > 0.9  # keep space, still arrive
    assert result[False][0] < 0.2  # without personal space they brush past each other
    # a group stays together while walking: its members keep within a few metres
    fam = np.array([[0.0, 0, 0], [0.5, 0, 0.3], [0.2, 0, -0.5], [-0.4, 0, 0.2]])
    goals = fam + [20.0, 0, 0] + np.array([[0.0, 0, 1.0], [0, 0, -1.0], [0, 0, 0.5], [0, 0, -0.5]])
    crowd = Crowd(fam, goals, groups=[0, 0, 0, 0], params=WalkerParams(), device=CPU)
    spread = run(crowd, 200, 0.05, lambda c: radius_of_gyration(c.positions.numpy()))
    assert max(spread) < 1.2 and nearest_distances(crowd.positions.numpy()).min() > 0.35


# --------------------------------------------------------------------------------------
# Scenes, determinism, USD
# --------------------------------------------------------------------------------------
def test_zombies_get_over_the_wall_and_runs_are_deterministic():
    from warpsim.scenes import get_scene

    cls = get_scene("zombies")
    scenes = [cls({"zombies": 40, "recovery_time": 5.0, "seed": s}, device=CPU) for s in (0, 0, 1)]
    fractions = []
    for frame in range(1, 1201):
        for sc in scenes:
            sc.advance(1.0 / 24.0, 1)
        if frame % 300 == 0:
            fractions.append(scenes[0].over_wall_fraction())
    print("zombies over the wall at 12.5 s intervals:", fractions)
    assert fractions[0] == 0.0  # nobody is over the wall after 12.5 s
    assert fractions[-1] >= 0.5  # at least half after 50 s
    assert fractions == sorted(fractions)
    a, b, c = (sc.agents.positions.numpy() for sc in scenes)
    assert np.array_equal(a, b)  # same seed: bit-identical
    assert not np.array_equal(a, c)
    assert (scenes[0].agents.state.numpy() != FALLEN).any()


def test_crowd_scene_reaches_destinations():
    from warpsim.scenes import get_scene

    sc = get_scene("crowd")({"people": 80, "plaza": 20.0}, device=CPU)
    g = sc.agents.group_ids.numpy()
    closest = np.inf
    for frame in range(1, 721):
        sc.advance(1.0 / 24.0, 1)
        if frame > 5 and frame % 3 == 0:
            d = nearest_distances(sc.agents.positions.numpy(), mask=lambda rows: g[None, :] != g[rows, None])
            closest = min(closest, d.min())
    assert sc.arrived_fraction() > 0.95
    assert closest > 0.6 * sc.agents.params.personal_distance


def test_scenes_write_usd(tmp_path):
    pytest.importorskip("pxr")
    from pxr import Usd, UsdGeom

    from warpsim.scenes import get_scene
    from warpsim.usd.writer import UsdCacheWriter

    small = {"flock": {"birds": 30, "geese": 6, "food": 2}, "school": {"fish": 10},
             "zombies": {"zombies": 10}, "crowd": {"people": 12, "plaza": 12.0}}
    for name, params in small.items():
        sc = get_scene(name)(params, device=CPU)
        path = tmp_path / f"{name}.usda"
        with UsdCacheWriter(path, fps=24) as w:
            sc.declare(w)
            w.write_frame(0, sc.frame_data())
            for frame in (1, 2):
                sc.advance(1.0 / 24.0, 1)
                w.write_frame(frame, sc.frame_data())
        stage = Usd.Stage.Open(str(path))
        inst = UsdGeom.PointInstancer(stage.GetPrimAtPath("/World/agents"))
        pos = np.array(inst.GetPositionsAttr().Get(2))
        quat = inst.GetOrientationsAttr().Get(2)
        state = np.array(UsdGeom.PrimvarsAPI(inst).GetPrimvar("state").Get(2))
        assert len(pos) == len(state) == sc.agents.agent_count
        assert set(state.tolist()) <= {int(s) for s in AgentState}
        if name in ("flock", "school"):
            # orientation from velocity: the prototype's +Z turned to the heading
            vel = sc.agents.velocities.numpy()
            for q, v in list(zip(quat, vel))[:5]:
                im = np.array(q.GetImaginary())
                z = np.array([0.0, 0, 1])
                rz = z + 2 * np.cross(im, np.cross(im, z) + q.GetReal() * z)
                assert np.allclose(rz, v / np.linalg.norm(v), atol=5e-3)
        if name in ("flock", "zombies"):
            assert stage.GetPrimAtPath("/World/terrain").IsA(UsdGeom.Mesh)


def test_checkpoint_roundtrip():
    from warpsim.scenes import get_scene

    cls = get_scene("flock")
    a = cls({"birds": 20, "geese": 5, "food": 1}, device=CPU)
    b = cls({"birds": 20, "geese": 5, "food": 1}, device=CPU)
    for _ in range(5):
        a.advance(1 / 24, 2)
    b.restore(a.checkpoint())
    for _ in range(5):
        a.advance(1 / 24, 2)
        b.advance(1 / 24, 2)
    assert np.array_equal(a.agents.positions.numpy(), b.agents.positions.numpy())


# --------------------------------------------------------------------------------------
# Bad input
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("make, words", [
    (lambda: Flock(np.zeros((3, 2))), "positions"),
    (lambda: Flock([[0, 0, 0], [np.nan, 0, 0]]), r"positions\[1\]"),
    (lambda: Flock(np.zeros((2, 3)), np.zeros((3, 3))), "velocities"),
    (lambda: Flock(np.zeros((2, 3)), params=BoidParams(max_speed=-1.0)), "max_speed"),
    (lambda: Flock(np.zeros((2, 3)), params=BoidParams(min_speed=9.0, max_speed=8.0)), "min_speed"),
    (lambda: Flock(np.zeros((2, 3)), params=BoidParams(fov_deg=400.0)), "fov_deg"),
    (lambda: Flock(np.zeros((2, 3)), params=BoidParams(draft_saving=1.5)), "draft_saving"),
    (lambda: Flock(np.zeros((2, 3)), species=[0, 2], params=[BoidParams(), BoidParams()]), r"species\[1\]"),
    (lambda: Flock(np.zeros((2, 3)), params=BoidParams(drain_rate=0.1)), "terrain"),
    (lambda: Flock(np.zeros((2, 3)), wrap=True), "bounds"),
    (lambda: Flock(np.zeros((2, 3)), bounds=((0, 0, 0), (4, 4, 4)), wrap=True), "twice"),
    (lambda: Flock(np.zeros((2, 3)), bounds=((0, 0, 0), (4, -1, 4))), "bounds upper"),
    (lambda: Flock(np.zeros((2, 3)), state=[0, 4]), r"state\[1\]"),
    (lambda: Flock(np.zeros((2, 3))).step(0.0), "dt"),
    (lambda: FoodSources([[0, 0, 0]], [-1]), "food source 0"),
    (lambda: FoodSources([[0, 0, 0], [1, 1, 1]], [1.5, 2]), "food source 0"),
    (lambda: Obstacles(spheres=[((0, 0, 0), -1.0)]), "sphere 0 radius"),
    (lambda: Obstacles(planes=[((0, 0, 0), 1.0)]), "plane 0"),
    (lambda: Obstacles(meshes=[(np.zeros((3, 3)), [[0, 1, 5]])]), "triangle 0"),
    (lambda: Terrain.from_heights(np.zeros((1, 4)), 1.0), "2 x 2"),
    (lambda: Terrain.from_heights(np.zeros((3, 3)), 0.0), "spacing"),
    (lambda: Crowd(np.zeros((2, 3)), np.zeros((3, 3))), "goals"),
    (lambda: Crowd(np.zeros((2, 3)), np.zeros(3), params=WalkerParams(max_slope=0.0)), "max_slope"),
    (lambda: Crowd(np.zeros((2, 3)), np.zeros(3), groups=[0, -1]), r"groups\[1\]"),
    (lambda: Crowd(np.zeros((2, 3)), np.zeros(3), terrain="hills"), "terrain"),
])
def test_bad_input_names_the_item(make, words):
    with pytest.raises(ValueError, match=words):
        make()


def test_scene_bad_parameter():
    from warpsim.scenes import get_scene

    with pytest.raises(ValueError, match="zombies"):
        get_scene("zombies")({"zombies": 0}, device=CPU)
    with pytest.raises(ValueError, match="size"):
        get_scene("school")({"size": (10.0, -1.0, 10.0)}, device=CPU)


def test_warp_device_arrays_stay_put():
    """A step allocates nothing: the agent arrays keep their buffers."""
    flock = Flock(np.random.default_rng(0).uniform(0, 5, (50, 3)), params=BoidParams(), device=CPU)
    ptrs = [arr.ptr for arr in (flock.positions, flock.velocities, flock.separation, flock.state)]
    flock.step(0.01)
    assert ptrs == [arr.ptr for arr in (flock.positions, flock.velocities, flock.separation, flock.state)]
    assert wp.get_device(CPU) == flock.device
