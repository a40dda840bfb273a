"""Springs that break (warpsim.core.fracture) and the ``wall`` scene: a spring under a growing load
breaks within one step of its threshold on every integrator and then stops acting for good
(implicit Euler's Jacobian included); momentum is conserved across a break; a brick wall stays
whole under a slow ball and breaks into pieces under a fast one; the USD springs curves lose the
broken springs; bad thresholds are clear errors."""
import numpy as np
import pytest
import warp as wp

import warpsim as ws
from warpsim.cloth.solver import ClothImplicitEuler, ClothSemiImplicitEuler, ClothSimulator
from warpsim.scenes import get_scene
from warpsim.scenes.fracture import pieces

DEVICE = "cpu"
RATE = 40.0  # load growth [N/s]
K, C, MASS, DT = 200.0, 20.0, 0.1, 2.0e-3


@wp.func
def growing_load(x: wp.vec3, v: wp.vec3, t: float) -> wp.vec3:
    return wp.vec3(0.0, -40.0 * t, 0.0)  # RATE


def _pulled_springs():
    """Two pinned anchors, each holding a 0.1 kg particle 1 m below by a spring (k = 200 N/m,
    c = 20 N s/m); spring 0 breaks at 20 N of tension, spring 1 at 10 % strain."""
    b = ws.ModelBuilder()
    for x, kw in ((0.0, {"break_force": 20.0}), (2.0, {"break_strain": 0.1})):
        top = b.add_particle((x, 1.0, 0.0), mass=0.0)
        low = b.add_particle((x, 0.0, 0.0), mass=MASS)
        b.add_spring(top, low, K, C, **kw)
    return b.finalize(DEVICE)


INTEGRATORS = {
    **{name: (lambda name=name: name) for name in ws.INTEGRATORS},
    "implicit_euler_1newton": lambda: ws.ImplicitEuler(newton_iterations=1),
    "cloth_implicit_euler": lambda: ClothImplicitEuler(),
    "cloth_semi_implicit_euler": lambda: ClothSemiImplicitEuler(mode="scatter"),
}


@pytest.mark.parametrize("name", sorted(INTEGRATORS))
def test_growing_load_breaks_within_one_step_of_threshold_and_the_spring_stops_acting(name):
    model = _pulled_springs()
    cls = ClothSimulator if name.startswith("cloth") else ws.Simulator
    sim = cls(model, integrator=INTEGRATORS[name](), forces=[ws.ForceField(growing_load)])
    assert sim.fracture is not None and model.breakable_spring_count == 2
    low = [1, 3]
    strain, tension, broken, vy = [], [], [], []
    for _ in range(520):
        sim.step(DT)
        x, v = sim.state.positions.numpy(), sim.state.velocities.numpy()
        strain.append([np.linalg.norm(x[0] - x[1]) - 1.0, np.linalg.norm(x[2] - x[3]) - 1.0])
        tension.append(K * strain[-1][0] + C * (v[0, 1] - v[1, 1]))  # k x + c dl/dt of spring 0
        broken.append(model.spring_broken.numpy().copy())
        vy.append(sim.state.velocities.numpy()[low, 1].copy())
    strain, broken, vy = np.array(strain), np.array(broken), np.array(vy)
    t = DT * np.arange(1, len(strain) + 1)
    first = [int(np.argmax(broken[:, s])) for s in range(2)]
    assert broken[-1].all() and all(k > 0 for k in first)
    # force threshold: the first step that ends with a tension past 20 N is the step it breaks;
    # the tension k x + c x' equals the load minus m a, so that is when the load passes 20 N,
    # t = 0.5 s, give or take the integrator's lag (allowed: 3 steps; Baraff-Witkin lags most)
    assert first[0] == int(np.argmax(np.array(tension) > 20.0))
    assert abs(t[first[0]] - 20.0 / RATE) <= 3 * DT, (t[first[0]], name)
    # strain threshold: the first step that ends past 10 % strain is the step it breaks
    over = int(np.argmax(strain[:, 1] > 0.1))
    assert first[1] == over, (first[1], over, strain[over - 1: over + 1, 1])
    # ... which, with the damper's lag c / k = 0.1 s behind the load, is near t = 0.6 s
    assert abs(t[first[1]] - (20.0 / RATE + C / K)) < 0.02
    # for good: afterwards each particle falls under the load alone, dv = -RATE t dt / m per step
    # (a spring left in an implicit Jacobian would slow it by h c / m = 20 %)
    for s in range(2):
        k0 = first[s] + 5
        k1 = k0 + 200
        expected = -(RATE / MASS) * 0.5 * (t[k1] ** 2 - t[k0] ** 2)
        assert vy[k1, s] - vy[k0, s] == pytest.approx(expected, rel=0.01), (name, s)
        assert broken[first[s]:, s].all()
    reports = sim.fracture.history
    assert reports == []  # reports come per frame from run(); step() alone leaves the mask
    assert sim.fracture.broken_count == 2


