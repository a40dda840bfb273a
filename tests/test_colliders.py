"""Colliders (warpsim.bodies.colliders, kernels/collide.py) on the "cpu" device (and CUDA when present).

Oracles: bounce heights h' = e^2 h of a dropped particle, Coulomb sliding that stops exactly when
mu g t = v0, the penalty contact's static depth m g / k, the 1D two-body collision rule for
unequal masses, momentum conservation and energy decrease of 10,000 colliding particles,
(1 + e) U for a particle struck by a moving wall, and agreement between a triangle-mesh floor
and the analytic plane.
"""
import math

import numpy as np
import pytest

import warpsim as ws
from warpsim.bodies.colliders import (
    Capsule,
    ParticleCollisions,
    Quad,
    Sphere,
    TriangleMesh,
    damping_ratio_for_restitution,
)

DEVICE = "cpu"
G = 9.81


def one_particle(pos, vel=(0.0, 0.0, 0.0), mass=1.0, radius=0.0, device=DEVICE):
    b = ws.ModelBuilder()
    b.add_particle(pos, vel=vel, mass=mass, radius=radius)
    return b.finalize(device)


def trajectory(model, colliders, steps, dt, forces=None):
    """Positions and velocities after every step, shapes (steps, n, 3)."""
    sim = ws.Simulator(model, forces=forces, colliders=colliders, check_every=0)
    xs, vs = [], []
    for _ in range(steps):
        sim.step(dt)
        xs.append(sim.state.positions.numpy().copy())
        vs.append(sim.state.velocities.numpy().copy())
    return np.array(xs), np.array(vs)


def bounce_apex(xs, vs):
    """Height of the first apex after the first bounce."""
    y, vy = xs[:, 0, 1], vs[:, 0, 1]
    up = np.flatnonzero(vy > 0.0)[0]
    down = up + np.flatnonzero(vy[up:] <= 0.0)[0]
    return y[up:down + 1].max()


def floor_mesh(size=2.0):
    pts = np.array([[-size, 0, -size], [size, 0, -size], [size, 0, size], [-size, 0, size]], dtype=float)
    return pts, np.array([[0, 2, 1], [0, 3, 2]])


