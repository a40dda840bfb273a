"""The cloth "lanes" step (eight particles a thread sharing a neighbour pattern, springs in SIMD
lanes): its blocks cover the model's CSR rows exactly, and it gives the scatter and owner modes'
bits."""

import numpy as np
import pytest
import warp as wp
from warpsim.kernels import collide as KC
from warpsim.kernels import collide_lanes as KL
from warpsim.kernels.cloth_lanes import LANES, ROW_MAX

import warpsim as ws
from warpsim.bodies.colliders import Capsule, Sphere
from warpsim.cloth.builder import add_cloth_grid
from warpsim.cloth.lanes import build_lane_blocks
from warpsim.cloth.solver import ClothSemiImplicitEuler, ClothSimulator
from warpsim.core.model import ensure_spring_adjacency

DEVICE = "cpu"


def grid(resolution, reverse=False, distinct=False):
    b = ws.ModelBuilder()
    add_cloth_grid(b, resolution, (0.3, 0.3), (0.0, 1.0, 0.0), particle_mass=0.1, pin=["corner_00", "corner_10"],
                   stiffness=400.0, damping=1.0)
    if reverse:  # first end the higher index
        b.spring_indices = [(int(j), int(i)) for i, j in np.asarray(b.spring_indices).reshape(-1, 2)]
    if distinct:
        b.spring_stiffness = list(np.random.default_rng(2).uniform(300.0, 500.0, b.spring_count))
    return b


def test_blocks_cover_every_row_entry_in_order():
    """Every particle is in one block (padding repeats a particle of its block); lane c of block
    b at entry k reaches the other end of its particle's k-th CSR entry through the pattern's
    delta, and its slot names that entry's spring; consecutive blocks hold eight consecutive
    particles and come first."""
    model = grid((20, 12), reverse=True).finalize(DEVICE)
    ensure_spring_adjacency(model)
    offsets, springs = model.particle_spring_offsets.numpy(), model.particle_springs.numpy()
    ends = model.spring_indices.numpy().reshape(-1, 2)
    blocks = build_lane_blocks(offsets, springs, ends, model.particle_count)
    seen = np.zeros(model.particle_count, dtype=int)
    for b, (lanes, (start, count, slot, run)) in enumerate(zip(blocks.particles, blocks.info)):
        assert (run == 1) == (b < blocks.runs)
        if run:
            assert np.array_equal(lanes, lanes[0] + np.arange(LANES))
        for p in set(lanes.tolist()):
            seen[p] += 1
        for k in range(count):
            for c, p in enumerate(lanes):
                s = springs[offsets[p] + k]
                assert blocks.slot_springs[slot + k, c] == s
                assert p + blocks.deltas[start + k] == (ends[s, 1] if ends[s, 0] == p else ends[s, 0])
        assert all(offsets[p + 1] - offsets[p] == count for p in lanes)
    assert np.all(seen == 1)
    assert blocks.runs > 0 and blocks.utilisation >= 0.5  # the automatic choice takes lanes


def run_frames(mode, resolution, frames=20):
    b = grid(resolution, reverse=True, distinct=True)
    sim = ClothSimulator(b.finalize(DEVICE), ClothSemiImplicitEuler(mode),
                         forces=[ws.Gravity(), ws.Wind(coefficient=0.02)],
                         colliders=[ws.Plane(offset=0.9, restitution=0.0, friction=0.3),
                                    Sphere((0.15, 0.95, -0.15), 0.04, restitution=0.0, friction=0.3)])
    for frame in range(frames):
        if frame == frames // 2:  # changed in place: read again at the next frame
            sim.model.spring_stiffness.assign(0.5 * sim.model.spring_stiffness.numpy())
        sim.frame(1.0 / 60.0, 16)
    return sim.state.positions.numpy(), sim.state.velocities.numpy(), sim.integrator.mode


@pytest.mark.parametrize("resolution, mode", [((20, 12), None), ((5, 4), "lanes")])
def test_lanes_give_the_scatter_modes_bits(resolution, mode):
    """Captured frames with wind (an external force), a floor and a sphere, springs whose first
    end is the higher index, distinct stiffnesses halved in place half way: the lanes step gives
    the scatter mode's bits, with consecutive blocks (20 x 12, where it is the CPU default) and
    with per-lane blocks only (5 x 4: no eight consecutive rows alike; asked for by name)."""
    x_lanes, v_lanes, mode = run_frames(mode, resolution)
    x_scatter, v_scatter, _ = run_frames("scatter", resolution)
    assert mode == "lanes"
    assert x_lanes.tobytes() == x_scatter.tobytes() and v_lanes.tobytes() == v_scatter.tobytes()
    assert 0.88 < x_lanes[:, 1].min() < 0.95  # it fell onto the floor, which held it


