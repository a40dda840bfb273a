"""Soft body against soft body (ws.SoftContact): the closest-point kernel against a NumPy
oracle; two tori pressed together never interpenetrate beyond the contact thickness (semi-implicit
and implicit Euler; without the contact the same press goes through); momentum is conserved
across a collision; the ``donuts`` heap comes to rest with no torus inside another; bad input."""
import numpy as np
import pytest
import warp as wp
from warpsim.kernels import soft_contact as K

import warpsim as ws
from warpsim.bodies import meshtools
from warpsim.scenes import get_scene

DEVICE = "cpu"
THICKNESS = 0.006


def distance_to_triangles(p, tri):
    """Distance [m] from each point p (N, 3) to the nearest of the triangles tri (F, 3, 3):
    projection inside the face, else the nearest edge point (NumPy oracle)."""
    best = np.full(len(p), np.inf)
    for A, B, C in tri:
        n = np.cross(B - A, C - A)
        n /= np.linalg.norm(n)
        d = (p - A) @ n
        q = p - d[:, None] * n
        v0, v1, v2 = B - A, C - A, q - A
        d00, d01, d11, d20, d21 = v0 @ v0, v0 @ v1, v1 @ v1, v2 @ v0, v2 @ v1
        den = d00 * d11 - d01 * d01
        v = (d11 * d20 - d01 * d21) / den
        w = (d00 * d21 - d01 * d20) / den
        dist = np.where((v >= 0) & (w >= 0) & (v + w <= 1), np.abs(d), np.inf)
        for P, Q in ((A, B), (B, C), (C, A)):
            e = Q - P
            t = np.clip(((p - P) @ e) / (e @ e), 0.0, 1.0)
            dist = np.minimum(dist, np.linalg.norm(p - (P + t[:, None] * e), axis=1))
        best = np.minimum(best, dist)
    return best


def penetration(x, a, b):
    """Deepest penetration [m] of body a's surface vertices inside closed body b (0 if none)."""
    p = x[a.surface_indices].astype(np.float64)
    # only vertices inside b's bounding box can be inside b (a filter: the result is the same)
    corners = x[b.surface_indices].astype(np.float64)
    p = p[((p >= corners.min(0)) & (p <= corners.max(0))).all(1)]
    if not len(p):
        return 0.0
    inside = meshtools.winding_number(x.astype(np.float64), b.faces, p) > 0.5
    if not inside.any():
        return 0.0
    return float(distance_to_triangles(p[inside], x[b.faces].astype(np.float64)).max())


@wp.kernel
def _closest(p: wp.array(dtype=wp.vec3), tri: wp.array(dtype=wp.vec3), out: wp.array(dtype=float)):
    i = wp.tid()
    a, b, c = tri[3 * i], tri[3 * i + 1], tri[3 * i + 2]
    w = K.triangle_barycentric(p[i], a, b, c)
    out[i] = wp.length(p[i] - (w[0] * a + w[1] * b + w[2] * c))


def test_closest_point_on_triangle_matches_numpy():
    rng = np.random.default_rng(3)
    n = 400
    tri = rng.normal(size=(n, 3, 3))
    p = 2.0 * rng.normal(size=(n, 3))
    out = wp.zeros(n, dtype=float, device=DEVICE)
    wp.launch(_closest, n, inputs=[wp.array(p, dtype=wp.vec3, device=DEVICE),
                                   wp.array(tri.reshape(-1, 3), dtype=wp.vec3, device=DEVICE), out], device=DEVICE)
    expected = np.array([distance_to_triangles(p[k:k + 1], tri[k:k + 1])[0] for k in range(n)])
    np.testing.assert_allclose(out.numpy(), expected, rtol=1e-4, atol=1e-5)


def two_tori(gap=0.01, velocity=((0, 0, 0), (0, 0, 0)), offset=(0.0, 0.0), mass=0.5):
    """Two flat tori (R = 0.1 m, r = 0.04 m, 16 x 8), the second above the first with ``gap``."""
    points, faces = ws.torus_mesh(0.1, 0.04, 16, 8)
    b = ws.ModelBuilder()
    bodies = [ws.add_soft_body(b, points, faces, position=(offset[k], 0.04 + k * (0.08 + gap), 0.0),
                               velocity=velocity[k], total_mass=mass, mass_distribution="uniform",
                               stiffness=200.0, damping=0.1, lattice_cells=7, name=f"torus {k}")
              for k in range(2)]
    return b, bodies


@pytest.mark.parametrize("integrator, dt, frames", [("semi_implicit_euler", 1.0 / 1200.0, 30),
                                                    ("implicit_euler", 1.0 / 600.0, 6)])