def cube_mesh(lo=-0.5, hi=0.5):
    """Closed outward-wound cube, 12 triangles."""
    v = np.array([[x, y, z] for x in (lo, hi) for y in (lo, hi) for z in (lo, hi)], dtype=float)
    f = [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
         [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]
    return v, np.array(f)


# ---------------------------------------------------------------- restitution and friction


@pytest.mark.parametrize("mode,e", [("reflect", 0.5), ("project", 0.8), ("penalty", 0.6)])
def test_drop_bounces_to_e_squared_height(mode, e):
    """A particle dropped from H bounces up to e^2 H (v_n' = -e v_n; energy ratio e^2). The
    penalty contact reaches e only as omega dt -> 0 (here omega dt = 0.06)."""
    H, dt = 1.0, 2.0e-4
    plane = ws.Plane(restitution=e, mode=mode, stiffness=1.0e5)
    steps = int((math.sqrt(2 * H / G) * (1 + 2 * e) + 0.05) / dt)
    xs, vs = trajectory(one_particle((0.0, H, 0.0)), [plane], steps, dt)
    apex = bounce_apex(xs, vs)
    tol = 0.03 if mode == "penalty" else 0.01
    assert apex == pytest.approx(e * e * H, rel=tol)
    # reflect/project never leave it below the floor; the penalty spring lets it sink at most v/omega
    depth = math.sqrt(2 * G * H) / math.sqrt(1.0e5) if mode == "penalty" else 1e-6
    assert xs[:, 0, 1].min() > -depth


def test_reflect_mirrors_penetration_scaled_by_restitution():
    """One step through the plane: h' = e h above it and v' = -e v (the lecture's rule)."""
    e, dt, v0 = 0.5, 0.01, -3.0
    xs, vs = trajectory(one_particle((0.0, 0.01, 0.0), vel=(0.0, v0, 0.0)), [ws.Plane(restitution=e)], 1, dt, [])
    h = -(0.01 + v0 * dt)
    assert xs[0, 0, 1] == pytest.approx(e * h, rel=1e-5)
    assert vs[0, 0, 1] == pytest.approx(-e * v0, rel=1e-6)


def test_coulomb_friction_stops_when_mu_g_t_equals_v0():
    """Sliding on a floor: v(t) = v0 - mu g t until it stops at t* = v0 / (mu g), never reversing;
    the distance is v0^2 / (2 mu g)."""
    mu, v0, dt = 0.4, 2.0, 1.0e-3
    t_stop = v0 / (mu * G)
    steps = int(1.5 * t_stop / dt)
    xs, vs = trajectory(one_particle((0.0, 0.0, 0.0), vel=(v0, 0.0, 0.0)),
                        [ws.Plane(restitution=0.0, friction=mu, mode="project")], steps, dt)
    vx = vs[:, 0, 0]
    t = dt * np.arange(1, steps + 1)
    moving = t < t_stop - dt
    np.testing.assert_allclose(vx[moving], v0 - mu * G * t[moving], atol=1e-4)
    stopped = np.flatnonzero(vx == 0.0)
    assert abs(t[stopped[0]] - t_stop) <= dt
    assert np.all(vx[stopped[0]:] == 0.0) and np.all(vx >= 0.0)
    assert xs[-1, 0, 0] == pytest.approx(v0 * v0 / (2 * mu * G), rel=2e-3)
    assert np.all(np.abs(xs[:, 0, 1]) < 1e-6)


def test_penalty_contact_rests_at_depth_mg_over_k():
    """A penalty contact at rest balances gravity: depth = m g / k."""
    m, k, r = 2.0, 5.0e3, 0.05
    plane = ws.Plane(restitution=0.2, mode="penalty", stiffness=k)
    xs, _ = trajectory(one_particle((0.0, r, 0.0), mass=m, radius=r), [plane], 3000, 1.0e-3)
    assert r - xs[-1, 0, 1] == pytest.approx(m * G / k, rel=1e-3)


def test_damping_ratio_gives_restitution():
    """zeta(e) inverts e = exp(-zeta pi / sqrt(1 - zeta^2))."""
    for e in (0.1, 0.5, 0.9):
        z = damping_ratio_for_restitution(e)
        assert math.exp(-z * math.pi / math.sqrt(1 - z * z)) == pytest.approx(e, rel=1e-12)
    assert damping_ratio_for_restitution(0.0) == 1.0 and damping_ratio_for_restitution(1.0) == 0.0


def test_thickness_offsets_the_resting_height():
    r, t = 0.02, 0.03
    plane = ws.Plane(restitution=0.0, mode="project", thickness=t)
    xs, _ = trajectory(one_particle((0.0, 0.5, 0.0), radius=r), [plane], 400, 1.0 / 120)
    assert xs[-1, 0, 1] == pytest.approx(r + t, abs=1e-6)


def test_box_keeps_particles_inside():
    rng = np.random.default_rng(1)
    b = ws.ModelBuilder()
    b.add_particles(rng.uniform(-0.4, 0.4, (200, 3)) + [0, 0.5, 0], rng.normal(0, 5, (200, 3)), radii=0.02)
    box = ws.Box((-0.5, 0.0, -0.5), (0.5, 1.0, 0.5), restitution=0.9)
    xs, _ = trajectory(b.finalize(DEVICE), [box], 200, 1.0 / 240)
    assert np.all(xs >= np.array([-0.5, 0.0, -0.5]) + 0.02 - 1e-5)
    assert np.all(xs <= np.array([0.5, 1.0, 0.5]) - 0.02 + 1e-5)


# ---------------------------------------------------------------- continuous collision detection


@pytest.mark.parametrize("make", ["quad", "mesh"])
def test_ccd_stops_100_m_per_s_particle_at_thin_quad(make, device):
    """At 100 m/s and dt = 1/60 the particle moves 1.67 m per step through a 0-thickness quad;
    continuous detection stops it on the side it came from (e = 0: it rests on the quad)."""
    r = 0.01
    if make == "quad":
        wall = Quad(center=(0, 0, 0), axis_u=(0.5, 0, 0), axis_v=(0, 0, 0.5), restitution=0.0)
    else:
        pts, faces = floor_mesh(0.5)
        wall = TriangleMesh(pts, faces, restitution=0.0)
    for y0, v in ((0.5, -100.0), (-0.5, 100.0)):
        xs, vs = trajectory(one_particle((0.1, y0, -0.2), vel=(0.0, v, 0.0), radius=r, device=device), [wall], 3,
                            1.0 / 60, [])
        side = np.sign(y0)
        np.testing.assert_allclose(xs[:, 0, 1], side * r, atol=1e-6)
        np.testing.assert_allclose(vs[:, 0], 0.0, atol=1e-6)
    # beside the quad it flies past
    xs, _ = trajectory(one_particle((0.7, 0.5, 0.0), vel=(0.0, -100.0, 0.0), radius=r, device=device), [wall], 1,
                       1.0 / 60, [])
    assert xs[0, 0, 1] == pytest.approx(0.5 - 100.0 / 60, rel=1e-6)


def test_ccd_elastic_quad_mirrors_the_path():
    """e = 1 at 100 m/s: the particle ends where the mirrored straight path would."""
    r, dt = 0.01, 1.0 / 60
    quad = Quad(center=(0, 0, 0), axis_u=(0.5, 0, 0), axis_v=(0, 0, 0.5), restitution=1.0)
    xs, vs = trajectory(one_particle((0.0, 0.5, 0.0), vel=(0.0, -100.0, 0.0), radius=r), [quad], 1, dt, [])
    y_free = 0.5 - 100.0 * dt
    assert xs[0, 0, 1] == pytest.approx(r + (r - y_free), rel=1e-5)
    assert vs[0, 0, 1] == pytest.approx(100.0, rel=1e-6)


def test_ccd_sphere_and_capsule_do_not_tunnel():
    dt, r = 1.0 / 60, 0.01
    for shape in (Sphere((0, 0, 0), 0.1, restitution=0.0), Capsule((-0.3, 0, 0), (0.3, 0, 0), 0.05, restitution=0.0)):
        xs, vs = trajectory(one_particle((0.2 * (type(shape) is Capsule), 0.5, 0.0), vel=(0, -100.0, 0), radius=r),
                            [shape], 2, dt, [])
        top = shape.radius + r
        assert xs[-1, 0, 1] == pytest.approx(top, abs=1e-5)
        np.testing.assert_allclose(vs[-1, 0], 0.0, atol=1e-4)


def test_sphere_head_on_restitution_and_container():
    e = 0.7
    xs, vs = trajectory(one_particle((0.0, 0.3, 0.0), vel=(0, -2.0, 0)), [Sphere((0, 0, 0), 0.25, restitution=e)],
                        3, 0.01, [])
    assert vs[-1, 0, 1] == pytest.approx(2.0 * e, rel=1e-6)
    # spherical container: particles thrown outwards stay inside
    rng = np.random.default_rng(3)
    b = ws.ModelBuilder()
    b.add_particles(rng.uniform(-0.3, 0.3, (100, 3)), rng.normal(0, 20, (100, 3)), radii=0.01)
    bowl = Sphere((0, 0, 0), 0.5, inside=True, restitution=0.5)
    xs, _ = trajectory(b.finalize(DEVICE), [bowl], 50, 1.0 / 60)
    assert np.linalg.norm(xs, axis=2).max() <= 0.49 + 1e-5


def test_capsule_side_normal_from_axis():
    """A particle hitting the cylinder part horizontally is sent back along the radial normal."""
    cap = Capsule((0, -0.5, 0), (0, 0.5, 0), 0.1, restitution=1.0)
    xs, vs = trajectory(one_particle((0.3, 0.2, 0.0), vel=(-3.0, 0, 0)), [cap], 10, 0.01, [])
    np.testing.assert_allclose(vs[-1, 0], [3.0, 0.0, 0.0], atol=1e-5)
    assert xs[:, 0, 0].min() >= 0.1 - 1e-6


# ---------------------------------------------------------------- triangle meshes


def test_mesh_floor_matches_analytic_plane(device):
    """Drop and slide with restitution and friction: the wp.Mesh floor and ws.Plane agree."""
    model = one_particle((0.0, 0.8, 0.0), vel=(1.5, 0.0, 0.7), radius=0.02, device=device)
    kw = {"restitution": 0.6, "friction": 0.3}
    pts, faces = floor_mesh(5.0)
    xa, va = trajectory(model, [ws.Plane(**kw)], 300, 1.0 / 120)
    xb, vb = trajectory(model, [TriangleMesh(pts, faces, **kw)], 300, 1.0 / 120)
    assert xa[:, 0, 1].min() < 0.05  # it did hit the floor
    np.testing.assert_allclose(xb, xa, atol=2e-5)
    np.testing.assert_allclose(vb, va, atol=2e-4)


def test_solid_mesh_pushes_inside_particle_out_through_closest_face():
    v, f = cube_mesh()
    cube = TriangleMesh(v, f, solid=True, mode="project", restitution=0.0)
    xs, _ = trajectory(one_particle((0.1, 0.4, -0.05), radius=0.01), [cube], 1, 1e-4, [])
    np.testing.assert_allclose(xs[0, 0], [0.1, 0.51, -0.05], atol=1e-5)


@pytest.mark.parametrize("e", [0.0, 1.0])
def test_kinematic_mesh_strikes_particle_with_its_velocity(e):
    """A plate moving up at U hits a particle at rest: afterwards v = (1 + e) U (infinite mass)."""
    U, dt = 2.0, 1.0 / 100
    pts, faces = floor_mesh(1.0)
    plate = TriangleMesh(pts, faces, restitution=e, motion=lambda t: ((0.0, U * t, 0.0), None))
    xs, vs = trajectory(one_particle((0.0, 0.1, 0.0), radius=0.01), [plate], 10, dt, [])
    hit = np.flatnonzero(np.abs(vs[:, 0, 1]) > 0)[0]
    np.testing.assert_allclose(vs[hit:, 0, 1], (1.0 + e) * U, rtol=1e-4)
    plate_y = U * dt * np.arange(1, 11)
    assert np.all(xs[:, 0, 1] >= plate_y + 0.01 - 1e-5)


def test_set_transform_moves_mesh_between_frames():
    """set_transform lifts a floor under a resting particle: it is carried up with the plate."""
    pts, faces = floor_mesh(1.0)
    plate = TriangleMesh(pts, faces, restitution=0.0, mode="project")
    sim = ws.Simulator(one_particle((0.0, 0.01, 0.0), radius=0.01), forces=[ws.Gravity()], colliders=[plate])
    for frame in range(1, 6):
        plate.set_transform((0.0, 0.05 * frame, 0.0))
        sim.step(0.01)
    y = sim.state.positions.numpy()[0, 1]
    assert y == pytest.approx(0.25 + 0.01, abs=1e-5)
    assert sim.state.velocities.numpy()[0, 1] == pytest.approx(5.0, rel=1e-4)


# ---------------------------------------------------------------- particle-particle collisions


@pytest.mark.parametrize("c_r", [0.0, 0.5, 1.0])
def test_two_body_head_on_matches_1d_rule(c_r, device):
    """m_a u_a + m_b u_b conserved and c_R = -(v_b - v_a)/(u_b - u_a)."""
    ma, mb, ua, ub = 1.0, 3.0, 2.0, -1.0
    b = ws.ModelBuilder()
    b.add_particle((0.0, 0.0, 0.0), vel=(ua, 0, 0), mass=ma, radius=0.05)
    b.add_particle((0.099, 0.0, 0.0), vel=(ub, 0, 0), mass=mb, radius=0.05)
    _, vs = trajectory(b.finalize(device), [ParticleCollisions(restitution=c_r)], 1, 1e-5, [])
    va = (ma * ua + mb * ub + mb * c_r * (ub - ua)) / (ma + mb)
    vb = (ma * ua + mb * ub + ma * c_r * (ua - ub)) / (ma + mb)
    np.testing.assert_allclose(vs[0, :, 0], [va, vb], atol=1e-6)
    np.testing.assert_allclose(vs[0, :, 1:], 0.0, atol=1e-7)


def test_oblique_contact_keeps_tangential_velocity_without_friction():
    b = ws.ModelBuilder()
    b.add_particle((0.0, 0.0, 0.0), vel=(1.0, 0.5, 0), mass=1.0, radius=0.05)
    b.add_particle((0.099, 0.0, 0.0), vel=(0.0, 0.0, 0), mass=1.0, radius=0.05)
    _, vs = trajectory(b.finalize(DEVICE), [ParticleCollisions(restitution=1.0)], 1, 1e-7, [])
    np.testing.assert_allclose(vs[0], [[0.0, 0.5, 0.0], [1.0, 0.0, 0.0]], atol=1e-5)


class _Recorder(ParticleCollisions):
    """Records momentum and kinetic energy just before and after the particle collisions."""

    def apply(self, model, state, q_prev, dt):
        m = model.particle_mass.numpy().astype(np.float64)[:, None]
        v0 = state.velocities.numpy().astype(np.float64)
        super().apply(model, state, q_prev, dt)
        v1 = state.velocities.numpy().astype(np.float64)
        self.log.append(((m * v0).sum(0), (m * v1).sum(0), 0.5 * (m * v0**2).sum(), 0.5 * (m * v1**2).sum(),
                         np.abs(m * v0).sum()))


def test_10000_particles_conserve_momentum_and_never_gain_energy(device):
    rng = np.random.default_rng(0)
    n, r = 10_000, 0.01
    g = np.stack(np.meshgrid(*[np.arange(22)] * 3, indexing="ij"), -1).reshape(-1, 3)[:n]
    pos = g * 0.021 + rng.uniform(-0.002, 0.002, (n, 3)) + 0.02
    b = ws.ModelBuilder()
    b.add_particles(pos, rng.normal(0.0, 1.0, (n, 3)), masses=rng.uniform(0.5, 2.0, n), radii=r)
    pc = _Recorder(restitution=0.5, friction=0.2)
    pc.log = []
    box = ws.Box((0.0, 0.0, 0.0), (0.5, 0.5, 0.5), restitution=1.0)
    trajectory(b.finalize(device), [box, pc], 15, 2.0e-3, [])
    collided = 0
    for p0, p1, k0, k1, scale in pc.log:
        assert np.abs(p1 - p0).max() <= 1e-6 * scale
        assert k1 <= k0 * (1 + 1e-6)
        collided += k1 < k0 * (1 - 1e-4)
    assert collided == len(pc.log)  # collisions happened every step


# ---------------------------------------------------------------- bad input


def test_bad_input_names_the_item():
    with pytest.raises(ValueError, match="mode 'bounce'"):
        ws.Plane(mode="bounce")
    with pytest.raises(ValueError, match="Sphere mode"):
        Sphere(mode="sticky")
    with pytest.raises(ValueError, match="thickness"):
        Quad(thickness=-0.1)
    with pytest.raises(ValueError, match="stiffness"):
        ws.Plane(mode="penalty", stiffness=-5.0)
    with pytest.raises(ValueError, match="orthogonal"):
        Quad(axis_u=(1, 0, 0), axis_v=(1, 0, 1))
    with pytest.raises(ValueError, match="radius"):
        Capsule(radius=0.0)
    with pytest.raises(ValueError, match="empty"):
        TriangleMesh(np.zeros((0, 3)), np.zeros((0, 3), int))
    with pytest.raises(ValueError, match="face 1"):
        TriangleMesh(np.zeros((3, 3)), [[0, 1, 2], [0, 1, 3]])
    with pytest.raises(ValueError, match="restitution"):
        ParticleCollisions(restitution=1.5)
    with pytest.raises(ValueError, match="particle 0 has radius"):
        ws.Simulator(one_particle((0, 0, 0)), colliders=[ParticleCollisions()])


def test_collisions_example_prints_the_two_body_table(tmp_path):
    """examples/collisions.py: its head-on table matches the analytic columns."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    script = Path(__file__).resolve().parents[1] / "examples" / "collisions.py"
    out = subprocess.run([sys.executable, str(script), "--balls", "64", "--frames", "6", "--out", "c.usda"],
                         cwd=tmp_path, env=dict(os.environ, WARP_QUIET="1"), capture_output=True, text=True,
                         timeout=600, check=False)
    assert out.returncode == 0, out.stderr[-3000:]
    rows = [[float(x) for x in line.split()] for line in out.stdout.splitlines()
            if line.strip()[:4] in ("0.00", "0.50", "1.00")]
    assert len(rows) == 3
    for c_r, va, va_exact, vb, vb_exact in rows:
        assert va == pytest.approx(va_exact, abs=1e-4) and vb == pytest.approx(vb_exact, abs=1e-4)


def test_keyframe_motion_interpolates_and_drives_a_mesh():
    from warpsim.bodies.colliders import keyframe_motion

    half_turn = (0.0, math.sin(math.pi / 4), 0.0, math.cos(math.pi / 4))  # 90 degrees about +y
    motion = keyframe_motion([(0.0, (0, 0, 0), None), (1.0, (2, 0, 0), half_turn)])
    p, q = motion(0.5)
    np.testing.assert_allclose(p, [1, 0, 0])
    np.testing.assert_allclose(q, [0, math.sin(math.pi / 8), 0, math.cos(math.pi / 8)], atol=1e-12)
    np.testing.assert_allclose(motion(5.0)[0], [2, 0, 0])
    with pytest.raises(ValueError, match="strictly increasing"):
        keyframe_motion([(1.0, (0, 0, 0), None), (1.0, (1, 0, 0), None)])
    # a floor lifted by keyframes carries a resting particle: y follows the key path
    pts, faces = floor_mesh(1.0)
    lift = TriangleMesh(pts, faces, restitution=0.0, mode="project",
                        motion=keyframe_motion([(0.0, (0, 0, 0), None), (0.1, (0, 0.2, 0), None)]))
    xs, vs = trajectory(one_particle((0.0, 0.01, 0.0), radius=0.01), [lift], 20, 0.01, [])
    np.testing.assert_allclose(xs[:10, 0, 1], 0.01 + 0.02 * np.arange(1, 11), atol=1e-5)
    np.testing.assert_allclose(vs[:10, 0, 1], 2.0, rtol=1e-4)
    # set_transform takes a 4x4 matrix too
    m = np.eye(4)
    m[:3, 3] = (0.0, 0.3, 0.0)
    lift.set_transform(m)
    np.testing.assert_allclose(lift.world_pose()[0], [0, 0.3, 0])