def test_lanes_steps_like_eager_steps_and_runs_twice_alike():
    """ws.Simulator's eager steps (parameters read every step) give the frames' bits, and two runs
    give identical bytes."""
    def eager():
        sim = ws.Simulator(grid((20, 12)).finalize(DEVICE), ClothSemiImplicitEuler("lanes"))
        for _ in range(40):
            sim.step(1.0 / 960.0)
        return sim.state.positions.numpy()

    b = grid((20, 12))
    sim = ClothSimulator(b.finalize(DEVICE), ClothSemiImplicitEuler("lanes"), forces=[ws.Gravity()])
    for _ in range(4):
        sim.frame(1.0 / 96.0, 10)
    first = eager()
    assert first.tobytes() == eager().tobytes()
    assert first.tobytes() == sim.state.positions.numpy().tobytes()


def test_rows_longer_than_the_lanes_take_fall_back_to_owner():
    """A particle with more than ROW_MAX springs: mode='lanes' is refused with the figures, the
    automatic choice is owner."""
    b = ws.ModelBuilder()
    b.add_particle((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 0.0)
    for k in range(ROW_MAX + 1):
        angle = 2.0 * np.pi * k / (ROW_MAX + 1)
        b.add_particle((np.cos(angle), 0.0, np.sin(angle)), (0.0, 0.0, 0.0), 0.1)
        b.add_spring(0, k + 1, 100.0, 1.0)
    model = b.finalize(DEVICE)
    with pytest.raises(ValueError, match=f"at most {ROW_MAX} springs.*with {ROW_MAX + 1}"):
        ws.Simulator(model, ClothSemiImplicitEuler("lanes")).step(1e-3)
    sim = ws.Simulator(model, ClothSemiImplicitEuler())
    sim.step(1e-3)
    assert sim.integrator.mode == "owner"


def test_a_static_spheres_early_out_gives_the_full_tests_bits(monkeypatch):
    """The lanes frames with floor and sphere: the sphere's early-out (particles out of reach
    skip the local test) gives the bits of the full test on every particle, and the cloth does
    lie on the sphere (the comparison covers contacts)."""
    x_fast, v_fast, _ = run_frames(None, (20, 12))
    monkeypatch.setattr(Capsule, "_reach", lambda self, prev, now: (wp.vec3(0.0, 0.0, 0.0), -1.0))
    x_full, v_full, _ = run_frames(None, (20, 12))
    assert x_fast.tobytes() == x_full.tobytes() and v_fast.tobytes() == v_full.tobytes()
    on_sphere = np.linalg.norm(x_fast - (0.15, 0.95, -0.15), axis=1)
    assert np.sum(np.abs(on_sphere - 0.04) < 1e-3) >= 3  # particles of radius 0 resting on it


@pytest.mark.parametrize("mode", ["reflect", "project", "penalty", "seed"])
def test_early_out_equals_the_full_test_on_grazing_paths(mode):
    """Particles whose 0.1 m step passes a static, moved and turned sphere at 0.9 to 1.01 of its
    inflated radius r from its centre (and some far away), launched without the early-out, with
    it, and as the CPU's lanes kernel (eight a thread, 4003 particles: a padded last block): the
    same bytes; some were pushed out (contacts, found by the path test where the end point is
    outside), some grazed past untouched (penalty: velocity only)."""
    rng = np.random.default_rng(7)
    n = 4003
    cap = Sphere((0.3, 1.0, -0.2), 0.05, mode=mode, restitution=0.3, friction=0.2)
    cap.set_transform((0.4, 0.1, -0.3), (0.0, 0.0, np.sin(0.3), np.cos(0.3)))
    r = cap.radius + 0.01  # particle radius 0.01
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1)[:, None]
    along = np.cross(axis, rng.normal(size=(n, 3)))
    along /= np.linalg.norm(along, axis=1)[:, None]
    gap = np.where(rng.uniform(size=n) < 0.9, r * rng.uniform(0.9, 1.01, n), rng.uniform(0.5, 3.0, n))
    closest = cap.center + gap[:, None] * axis  # the path's point nearest the centre
    t = rng.uniform(-1.0, 1.0, (n, 1)) * 0.05  # paths of 0.1 m, many crossing the sphere's edge
    x0 = closest - (0.05 + t) * along
    x1 = closest + (0.05 - t) * along
    v = (x1 - x0) * 100.0  # 10 m/s over dt = 0.01 s

    def collide(early_out: bool, lanes: bool = False):
        q = wp.array(x1.astype(np.float32), dtype=wp.vec3, device=DEVICE)
        qd = wp.array(v.astype(np.float32), dtype=wp.vec3, device=DEVICE)
        prev, now = cap.advance_pose(0.01)  # static: the second pose equals the first
        prev, now = cap.advance_pose(0.01)
        reach = cap._reach(prev, now) if early_out else (wp.vec3(0.0, 0.0, 0.0), -1.0)
        assert (reach[1] >= 0.0) == early_out
        kernel, dim, head = (KL.collide_capsule_lanes, (n + LANES - 1) // LANES, [n]) if lanes else (
            KC.collide_capsule, n, [])
        wp.launch(kernel, dim,
                  inputs=[*head, wp.full(n, 1.0, dtype=float, device=DEVICE),
                          wp.full(n, 0.01, dtype=float, device=DEVICE),
                          wp.array(x0.astype(np.float32), dtype=wp.vec3, device=DEVICE), 1,
                          wp.vec3(*cap.a_local), wp.vec3(*cap.b_local), cap.radius, 0, prev, now, *reach,
                          *cap._contact_args(0.01), wp.zeros(n, dtype=wp.vec3, device=DEVICE), q, qd],
                  device=DEVICE)
        return q.numpy().tobytes() + qd.numpy().tobytes(), q.numpy(), qd.numpy()

    full, q_full, qd_full = collide(False)
    assert collide(True)[0] == full and collide(True, lanes=True)[0] == full
    touched = np.any(q_full != x1.astype(np.float32), axis=1) | np.any(qd_full != v.astype(np.float32), axis=1)
    assert 100 < touched[gap < r].sum() and 100 < (~touched[gap < 1.01 * r]).sum()  # contacts, grazes


