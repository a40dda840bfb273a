"""Contact at the implicit step's size: a backward Euler step's path is a straight line, so a
reflecting plane must not read a parabola from the start force (a compressed spring landing on a
plane gained energy); speculative soft contacts (``SoftContact(reach=...)``) let an approaching
pair close exactly its gap beyond the thickness in one step and no more."""
import numpy as np
import pytest

import warpsim as ws

DEVICE = "cpu"


def spring_energy(x, v, m, k, rest, g):
    """Kinetic + spring + gravitational energy [J] of the two-particle system (particle 1 pinned)."""
    stretch = np.linalg.norm(x[0] - x[1]) - rest
    return 0.5 * m * float(v[0] @ v[0]) + 0.5 * k * stretch ** 2 + m * g * float(x[0, 1])


@pytest.mark.parametrize("dt", [1.0 / 240.0, 1.0 / 60.0])
def test_compressed_spring_landing_on_an_inelastic_plane_gains_no_energy_with_implicit_euler(dt):
    # particle 0, 2 mm above the floor and falling, is pushed down by a compressed stiff spring
    # from a pinned particle above it: the start force's acceleration is -2,000 m/s^2
    m, k, g = 0.001, 200.0, 9.81
    b = ws.ModelBuilder()
    b.add_particle((0.0, 0.002, 0.0), vel=(0.0, -0.5, 0.0), mass=m)
    b.add_particle((0.0, 0.012, 0.0), mass=0.0)
    b.add_spring(0, 1, stiffness=k, rest_length=0.02)
    sim = ws.Simulator(b.finalize(DEVICE), integrator=ws.ImplicitEuler(newton_iterations=8),
                       forces=[ws.Gravity((0.0, -g, 0.0))],
                       colliders=[ws.Plane(restitution=0.0, mode="reflect")])
    x0, v0 = sim.state.positions.numpy().astype(np.float64), sim.state.velocities.numpy().astype(np.float64)
    before = spring_energy(x0, v0, m, k, 0.02, g)
    for _ in range(5):
        sim.step(dt)
        x, v = sim.state.positions.numpy().astype(np.float64), sim.state.velocities.numpy().astype(np.float64)
        assert x[0, 1] >= -1e-6  # the plane holds
        # backward Euler only dissipates and an inelastic plane takes energy: it never rises (with
        # the start force's parabola the velocity was handed back staggered by -a_n dt / 2, 4.2 m/s
        # at 1/240 s for the start acceleration of -2,000 m/s^2)
        assert spring_energy(x, v, m, k, 0.02, g) <= before * (1.0 + 1e-4) + 1e-9
    assert np.abs(sim.state.forces.numpy()).max() == 0.0  # the step's path acceleration: none


def vertex_over_triangle(gap, speed, thickness, reach):
    """A free vertex ``gap`` [m] above a pinned triangle, approaching at ``speed`` [m/s], in a
    SoftContact with ``reach``; returns (simulator, contact)."""
    b = ws.ModelBuilder()
    b.add_particle((0.1, gap, 0.1), vel=(0.0, -speed, 0.0), mass=0.01)
    for p in ((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), (1.0, 0.0, 0.0)):
        b.add_particle(p, mass=0.0)
    contact = ws.SoftContact([np.array([[0, 0, 0]]), np.array([[1, 2, 3]])], thickness=thickness, reach=reach,
                             friction=0.0, broad_phase="all_pairs")
    return ws.Simulator(b.finalize(DEVICE), forces=[], colliders=[contact]), contact


@pytest.mark.parametrize("broad_phase", ["all_pairs", "bvh", "list"])
def test_speculative_contact_lets_a_pair_close_its_gap_in_one_step_and_no_more(broad_phase):
    thickness, reach, dt = 0.006, 0.012, 1.0 / 240.0
    # 14 mm apart (8 mm beyond the thickness), closing at 3 m/s: 12.5 mm in a step
    sim, contact = vertex_over_triangle(0.014 + 3.0 * dt, 3.0, thickness, reach)
    contact.set_broad_phase(broad_phase) if broad_phase != "all_pairs" else None
    sim.step(dt)  # the step moves it to 14 mm; the contact then allows 8 mm a step
    x, v = sim.state.positions.numpy(), sim.state.velocities.numpy()
    assert contact.contact_count == 1
    assert x[0, 1] == pytest.approx(0.014, abs=1e-6)
    assert v[0, 1] == pytest.approx(-(0.014 - thickness) / dt, rel=1e-4)  # exactly the gap beyond the thickness
    sim.step(dt)
    x, v = sim.state.positions.numpy(), sim.state.velocities.numpy()
    assert x[0, 1] == pytest.approx(thickness, abs=2e-5)  # at the thickness, not through
    assert abs(v[0, 1]) < 1e-3  # and stopped there (no restitution)
    # a slower pair is left alone
    sim, contact = vertex_over_triangle(0.014 + 1.0 * dt, 1.0, thickness, reach)
    sim.step(dt)
    assert contact.contact_count == 1
    assert sim.state.velocities.numpy()[0, 1] == pytest.approx(-1.0, rel=1e-5)


