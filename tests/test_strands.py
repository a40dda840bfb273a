"""Hair strands and sag-free initialization: NumPy references of the strand forces and of the
sag-free solve, equilibrium held over 2 s (strand and cloth), a released strand falling as a
chain, and bad input."""

import numpy as np
import pytest
import warp as wp

import warpsim as ws

DEVICE = "cpu"
G = 9.81


# ---------------------------------------------------------------------------------- references
def _normalize(u):
    n = np.linalg.norm(u)
    return u / n if n > 1e-12 else np.array([1.0, 0.0, 0.0])


def _transport(n, t):
    m = n - np.dot(n, t) * t
    return m / np.linalg.norm(m)


def strand_frames_np(x, root_normal):
    """Frames (stride, 3, 3) of one strand's bending vertices 1 .. stride - 2 (columns t, n, t x n):
    t the incoming edge, n carried from the root normal by projection transport."""
    frames = np.zeros((len(x), 3, 3))
    t = _normalize(x[1] - x[0])
    n = _transport(root_normal, t)
    for v in range(1, len(x) - 1):
        if v >= 2:
            t = _normalize(x[v] - x[v - 1])
            n = _transport(n, t)
        frames[v] = np.column_stack([t, n, np.cross(t, n)])
    return frames


def strand_energy_np(x, rest, bend_rest, ks, kb, root_normal):
    """Spring energy [J] of one strand: stretch plus kb / 2 |b - F c|^2 per bending vertex."""
    frames = strand_frames_np(x, root_normal)
    e = 0.0
    for v in range(1, len(x) - 1):
        b = x[v - 1] - 2 * x[v] + x[v + 1] - frames[v] @ bend_rest[v]
        e += 0.5 * kb * b @ b + 0.5 * ks * (np.linalg.norm(x[v + 1] - x[v]) - rest[v]) ** 2
    return e


def strand_forces_np(x, vel, rest, bend_rest, ks, kb, ds, db, root_normal, eps=1e-7):
    """Float64 reference of warpsim.kernels.strands.eval_strand_forces on one strand: minus the
    gradient of strand_energy_np (central differences; analytic when bend_rest = 0) plus the
    stretch and bending dampers."""
    f = np.zeros_like(x)
    if np.any(bend_rest):
        for i in range(len(x)):
            for c in range(3):
                xp, xm = x.copy(), x.copy()
                xp[i, c] += eps
                xm[i, c] -= eps
                f[i, c] = -(strand_energy_np(xp, rest, bend_rest, ks, kb, root_normal)
                            - strand_energy_np(xm, rest, bend_rest, ks, kb, root_normal)) / (2 * eps)
    for v in range(1, len(x) - 1):
        e = db * (vel[v - 1] - 2 * vel[v] + vel[v + 1])
        if not np.any(bend_rest):
            e = e + kb * (x[v - 1] - 2 * x[v] + x[v + 1])
        f[v - 1] -= e
        f[v] += 2 * e
        f[v + 1] -= e
        u = x[v + 1] - x[v]
        d = u / np.linalg.norm(u)
        ft = ds * np.dot(vel[v + 1] - vel[v], d)
        if not np.any(bend_rest):
            ft += ks * (np.linalg.norm(u) - rest[v])
        f[v] += ft * d
        f[v + 1] -= ft * d
    return f


# ---------------------------------------------------------------------------------- helpers
def horizontal_strand(segments=8, **kw):
    b = ws.ModelBuilder()
    hair = ws.add_strands(b, [(0.0, 1.0, 0.0)], [(1.0, 0.0, 0.0)], segments, length=0.2, mass=1e-3, **kw)
    model = b.finalize(DEVICE)
    sim = ws.Simulator(model, forces=[ws.Gravity(), ws.StrandForce(hair)], colliders=[ws.StrandRoots(hair)])
    return hair, sim


def max_displacement(sim, seconds=2.0, dt=2.5e-4, every=20):
    x0 = sim.state.positions.numpy().copy()
    worst = 0.0
    for k in range(round(seconds / dt)):
        sim.step(dt)
        if k % every == every - 1:
            worst = max(worst, float(np.linalg.norm(sim.state.positions.numpy() - x0, axis=1).max()))
    return worst