def test_breaks_are_reported_per_frame_by_run():
    model = _pulled_springs()
    sim = ws.Simulator(model, forces=[ws.ForceField(growing_load)])
    sim.run(frames=45, frame_dt=1.0 / 60.0, substeps=17)
    reports = sim.fracture.history
    assert [r.frame for r in reports] == list(range(1, 46))
    hits = {r.frame: list(r.springs) for r in reports if r.count}
    # 0.5 s and ~0.6 s: frames 30 and 36 or 37 (60 fps)
    assert hits.get(30) == [0] or hits.get(31) == [0], hits
    assert sum(r.count for r in reports) == 2 and any(v == [1] for v in hits.values())


def test_broken_spring_leaves_the_jacobian():
    b = ws.ModelBuilder()
    for p in ((0, 0, 0), (1.2, 0, 0), (2.0, 0.5, 0)):
        b.add_particle(p)
    b.add_spring(0, 1, 100.0, 3.0, rest_length=1.0, break_strain=0.5)
    b.add_spring(1, 2, 50.0, 1.0, rest_length=1.0)
    model = b.finalize(DEVICE)
    system = ws.ParticleSystem(model, [])
    q, qd = model.particle_q, wp.array(np.ones((3, 3), np.float32), dtype=wp.vec3, device=DEVICE)
    time = wp.zeros(1, dtype=float, device=DEVICE)

    def blocks():
        n = system.jacobian_triplet_count()
        diag = wp.zeros(3, dtype=wp.mat33, device=DEVICE)
        rows, cols = wp.zeros(n, dtype=int, device=DEVICE), wp.zeros(n, dtype=int, device=DEVICE)
        values = wp.zeros(n, dtype=wp.mat33, device=DEVICE)
        system.eval_jacobians(q, qd, time, 0.0, 1.0, 1.0, diag, rows, cols, values)
        f = wp.zeros(3, dtype=wp.vec3, device=DEVICE)
        system.eval_forces(q, qd, time, 0.0, f)
        return diag.numpy(), rows.numpy(), values.numpy(), f.numpy()

    d0, r0, v0, _ = blocks()
    model.spring_broken.assign(np.array([1, 0], dtype=np.int32))
    d1, r1, v1, f1 = blocks()
    assert np.abs(v0[:2]).max() > 10.0 and np.abs(v1[:2]).max() == 0.0  # spring 0's couplings: zero
    np.testing.assert_array_equal(r0, r1)  # same sparsity pattern (graph capture keeps working)
    np.testing.assert_array_equal(v0[2:], v1[2:])
    np.testing.assert_allclose(d1[0], 0.0)  # particle 0 only touched spring 0
    np.testing.assert_allclose(d1[1], d0[1] - d0[0], atol=1e-4)
    np.testing.assert_allclose(f1[0], 0.0)
    np.testing.assert_allclose(f1[1] + f1[2], 0.0, atol=1e-5)


@pytest.mark.parametrize("integrator", ["semi_implicit_euler", "rk4", "implicit_euler"])
def test_momentum_is_conserved_across_a_break(integrator):
    """A free chain (masses 1, 2, 3 kg) flung apart; the middle spring breaks mid-run."""
    b = ws.ModelBuilder()
    b.add_particle((0, 0, 0), vel=(-1.0, 0.3, 0.0), mass=1.0)
    b.add_particle((1, 0, 0), vel=(0.2, -0.1, 0.4), mass=2.0)
    b.add_particle((2, 0.2, 0), vel=(1.5, 0.2, -0.3), mass=3.0)
    b.add_spring(0, 1, 50.0, 0.5)
    b.add_spring(1, 2, 80.0, 0.5, break_strain=0.15)
    model = b.finalize(DEVICE)
    sim = ws.Simulator(model, integrator=integrator, forces=[])
    m = model.particle_mass.numpy().astype(np.float64)[:, None]
    p0 = (m * sim.state.velocities.numpy()).sum(0)
    momenta, broken = [], []
    for _ in range(400):
        sim.step(2.0e-3)
        v = sim.state.velocities.numpy().astype(np.float64)
        momenta.append(((m * v).sum(0), (m[2] * v[2])))
        broken.append(int(model.spring_broken.numpy()[1]))
    k = broken.index(1)
    assert 10 < k < 300 and model.spring_broken.numpy()[0] == 0
    total = np.array([p for p, _ in momenta])
    np.testing.assert_allclose(total, np.broadcast_to(p0, total.shape), atol=2e-5 * np.abs(p0).max())
    # after the break nothing acts on particle 2 any more: its own momentum is constant
    third = np.array([p for _, p in momenta[k + 1:]])
    np.testing.assert_allclose(third, np.broadcast_to(third[0], third.shape), atol=1e-5)