def test_without_reach_the_same_pair_is_no_contact_until_it_touches():
    sim, contact = vertex_over_triangle(0.014 + 3.0 * 1.0 / 240.0, 3.0, 0.006, 0.0)
    sim.step(1.0 / 240.0)
    assert contact.contact_count == 0
    assert sim.state.velocities.numpy()[0, 1] == pytest.approx(-3.0, rel=1e-6)


def test_reach_must_be_a_distance():
    with pytest.raises(ValueError, match="reach"):
        ws.SoftContact([np.array([[0, 1, 2]]), np.array([[3, 4, 5]])], reach=-0.01)


def test_speculative_contacts_do_not_weaken_a_touching_one():
    # one vertex 3 mm over a pinned triangle (inside the 6 mm thickness) and three more 14 mm over it
    # (within the reach, at rest): the touching contact is resolved as if alone; when the three counted
    # in the triangle's contact counts (the Jacobi scale) it was pushed a quarter of the way
    thickness = 0.006
    b = ws.ModelBuilder()
    for x, z, h in ((0.1, 0.1, 0.003), (0.3, 0.1, 0.014), (0.1, 0.3, 0.014), (0.25, 0.25, 0.014)):
        b.add_particle((x, h, z), mass=0.01)
    for p in ((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), (1.0, 0.0, 0.0)):
        b.add_particle(p, mass=0.0)
    bodies = [np.array([[i, i, i]]) for i in range(4)] + [np.array([[4, 5, 6]])]
    contact = ws.SoftContact(bodies, thickness=thickness, reach=0.012, friction=0.0, iterations=1, push=1.0,
                             broad_phase="all_pairs")
    sim = ws.Simulator(b.finalize(DEVICE), forces=[], colliders=[contact])
    sim.step(1.0 / 240.0)
    y = sim.state.positions.numpy()[:, 1]
    assert contact.contact_count == 4
    assert y[0] == pytest.approx(thickness, abs=1e-6)  # pushed out to the thickness in one pass
    np.testing.assert_allclose(y[1:4], 0.014, atol=1e-7)  # the speculative ones did not move


@pytest.mark.parametrize("broad_phase", ["all_pairs", "bvh", "list"])
def test_edge_reach_sets_the_speculative_edge_pairs_apart_from_the_vertex_ones(broad_phase):
    """Two box rods crossed at right angles, 10 mm apart (beyond the 6 mm thickness, within the 12 mm
    reach), at rest: only their long edges are near each other. With ``edge_reach`` None (the reach)
    their edge pairs are speculative contacts; with ``edge_reach=0`` there are none, and still none
    of the vertex kind in both cases; every broad phase agrees."""
    from test_soft_contact_scale import box_mesh

    counts = {}
    for edge_reach in (None, 0.0):
        b = ws.ModelBuilder()
        rods = []
        for k, size in enumerate(((0.3, 0.02, 0.02), (0.02, 0.02, 0.3))):
            points, faces = box_mesh(size)
            rods.append(ws.add_soft_body(b, points, faces, position=(0.0, k * 0.030, 0.0), total_mass=0.1,
                                         stiffness=2000.0, interior="none"))
        contact = ws.SoftContact(rods, thickness=0.006, reach=0.012, edge_reach=edge_reach, broad_phase=broad_phase)
        sim = ws.Simulator(b.finalize(DEVICE), forces=[], colliders=[contact])
        sim.step(1.0 / 240.0)
        counts[edge_reach] = (contact.contact_count, contact.edge_contact_count)
        assert contact.edge_detect_distance == pytest.approx(0.006 + (0.012 if edge_reach is None else 0.0))
    assert counts[None][0] == 0 and counts[None][1] > 0
    assert counts[0.0] == (0, 0)
    with pytest.raises(ValueError, match="edge_reach"):
        ws.SoftContact([np.array([[0, 1, 2]]), np.array([[3, 4, 5]])], reach=0.01, edge_reach=-0.01)