@pytest.mark.parametrize("mode", ["reflect", "penalty"])
def test_planes_lanes_kernel_equals_the_per_particle_kernel(mode):
    """A box of six walls and 1003 particles ending within +-2 cm of them (steps of up to 5 cm,
    mass 0 for some): the CPU's lanes kernel gives collide_planes' bytes, some particles touched,
    some not."""
    rng = np.random.default_rng(3)
    n = 1003
    box = ws.Box((-0.5, 0.0, -0.5), (0.5, 1.0, 0.5), restitution=0.4, friction=0.3, mode=mode, thickness=0.003)
    box.bind(grid((3, 3)).finalize(DEVICE))
    x1 = rng.uniform(-0.52, 0.52, (n, 3)) + (0.0, 0.5, 0.0)
    x0 = x1 - rng.uniform(-0.05, 0.05, (n, 3))
    inv_mass = np.where(rng.uniform(size=n) < 0.1, 0.0, 1.0)

    def collide(lanes: bool):
        q = wp.array(x1.astype(np.float32), dtype=wp.vec3, device=DEVICE)
        qd = wp.array(((x1 - x0) * 50.0).astype(np.float32), dtype=wp.vec3, device=DEVICE)
        kernel, dim, head = (KL.collide_planes_lanes, (n + LANES - 1) // LANES, [n]) if lanes else (
            KC.collide_planes, n, [])
        wp.launch(kernel, dim,
                  inputs=[*head, wp.array(inv_mass.astype(np.float32), dtype=float, device=DEVICE),
                          wp.full(n, 0.01, dtype=float, device=DEVICE), box._normals, box._offsets,
                          *box._contact_args(0.02), wp.array(x0.astype(np.float32), dtype=wp.vec3, device=DEVICE),
                          wp.zeros(n, dtype=wp.vec3, device=DEVICE), q, qd],
                  device=DEVICE)
        return q.numpy(), qd.numpy()

    q_full, qd_full = collide(False)
    q_lanes, qd_lanes = collide(True)
    assert q_lanes.tobytes() == q_full.tobytes() and qd_lanes.tobytes() == qd_full.tobytes()
    touched = np.any(qd_full != ((x1 - x0) * 50.0).astype(np.float32), axis=1)
    assert 50 < touched.sum() < n - 50