# ---------------------------------------------------------------------------------- forces
def test_strand_forces_match_numpy_reference():
    rng = np.random.default_rng(3)
    b = ws.ModelBuilder()
    hair = ws.add_strands(b, [(0.0, 1.0, 0.0), (0.1, 1.0, 0.0)], [(1.0, 0.2, 0.0), (0.0, -1.0, 0.3)], 5,
                          length=0.2, stretch_damping=0.05, bend_damping=0.01)
    model = b.finalize(DEVICE)
    force = ws.StrandForce(hair)
    force.bind(model)
    data = hair.bind(model)
    data["bend_rest"].assign(rng.normal(0.0, 0.01, (hair.strand_count * hair.stride, 3)).astype(np.float32))
    x = model.particle_q.numpy() + rng.normal(0.0, 0.004, (model.particle_count, 3)).astype(np.float32)
    v = rng.normal(0.0, 0.3, (model.particle_count, 3)).astype(np.float32)
    f = wp.zeros(model.particle_count, dtype=wp.vec3, device=DEVICE)
    force.eval(wp.array(x, dtype=wp.vec3, device=DEVICE), wp.array(v, dtype=wp.vec3, device=DEVICE), None, 0.0, f)
    got = f.numpy()
    rest = data["rest_length"].numpy().reshape(hair.strand_count, hair.stride)
    bend = data["bend_rest"].numpy().reshape(hair.strand_count, hair.stride, 3)
    normal = data["root_normal"].numpy()
    for s, idx in enumerate(hair.particles()):
        want = strand_forces_np(x[idx].astype(np.float64), v[idx].astype(np.float64), rest[s], bend[s],
                                hair.stretch_stiffness[s], hair.bend_stiffness[s], hair.stretch_damping[s],
                                hair.bend_damping[s], normal[s].astype(np.float64))
        # the free vertices (ghost and root are pinned: the kernel leaves out the frame gradient there)
        np.testing.assert_allclose(got[idx[2:]], want[2:], rtol=2e-3, atol=2e-4 * np.abs(want).max())


def test_sag_free_matches_numpy_least_squares_and_holds_a_horizontal_strand():
    hair, sim = horizontal_strand(segments=6)
    report = ws.sag_free(sim)
    assert report.iterations == 0  # strands alone: the direct per-strand solve, no CGLS
    # NumPy reference: the minimum complementary-energy rest state that balances gravity
    x = sim.state.positions.numpy().astype(np.float64)
    idx = hair.particles()[0]
    xs = x[idx]
    stride = hair.stride
    ks, kb = hair.stretch_stiffness[0], hair.bend_stiffness[0]
    free = list(range(2, stride))
    cols = []
    for v in range(1, stride - 1):  # stretch tension t pulls v toward v + 1
        col = np.zeros((stride, 3))
        d = _normalize(xs[v + 1] - xs[v])
        col[v] += d
        col[v + 1] -= d
        cols.append(col[free].reshape(-1) * np.sqrt(ks))
    for v in range(1, stride - 1):  # bending: +g, -2 g, +g
        for c in range(3):
            col = np.zeros((stride, 3))
            col[v - 1, c] += 1
            col[v, c] -= 2
            col[v + 1, c] += 1
            cols.append(col[free].reshape(-1) * np.sqrt(kb))
    A = np.stack(cols, axis=1)
    mass = hair.mass[0] / hair.segments
    rhs = np.tile([0.0, mass * G, 0.0], len(free))
    u = np.linalg.lstsq(A, rhs, rcond=None)[0]
    n = stride - 2
    seg = np.linalg.norm(np.diff(xs[1:], axis=0), axis=1)
    rest_ref = seg - u[:n] / np.sqrt(ks)
    bend_ref = (xs[:-2] - 2 * xs[1:-1] + xs[2:]) + u[n:].reshape(n, 3) / np.sqrt(kb)
    data = hair.bind(sim.model)
    rest = data["rest_length"].numpy()[1:-1]
    np.testing.assert_allclose(rest, rest_ref, rtol=1e-6, atol=1e-9)
    world = wp.zeros_like(data["bend_rest"])
    from warpsim.kernels import strands as KS
    wp.launch(KS.bend_world_from_rest, 1, inputs=[sim.state.positions, hair.first, hair.stride, data["root_normal"],
                                                   data["bend_rest"], world], device=DEVICE)
    # the global step is this least-squares solution; later rounds add the frames' gradient (small)
    np.testing.assert_allclose(world.numpy()[1:-1], bend_ref, atol=0.02 * np.abs(bend_ref).max())
    # equilibrium by the NumPy force model (minus the energy gradient, frames included, and gravity)
    normal = data["root_normal"].numpy()[0].astype(np.float64)
    f = strand_forces_np(xs, np.zeros_like(xs), data["rest_length"].numpy().astype(np.float64),
                         data["bend_rest"].numpy().astype(np.float64), ks, kb, 0.0, 0.0, normal)
    f[:, 1] -= mass * G
    assert np.abs(f[2:]).max() < 1e-2 * mass * G
    # residual in the simulator's kernels below 1 % of the load; rest lengths positive and bounded
    assert report.residual_relative < 1e-2
    assert rest.min() > 0.0 and 1 - report.max_strain <= report.rest_ratio_min <= report.rest_ratio_max <= 1.2
    # equilibrium held for 2 s; the same strand without sag-free sags by centimetres
    held = max_displacement(sim)
    _, plain = horizontal_strand(segments=6)
    sag = max_displacement(plain)
    assert sag > 0.01, sag
    assert held < 1e-3 and held < 0.01 * sag, (held, sag)