def test_pressed_tori_never_interpenetrate_beyond_their_thickness(integrator, dt, frames):
    runs = {}
    for with_contact in (True, False):
        b, (lower, upper) = two_tori(gap=0.004)
        model = b.finalize(DEVICE)
        press = [ws.ConstantForce((0.0, 0.03, 0.0), lower.surface_indices),  # ~4 N on each torus
                 ws.ConstantForce((0.0, -0.03, 0.0), upper.surface_indices)]
        contact = ws.SoftContact([lower, upper], thickness=THICKNESS, friction=0.5)
        sim = ws.Simulator(model, integrator=integrator, forces=press, colliders=[contact] if with_contact else [])
        deepest, gaps = 0.0, []
        substeps = round(1.0 / 60.0 / dt)
        for _ in range(frames):
            for _ in range(substeps):
                sim.step(dt)
            x = sim.state.positions.numpy()
            deepest = max(deepest, penetration(x, lower, upper), penetration(x, upper, lower))
            gaps.append(x[upper.surface_indices, 1].mean() - x[lower.surface_indices, 1].mean())
        runs[with_contact] = (deepest, gaps, contact.contact_count if with_contact else 0)
    deepest, gaps, contacts = runs[True]
    assert contacts > 20  # they are pressed together ...
    assert deepest <= THICKNESS, deepest  # ... and never interpenetrate beyond the thickness
    assert gaps[-1] > 0.08 + 0.5 * THICKNESS  # the upper torus rests on the lower one
    free_deepest, free_gaps, _ = runs[False]
    assert free_deepest > 3.0 * THICKNESS and free_gaps[-1] < gaps[-1] - 0.02  # without contact: through


def test_momentum_is_conserved_across_a_collision():
    b, bodies = two_tori(gap=0.03, velocity=((0.0, 1.5, 0.2), (0.0, -1.5, 0.0)), offset=(0.0, 0.06), mass=0.5)
    b.add_particle((3.0, 0.0, 0.0), mass=0.0)  # a pinned particle the contact never touches
    model = b.finalize(DEVICE)
    contact = ws.SoftContact(bodies, thickness=THICKNESS, friction=0.5, restitution=0.5)
    sim = ws.Simulator(model, forces=[], colliders=[contact])
    m = model.particle_mass.numpy().astype(np.float64)[:, None]

    def momenta():
        v = sim.state.velocities.numpy().astype(np.float64)
        return [(m[body.particle_start:body.particle_start + body.particle_count]
                 * v[body.particle_start:body.particle_start + body.particle_count]).sum(0) for body in bodies]

    p0 = momenta()
    most = 0
    for _ in range(240):
        sim.step(1.0 / 2400.0)
        most = max(most, contact.contact_count)
        p = momenta()
        np.testing.assert_allclose(p[0] + p[1], p0[0] + p0[1], atol=1e-4)
    assert most > 10
    # the collision happened: the lower torus no longer moves up at 0.75 kg m/s
    assert p[0][1] < 0.5 * p0[0][1]
    x = sim.state.positions.numpy()
    assert max(penetration(x, bodies[0], bodies[1]), penetration(x, bodies[1], bodies[0])) <= THICKNESS


def test_donut_heap_comes_to_rest_with_no_torus_inside_another():
    cls = get_scene("donuts")
    params = cls.resolve_params({"count": 4, "segments": 14, "sides": 7, "lattice_cells": 6, "box": 0.16})
    scene = cls(params, device=DEVICE)
    energies = []
    for _ in range(150):
        scene.advance(1.0 / 60.0, scene.substeps)
        energies.append(scene.kinetic_energy())
    energies = np.array(energies)
    peak = energies.max()
    assert peak > 0.5  # they fell
    assert energies[-10:].max() < 1e-3 * peak  # ... and came to rest
    x = scene.sim.state.positions.numpy()
    heights = [x[b.surface_indices, 1].mean() for b in scene.bodies]
    assert max(heights) > 0.1  # a heap: at least one torus lies on another (tube diameter 0.08 m)
    for a in scene.bodies:
        for b in scene.bodies:
            if a is not b:
                assert penetration(x, a, b) <= scene.params["thickness"]


def test_self_contact_finds_nothing_in_the_rest_pose():
    b, bodies = two_tori()
    model = b.finalize(DEVICE)
    contact = ws.SoftContact(bodies[:1], thickness=THICKNESS, self_contact=True)
    sim = ws.Simulator(model, forces=[], colliders=[contact])
    sim.step(1e-3)
    assert contact.contact_count == 0


def test_bad_input():
    b, bodies = two_tori()
    with pytest.raises(ValueError, match="thickness"):
        ws.SoftContact(bodies, thickness=0.0)
    with pytest.raises(ValueError, match="restitution"):
        ws.SoftContact(bodies, restitution=1.5)
    with pytest.raises(ValueError, match="friction"):
        ws.SoftContact(bodies, friction=float("nan"))
    with pytest.raises(ValueError, match="self_contact"):
        ws.SoftContact(bodies[:1])
    with pytest.raises(ValueError, match="shape"):
        ws.SoftContact([bodies[0], np.arange(4)])
    model = b.finalize(DEVICE)
    with pytest.raises(ValueError, match="also belongs to bodies"):
        ws.Simulator(model, colliders=[ws.SoftContact([bodies[0], bodies[0].faces[:5]])])
    with pytest.raises(ValueError, match="out of range"):
        ws.Simulator(model, colliders=[ws.SoftContact([bodies[0], bodies[1].faces + 10_000])])