def _wall(speed, frames, ball_velocities=None):
    cls = get_scene("wall")
    scene = cls(cls.resolve_params({"ball_speed": speed, "bricks": (3.0, 3.0)}), device=DEVICE)
    for _ in range(frames):
        scene.advance(1.0 / 60.0, scene.substeps)
        if ball_velocities is not None:
            ball_velocities.append(scene.sim.state.velocities.numpy()[scene.ball].mean(0))
    model = scene.sim.model
    broken = model.spring_broken.numpy()
    labels = pieces(model.spring_indices.numpy(), broken, scene.wall.nodes)
    return scene, broken, labels


def test_wall_stays_whole_under_a_slow_ball_and_breaks_under_a_fast_one():
    v_ball = []
    slow, broken, labels = _wall(1.0, 24, v_ball)
    assert broken.sum() == 0 and labels.max() == 0
    # it bounced off (the ball, raised clear of the floor on a wall this low, then rocks against it)
    assert min(v[2] for v in v_ball) < -0.2
    assert all(r.count == 0 for r in slow.sim.fracture.history)

    fast, broken, labels = _wall(12.0, 24)
    mortar = fast.wall.mortar_springs
    assert broken[fast.wall.brick_springs].sum() == 0  # bricks stay whole (unbreakable springs)
    assert broken[mortar].sum() > 0.1 * len(mortar)
    sizes = np.bincount(labels)
    assert len(sizes) >= 3  # pieces
    assert np.all(sizes % 8 == 0)  # every piece is made of whole bricks (4 x 2 x 2 nodes; half bricks at the ends)
    # reports add up to the mask, and the pieces knocked out fly off and fall
    assert sum(r.count for r in fast.sim.fracture.history) == broken.sum()
    x0 = fast.sim.model.particle_q.numpy()[fast.wall.nodes]
    x = fast.sim.state.positions.numpy()[fast.wall.nodes]
    moved = np.linalg.norm(x - x0, axis=1)
    assert moved.max() > 0.5
    ball = fast.sim.state.velocities.numpy()[fast.ball].mean(0)
    assert ball[2] > 3.0  # the ball went on through


def test_wall_cache_curves_lose_broken_springs(tmp_path):
    pytest.importorskip("pxr")
    from pxr import Usd

    from warpsim.cli import main

    path = tmp_path / "wall.usda"
    code = main(["run", "wall", "--frames", "3", "--out", str(path), "--device", DEVICE, "--no-progress",
                 "--set", "bricks=2,2", "--set", "ball_speed=20"])
    assert code == 0
    stage = Usd.Stage.Open(str(path))
    springs = stage.GetPrimAtPath("/World/springs")
    broken = np.asarray(springs.GetAttribute("primvars:broken").Get(3))
    points = np.asarray(springs.GetAttribute("points").Get(3)).reshape(-1, 2, 3)
    length = np.linalg.norm(points[:, 0] - points[:, 1], axis=1)
    assert broken.sum() > 0 and springs.GetAttribute("warpsim:brokenCount").Get(3) == broken.sum()
    assert np.all(length[broken == 1] == 0.0) and np.all(length[broken == 0] > 0.0)
    per_frame = [len(springs.GetAttribute("warpsim:brokenThisFrame").Get(f) or []) for f in range(4)]
    assert per_frame[0] == 0 and sum(per_frame) == broken.sum()
    assert np.asarray(springs.GetAttribute("primvars:broken").Get(0)).sum() == 0