def test_sag_free_pinned_cloth_holds_its_shape():
    def curtain():
        b = ws.ModelBuilder()
        ws.add_cloth_grid(b, (6, 6), (0.5, 0.5), (0.0, 1.0, 0.0), v_axis=(0, -1, 0), density=0.2,
                          pin=["corner_00", "corner_10"], structural=(50.0, 0.05), shear=(20.0, 0.05),
                          bend=(5.0, 0.01))
        return ws.Simulator(b.finalize(DEVICE), forces=[ws.Gravity()])

    sim = curtain()
    geometric = sim.model.spring_rest_length.numpy().copy()
    report = ws.sag_free(sim)
    rest = sim.model.spring_rest_length.numpy()
    assert rest.min() > 0.0
    assert np.all(np.abs(rest / geometric - 1.0) <= report.max_strain + 1e-6)
    assert report.residual_relative < 1e-2
    held = max_displacement(sim, dt=1e-3, every=10)
    sag = max_displacement(curtain(), dt=1e-3, every=10)
    assert sag > 0.01, sag
    assert held < 1e-3 and held < 0.01 * sag, (held, sag)


def test_sag_free_soft_block_resting_on_a_floor():
    """A spring lattice on a plane: the floor's support forces (unknowns >= 0) carry the weight."""
    import itertools

    def block():
        b = ws.ModelBuilder()
        h, idx = 0.05, {}
        for i, j, k in itertools.product(range(4), range(3), range(4)):
            idx[i, j, k] = b.add_particle((i * h, 0.01 + j * h, k * h), mass=0.01, radius=0.01)
        for (a, pa), (c, pc) in itertools.combinations(idx.items(), 2):
            if np.linalg.norm(np.subtract(a, c)) < 1.8:  # edges and face and body diagonals
                b.add_spring(pa, pc, 20.0, 0.02)
        return ws.Simulator(b.finalize(DEVICE), forces=[ws.Gravity()],
                            colliders=[ws.Plane(restitution=0.0, friction=0.5, mode="project")])

    sim = block()
    report = ws.sag_free(sim)
    assert len(report.support_particles) == 16  # the bottom layer
    assert min(report.support_forces) >= 0.0
    assert sum(report.support_forces) == pytest.approx(48 * 0.01 * G, rel=1e-3)  # the floor takes the weight
    assert report.residual_relative < 1e-2
    held = max_displacement(sim, dt=1e-3, every=20)
    sag = max_displacement(block(), dt=1e-3, every=20)
    assert sag > 0.01, sag
    assert held < 1e-3 and held < 0.01 * sag, (held, sag)


