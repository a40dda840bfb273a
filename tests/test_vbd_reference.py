"""VBD against statics and against another VBD: a soft torus dropped on the floor by ``ws.VBD`` comes to rest where its
springs, gravity and the floor's contact balance, and where Newton's ``SolverVBD`` brings the same torus
(``tests/newton_reference.py``: the same particles, springs, colouring, planes and contact coefficients).

Friction is off, so the resting shape is the one equilibrium of the springs, gravity and the floor (a torus still
sliding on a frictionless floor is at rest in every other sense: it drifts, it does not deform); 300 steps of 1/240 s
(1.25 s: the torus lands at about 0.3 s, and both solvers' heights stop changing by 0.75 s); the box widened
to 0.4 m so that the drifting torus meets no wall before the end (it does at step 342; in the scene's own box at
step 259).
"""

import numpy as np
import pytest

from warpsim.scenes import get_scene

H = 1.0 / 240.0
STEPS = 300
PARAMS = {"count": 1, "segments": 24, "sides": 12, "lattice_cells": 8, "dt": H, "integrator": "vbd", "friction": 0.0,
          "box": 0.4}


def dropped_torus():
    """The donuts scene with one torus of 24 x 12 surface vertices and its lattice, stepped by VBD, not yet stepped."""
    cls = get_scene("donuts")
    return cls(cls.resolve_params(dict(PARAMS)), device="cpu")


def static_residual(scene, x: np.ndarray) -> np.ndarray:
    """Each particle's net force [N] at positions ``x`` (N, 3) [m] from the springs, gravity and the planes' contact
    k_c (r_c - d) n (the scene's coefficients; no friction, no velocity): zero at a static equilibrium. NumPy, in
    float64, independent of the kernels."""
    model, contact = scene.sim.model, scene.vbd_contact
    x = x.astype(np.float64)
    ends = model.spring_indices.numpy().reshape(-1, 2)
    rest = model.spring_rest_length.numpy().astype(np.float64)
    k = model.spring_stiffness.numpy().astype(np.float64)
    d = x[ends[:, 1]] - x[ends[:, 0]]
    length = np.linalg.norm(d, axis=1)
    pull = (k * (length - rest) / length)[:, None] * d
    force = np.zeros_like(x)
    np.add.at(force, ends[:, 0], pull)
    np.add.at(force, ends[:, 1], -pull)
    force[:, 1] -= model.particle_mass.numpy() * scene.params["gravity"]
    for plane in contact._planes.numpy().astype(np.float64):
        depth = np.clip(contact.thickness - (x @ plane[:3] - plane[3]), 0.0, None)
        force += (contact.stiffness * depth)[:, None] * plane[:3]
    return force


def test_a_dropped_torus_comes_to_rest_where_springs_gravity_and_floor_balance():
    """Over the last 60 steps, each step's largest residual (the median of them) under 10 % of the lightest
    particle's weight (25.5 mN; in flight a particle's residual is its whole weight). Measured: median 0.11 mN, the
    largest 0.43 mN. The torus drifts on the frictionless floor (about 0.09 m/s) and meets a wall of the widened box
    at step 342, after the window (its vertices then take 20 mN from the wall for a step and ring at about 3.5 mN);
    the median keeps a step where a vertex enters or leaves the floor's range from deciding it."""
    scene = dropped_torus()
    largest = []
    for k in range(STEPS):
        scene.sim.step(H)
        if k >= STEPS - 60:
            largest.append(np.linalg.norm(static_residual(scene, scene.sim.state.positions.numpy()), axis=1).max())
    x = scene.sim.state.positions.numpy()
    weight = scene.sim.model.particle_mass.numpy() * scene.params["gravity"]
    assert np.median(largest) < 0.1 * weight.min(), largest
    depth = np.clip(scene.vbd_contact.thickness - x[:, 1], 0.0, None)
    floor = (scene.vbd_contact.stiffness * depth).sum()
    assert floor == pytest.approx(weight.sum(), rel=0.01)  # measured 9.816 N against 9.810 N
    assert 0.0 < depth.max() < 0.5 * scene.vbd_contact.thickness  # inside the contact's quadratic range


def test_newton_solver_vbd_brings_the_same_torus_to_the_same_rest():
    pytest.importorskip("newton")
    from newton_reference import NewtonHeap

    scene = dropped_torus()
    other = NewtonHeap(scene)  # built from the scene before its first step: both start from the same state
    for _ in range(STEPS):
        scene.sim.step(H)
        other.step(H)
    ours, theirs = scene.sim.state.positions.numpy(), other.positions()
    weight = scene.sim.model.particle_mass.numpy() * scene.params["gravity"]
    # Newton's rest balances the same forces (measured: largest residual 2.7 mN; ours 0.03-5.8 mN, above) ...
    assert np.linalg.norm(static_residual(scene, theirs), axis=1).max() < 0.2 * weight.min()
    # ... at the same height: measured mean heights 44.57 and 44.59 mm, lowest vertices 5.73 mm both; halving the
    # contact stiffness would double the floor penetration of 0.27 mm (inversely proportional to it)
    assert theirs[:, 1].mean() == pytest.approx(ours[:, 1].mean(), abs=1.0e-4)
    assert theirs[:, 1].min() == pytest.approx(ours[:, 1].min(), abs=5.0e-5)


def test_newtons_adjacency_built_on_another_device_is_newtons_own():
    """On the GPU machine Warp has no CPU compiler, and Newton's ``ModelBuilder.finalize`` launches its vertex
    adjacency kernels on "cpu"; ``newton_reference.adjacency_on(device)`` launches the same kernels on the heap's
    device. Here (a CPU compiler at hand) both run: the same vertex-edge, vertex-triangle and vertex-spring CSR rows
    for the donut torus, its surface triangles, edges and springs, as Newton's own builder."""
    pytest.importorskip("newton")
    from newton._src.utils import mesh
    from newton_reference import NewtonHeap, adjacency_on

    scene = dropped_torus()
    own = NewtonHeap(scene).model.soft_mesh_adjacency
    names = ("v_adj_edges", "v_adj_edges_offsets", "v_adj_tris", "v_adj_tris_offsets", "v_adj_springs",
             "v_adj_springs_offsets")
    expected = [np.array(getattr(own, name)) for name in names]
    original = mesh.build_vertex_adjacency_with_warp
    calls = []

    def counted(*args, **kwargs):
        calls.append(1)
        return adjacency_on("cpu")(*args, **kwargs)

    mesh.build_vertex_adjacency_with_warp = counted
    try:
        ours = NewtonHeap(scene).model.soft_mesh_adjacency
    finally:
        mesh.build_vertex_adjacency_with_warp = original
    assert len(calls) >= 3  # edges, triangles, springs
    for name, want in zip(names, expected):
        got = np.array(getattr(ours, name))
        assert len(want) > 0 and np.array_equal(got, want), name