@pytest.mark.parametrize("kw, words", [
    ({"break_strain": -0.1}, ["spring 1", "break_strain", "-0.1"]),
    ({"break_strain": float("nan")}, ["spring 1", "break_strain", "nan"]),
    ({"break_force": -5.0}, ["spring 1", "break_force", "-5"]),
    ({"break_force": float("nan")}, ["spring 1", "break_force", "nan"]),
    ({"break_force": 0.0}, ["spring 1", "break_force"]),
    ({"break_strain": float("inf")}, ["spring 1", "break_strain", "finite"]),
    ({"break_force": "strong"}, ["spring 1", "break_force", "strong"]),
    ({"break_strain": 0.1, "rest_length": 0.0}, ["spring 1", "rest length 0", "break_force"]),
])
def test_bad_thresholds_are_clear_errors(kw, words):
    b = ws.ModelBuilder()
    for k in range(3):
        b.add_particle((k, 0, 0))
    b.add_spring(0, 1, 10.0)
    with pytest.raises(ValueError) as err:
        b.add_spring(1, 2, 10.0, **kw)
    for word in words:
        assert word in str(err.value)
    assert b.spring_count == 1  # nothing half-added


def test_set_spring_breaking_validates_and_marks_springs():
    b = ws.ModelBuilder()
    for k in range(4):
        b.add_particle((k, 0, 0))
    for k in range(3):
        b.add_spring(k, k + 1, 10.0)
    b.set_spring_breaking(range(1, 3), break_strain=0.2)
    with pytest.raises(ValueError, match="spring 0 has break_force -1"):
        b.set_spring_breaking([0], break_force=-1)
    with pytest.raises(ValueError, match="spring index 7 is out of range"):
        b.set_spring_breaking([7], break_force=1.0)
    model = b.finalize(DEVICE)
    assert model.breakable_spring_count == 2
    np.testing.assert_array_equal(np.isfinite(model.spring_break_strain.numpy()), [False, True, True])


def test_gather_cloth_refuses_breakable_springs():
    b = ws.ModelBuilder()
    b.add_particle((0, 0, 0), mass=0.0)
    b.add_particle((0, -1, 0))
    b.add_spring(0, 1, 10.0, break_force=5.0)
    with pytest.raises(ValueError, match="gather"):
        ClothSimulator(b.finalize(DEVICE), integrator=ClothSemiImplicitEuler(mode="gather"))


def test_wall_rejects_bad_parameters():
    cls = get_scene("wall")
    with pytest.raises(ValueError, match="mortar_strength"):
        cls(cls.resolve_params({"mortar_strength": -1.0}), device=DEVICE)
    with pytest.raises(ValueError, match="multiple of"):
        cls(cls.resolve_params({"brick_size": (0.23, 0.1, 0.1)}), device=DEVICE)


def test_wall_checkpoint_restores_the_broken_springs_bit_for_bit():
    cls = get_scene("wall")
    params = cls.resolve_params({"bricks": (2.0, 2.0), "ball_speed": 20.0})
    a = cls(params, device=DEVICE)
    for _ in range(3):
        a.advance(1.0 / 60.0, a.substeps)
    saved = a.checkpoint()
    assert saved["spring_broken"].sum() > 0
    b = cls(params, device=DEVICE)
    b.restore(saved)
    for scene in (a, b):
        for _ in range(2):
            scene.advance(1.0 / 60.0, scene.substeps)
    np.testing.assert_array_equal(a.sim.state.positions.numpy(), b.sim.state.positions.numpy())
    np.testing.assert_array_equal(a.sim.model.spring_broken.numpy(), b.sim.model.spring_broken.numpy())
    assert [r.springs.tolist() for r in a.sim.fracture.history[3:]] == \
        [r.springs.tolist() for r in b.sim.fracture.history]
    assert [r.frame for r in b.sim.fracture.history] == [4, 5]


def test_springs_break_inside_captured_frames():
    """ClothSimulator replays each frame as a captured graph (CPU too): the mask lives on the
    device, so a break inside a replayed frame is seen and the spring stays broken."""
    model = _pulled_springs()
    sim = ClothSimulator(model, integrator="implicit_euler", forces=[ws.ForceField(growing_load)])
    assert sim.use_graph
    sim.run(frames=45, frame_dt=1.0 / 60.0, substeps=10)
    assert len(sim._graphs) == 1  # every frame after the first was a replay
    hits = {r.frame: r.springs.tolist() for r in sim.fracture.history if r.count}
    assert hits.get(31) == [0] or hits.get(30) == [0], hits  # 20 N at t = 0.5 s
    assert sorted(s for v in hits.values() for s in v) == [0, 1]
    # after the break: free fall under the load alone, v = -(RATE / m) (t^2 - t_b^2) / 2
    v = sim.state.velocities.numpy()[1, 1]
    assert v == pytest.approx(-(RATE / MASS) * 0.5 * (0.75 ** 2 - 0.5 ** 2), rel=0.02)