def test_released_strand_falls_as_a_chain():
    """Roots let go: the chain falls freely. Its centre of mass follows y0 - g t^2 / 2 (internal
    forces cancel) and its energy and shape follow a NumPy semi-implicit Euler of the same springs."""
    b = ws.ModelBuilder()
    hair = ws.add_strands(b, [(0.0, 1.0, 0.0)], [(1.0, 0.5, 0.0)], 6, length=0.2, mass=1e-3, stretch_damping=0.0,
                          bend_damping=0.0)
    idx = hair.particles()[0]
    vertex_mass = hair.mass[0] / hair.segments
    for i in idx[:2]:  # release ghost and root
        b.particle_mass[i] = vertex_mass
    model = b.finalize(DEVICE)
    sim = ws.Simulator(model, forces=[ws.Gravity(), ws.StrandForce(hair)])
    data = hair.bind(model)
    x = model.particle_q.numpy().astype(np.float64)[idx]
    v = np.zeros_like(x)
    rest = data["rest_length"].numpy().astype(np.float64)
    bend = np.zeros((hair.stride, 3))
    normal = data["root_normal"].numpy()[0].astype(np.float64)
    ks, kb = hair.stretch_stiffness[0], hair.bend_stiffness[0]
    dt, steps = 1.0e-4, 2000  # h omega_max ~ 0.2: the symplectic energy error stays ~1 %
    g = np.array([0.0, -G, 0.0])

    def internal_energy(x, v):
        """Kinetic energy about the centre of mass plus spring energy [J] (conserved: bend_rest = 0)."""
        vc = v - v.mean(axis=0)
        return 0.5 * vertex_mass * (vc * vc).sum() + strand_energy_np(x, rest, bend, ks, kb, normal)

    x[-1] += np.array([0.01, 0.0, 0.0])  # stretch the tip segment so the springs work while it falls
    q = model.particle_q.numpy()
    q[idx] = x.astype(np.float32)
    sim.state.positions.assign(q)
    e0 = internal_energy(x, v)
    cm0 = x.mean(axis=0)
    for k in range(steps):
        f = strand_forces_np(x, v, rest, bend, ks, kb, 0.0, 0.0, normal) + vertex_mass * g
        v = v + dt * f / vertex_mass
        x = x + dt * v
        sim.step(dt)
        if k % 100 == 99:
            got = sim.state.positions.numpy()[idx].astype(np.float64)
            vel = sim.state.velocities.numpy()[idx].astype(np.float64)
            np.testing.assert_allclose(got, x, atol=2e-4)
            # semi-implicit Euler free fall of the centre of mass: y = y0 - g dt^2 n (n + 1) / 2
            np.testing.assert_allclose(got.mean(axis=0)[1], cm0[1] - G * dt * dt * (k + 1) * (k + 2) / 2, atol=1e-5)
            e_ref, e_got = internal_energy(x, v), internal_energy(got, vel)
            assert abs(e_got - e_ref) < 0.02 * e0, (k, e_got, e_ref)
            assert abs(e_got - e0) < 0.05 * e0, (k, e_got, e0)


# ---------------------------------------------------------------------------------- bad input
def test_bad_strand_input_names_the_strand():
    b = ws.ModelBuilder()
    with pytest.raises(ValueError, match="segments"):
        ws.add_strands(b, [(0, 1, 0)], [(1, 0, 0)], 0)
    with pytest.raises(ValueError, match="strand 1 is not finite"):
        ws.add_strands(b, [(0, 1, 0), (0, 1, 0)], [(1, 0, 0), (np.nan, 0, 1)], 4)
    head = ws.Sphere((0.0, 1.0, 0.0), 0.1)
    with pytest.raises(ValueError, match="strand 1 root .* outside the head"):
        ws.add_strands(b, [(0.0, 1.1, 0.0), (0.0, 1.3, 0.0)], [(0, 1, 0), (0, 1, 0)], 4, head=head)
    with pytest.raises(ValueError, match="strand 0 vertex .* inside the head"):
        ws.add_strands(b, [(0.0, 1.1, 0.0)], [(0, -1, 0)], 4, head=head)
    assert b.particle_count == 0  # nothing was added by a failed call
    _, sim = horizontal_strand(segments=4)
    with pytest.raises(ValueError, match=r"max_strain=0.0001 cannot be met: strand 0"):
        ws.sag_free(sim, max_strain=1e-4)


# ---------------------------------------------------------------------------------- the hair scene
def _hair_scene(**params):
    from warpsim.scenes import get_scene

    base = {"strands": 24, "segments": 8}
    base.update(params)
    return get_scene("hair")(base, device=DEVICE)


def _tip_drift(scene, seconds=2.0):
    tips = scene.hair.tip_particles()
    x0 = scene.sim.state.positions.numpy()[tips].copy()
    worst = 0.0
    for _ in range(round(60 * seconds)):
        scene.advance(1.0 / 60.0, 1)
        worst = max(worst, float(np.linalg.norm(scene.sim.state.positions.numpy()[tips] - x0, axis=1).max()))
    return worst


@pytest.mark.parametrize("style", ["straight", "wavy", "curly"])
def test_groomed_hair_keeps_its_shape_with_sag_free(style):
    held = _tip_drift(_hair_scene(motion="still", style=style))
    assert held < 2e-3, held
    if style == "straight":
        sagged = _tip_drift(_hair_scene(motion="still", sag_free=False))
        assert sagged > 1e-2, sagged


def test_moving_head_keeps_strands_out_of_it_and_the_curves_taper(tmp_path):
    from warpsim.strands import head_signed_distance
    from warpsim.usd.writer import UsdCacheWriter

    scene = _hair_scene(motion="turn_nod", still=0.2, strands=16)
    hair = scene.hair
    free = hair.free_particles()
    path = tmp_path / "hair.usda"
    writer = UsdCacheWriter(str(path))
    scene.declare(writer)
    writer.write_frame(0, scene.frame_data())
    moved = 0.0
    p0 = scene.head.world_pose()[1]
    for frame in range(1, 91):
        scene.advance(1.0 / 60.0, 1)
        depth = head_signed_distance(scene.head, scene.sim.state.positions.numpy()[free])
        assert depth.min() >= -hair.radius.max(), (frame, depth.min())
        moved = max(moved, float(np.abs(scene.head.world_pose()[1] - p0).max()))
        if frame % 30 == 0:
            writer.write_frame(frame, scene.frame_data())
    writer.close()
    assert moved > 0.1  # the head did turn
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(path))
    curves = UsdGeom.BasisCurves(stage.GetPrimAtPath("/World/hair"))
    widths = np.array(curves.GetWidthsAttr().Get())
    assert curves.GetWidthsInterpolation() == UsdGeom.Tokens.vertex
    per_curve = widths.reshape(hair.strand_count, hair.segments + 1)
    assert np.all(np.diff(per_curve, axis=1) < 0) and per_curve[0, 0] == pytest.approx(2 * hair.radius[0])


def test_viewer_drags_a_strand():
    from warpsim.scenes import get_scene
    from warpsim.viewer.session import Session

    params = {"strands": 8, "segments": 6, "motion": "still"}
    s = Session(get_scene("hair"), params, device=DEVICE)
    item = s.items["hair_vertices"]
    particles, _ = s._grabbable("hair_vertices")
    tip = int(np.flatnonzero(np.isin(particles, s.scene.hair.tip_particles()))[0])
    eye = item.points[tip] + np.array([0.0, 0.0, 2.0])
    picked = s.pick("hair_vertices", eye, (0.0, 0.0, -1.0))
    assert picked == tip
    particle = s.grab("hair_vertices", picked, client=1)
    assert particle == s.scene.hair.tip_particles()[0]
    x0 = s.grabbed_position()
    target = s.drag_ray(eye, (x0 + [0.1, 0.0, 0.0]) - eye, (0.0, 0.0, -1.0))
    free = Session(get_scene("hair"), params, device=DEVICE)
    for _ in range(30):
        assert s.advance(), s.error
        free.advance()
    x1 = s.grabbed_position()
    x_free = free.scene.sim.state.positions.numpy()[particle]
    assert (x1 - x_free) @ (target - x0) / np.linalg.norm(target - x0) > 0.02  # pulled toward the pointer
    assert s.release(client=1)
