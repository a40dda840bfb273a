"""Differentiable runs (warpsim.diff): the forward pass equals the ordinary mode bit for bit, the
gradients of every differentiable force, integrator and collider match central finite
differences of a float64 NumPy reference (warpsim.diff.reference), and what cannot be
differentiated is refused with a ValueError that says so."""

import numpy as np
import pytest
import warp as wp

import warpsim as ws
from warpsim.diff import check_differentiable
from warpsim.diff import reference as ref

RTOL = 1.0e-3


def particles(n=2):
    return dict(q=[(0.0, 0.5, 0.0), (0.3, 0.62, 0.1)][:n], v=[(0.4, 0.8, 0.2), (-0.3, 0.1, 0.05)][:n],
                mass=[1.0, 0.7][:n], radius=[0.05, 0.05][:n], springs=[], forces=[], colliders=[],
                integrator="semi_implicit_euler", h=0.01, steps=12)


def falling(**kw):
    """Two particles that reach the floor y = 0 within a few steps."""
    s = dict(particles(), q=[(0.0, 0.15, 0.0), (0.3, 0.2, 0.1)], v=[(0.4, -1.0, 0.2), (-0.3, -1.5, 0.05)],
             forces=[("gravity", (0.0, -9.81, 0.0))], steps=30)
    s.update(kw)
    return s


def spring_pair(**kw):
    s = particles()
    s["springs"] = [(0, 1, 60.0, 0.4, 0.25)]
    s.update(kw)
    return s


SCENES = {
    "gravity": (dict(particles(), forces=[("gravity", (0.3, -9.81, 0.2))]), ["gravity.g", "v"]),
    "constant": (dict(particles(), forces=[("constant", (0.5, 1.0, -0.2), [1])]), ["constant.force", "mass", "v"]),
    "drag": (dict(particles(), forces=[("drag", 0.3, 0.2)]), ["drag.linear", "drag.quadratic", "v", "mass"]),
    "wind": (dict(particles(), forces=[("wind", dict(direction=(1.0, 0.2, 0.0), speed=3.0, gust_amplitude=0.3,
                                                     gust_frequency=2.0, coefficient=0.2, seed=1))]),
             ["wind.coefficient", "v", "mass"]),
    "magnets": (dict(particles(), forces=[("magnets", [(0.2, 0.9, 0.0), (-0.3, 0.2, 0.1)], [0.05, -0.03], 0.1,
                                           None)]), ["magnets.strengths", "magnets.centers", "q", "mass"]),
    "springs_semi_implicit": (spring_pair(), ["stiffness", "damping", "rest_length", "q", "v", "mass"]),
    "springs_explicit": (spring_pair(integrator="explicit_euler"), ["stiffness", "damping", "q", "v", "mass"]),
    "plane_reflect": (falling(colliders=[("plane", (0.0, 1.0, 0.0), 0.0, dict(restitution=0.6, friction=0.1))]),
                      ["v", "q", "gravity.g"]),
    "plane_project": (falling(colliders=[("plane", (0.1, 1.0, 0.0), -0.02, dict(restitution=0.3, mode="project"))]),
                      ["v", "q"]),
    "plane_penalty": (falling(h=0.005, steps=50, colliders=[("plane", (0.0, 1.0, 0.0), 0.0, dict(
        restitution=0.5, friction=0.2, mode="penalty", stiffness=2000.0))]), ["v", "q", "mass"]),
    "sphere": (dict(particles(1), q=[(0.05, 0.9, 0.02)], v=[(0.0, -1.0, 0.0)], forces=[("gravity", (0.0, -9.81, 0.0))],
                    steps=30, colliders=[("sphere", (0.0, 0.4, 0.0), 0.25, dict(restitution=0.7, friction=0.1))]),
               ["v", "q"]),
    "cloth_semi_implicit": (dict(spring_pair(integrator="cloth"), forces=[("gravity", (0.0, -9.81, 0.0)),
                                                                          ("drag", 0.1, 0.0)]),
                            ["stiffness", "damping", "v", "gravity.g", "drag.linear"]),
}


def warp_gradients(scene, names, targets):
    sim = ref.build(scene)
    for _ in range(scene["steps"]):
        sim.step(scene["h"])
    r = sim.rollout
    loss = r.trajectory_loss([wp.array(t, dtype=wp.vec3, device="cpu") for t in targets])
    r.backward(loss)
    out = {}
    m = sim.model
    for name in names:
        if name == "q":
            out[name] = r.states[0].positions.grad.numpy().reshape(-1)
        elif name == "v":
            out[name] = r.states[0].velocities.grad.numpy().reshape(-1)
        elif name == "mass":
            out[name] = r.mass_gradient()
        elif name in ("stiffness", "damping", "rest_length"):
            out[name] = getattr(m, "spring_" + name).grad.numpy()
        else:
            kind, coef = name.split(".")
            cls = {"gravity": ws.Gravity, "constant": ws.ConstantForce, "drag": ws.Drag, "wind": ws.Wind,
                   "magnets": ws.Magnets}[kind]
            force = next(f for f in sim.forces if isinstance(f, cls))
            out[name] = np.atleast_1d(r.coefficient_gradients(force)[coef]).reshape(-1)
    return float(loss.numpy()[0]), out


def fd_indices(scene, name):
    n, s = len(scene["q"]), len(scene["springs"])
    if name in ("q", "v"):
        return [(i, c) for i in range(n) for c in range(3)]
    if name == "mass":
        return list(range(n))
    if name in ("stiffness", "damping", "rest_length"):
        return list(range(s))
    kind, coef = name.split(".")
    spec = next(sp for sp in scene["forces"] if sp[0] == kind)
    if coef in ("g", "force"):
        return [0, 1, 2]
    if coef == "centers":
        return [(m, c) for m in range(len(spec[1])) for c in range(3)]
    if coef == "strengths":
        return list(range(len(spec[2])))
    return [None]


@pytest.mark.parametrize("case", sorted(SCENES))
def test_gradients_match_central_differences_of_float64_reference(case):
    scene, names = SCENES[case]
    target = np.array(scene["q"], dtype=np.float64) + np.array([0.3, -0.2, 0.1])
    targets = [target]
    loss, grads = warp_gradients(scene, names, targets)
    assert loss == pytest.approx(ref.loss(scene, targets), rel=1e-4)
    for name in names:
        fd = ref.finite_difference(scene, targets, name, fd_indices(scene, name))
        g = grads[name]
        err = np.linalg.norm(g - fd) / np.linalg.norm(fd)
        assert np.linalg.norm(fd) > 1e-6, (case, name, fd)  # the parameter matters
        assert err < RTOL, (case, name, g, fd, err)


def test_contact_happens_in_the_collider_cases():
    """The collider cases exercise contact (their gradients go through the contact branch)."""
    for case in ("plane_reflect", "plane_project", "plane_penalty", "sphere"):
        scene = SCENES[case][0]
        free = dict(scene, colliders=[])
        assert np.abs(ref.simulate(scene) - ref.simulate(free)).max() > 0.01, case


ALL_FORCES = [ws.Gravity((0.1, -9.81, 0.0)), ws.Drag(0.1, 0.05), ws.Wind(coefficient=0.2, gust_frequency=1.0),
              ws.Magnets([(0.0, 1.0, 0.0)], [0.1]), ws.ConstantForce((0.1, 0.0, 0.0))]


def spring_model(device="cpu"):
    b = ws.ModelBuilder()
    b.add_particle((0.0, 0.5, 0.0), vel=(1.0, 2.0, 0.3), mass=1.0, radius=0.05)
    b.add_particle((0.3, 0.6, 0.0), mass=0.5, radius=0.05)
    b.add_particle((0.1, 0.9, 0.0), mass=0.0, radius=0.05)
    b.add_spring(0, 1, 50.0, 0.5)
    b.add_spring(1, 2, 80.0, 0.2)
    return b.finalize(device)


@pytest.mark.parametrize("integrator", ["semi_implicit_euler", "explicit_euler"])
def test_forward_is_identical_to_the_ordinary_mode(integrator):
    def colliders():
        return [ws.Plane(restitution=0.5, friction=0.2), ws.Box((-1, -1, -1), (1, 2, 1), restitution=0.9),
                ws.Sphere((0.5, 0.2, 0.0), 0.2, continuous=False, mode="penalty")]

    a = ws.Simulator(spring_model(), integrator, ALL_FORCES, colliders())
    b = ws.Simulator(spring_model(), integrator, ALL_FORCES, colliders(), differentiable=True)
    for _ in range(80):
        a.step(0.01)
        b.step(0.01)
    assert b.state is b.rollout.states[80]
    assert np.array_equal(a.state.positions.numpy(), b.state.positions.numpy())
    assert np.array_equal(a.state.velocities.numpy(), b.state.velocities.numpy())
    assert np.array_equal(a.state.forces.numpy(), b.state.forces.numpy())
    assert a.state.positions.numpy()[0, 1] < 0.5  # it moved


def test_cloth_forward_is_identical_and_reset_replays():
    def make(diff):
        b = ws.ModelBuilder()
        ws.add_cloth_grid(b, (4, 4), (0.4, 0.4), origin=(0.0, 0.5, 0.0), pin=["corner_00", "corner_10"],
                          particle_mass=0.01, structural=(20.0, 0.05), shear=(20.0, 0.05), bend=(2.0, 0.01))
        return ws.ClothSimulator(b.finalize("cpu"), "semi_implicit_euler",
                                 [ws.Gravity(), ws.Wind(coefficient=0.01)], [ws.Sphere((0.2, 0.3, -0.2), 0.1,
                                                                                      continuous=False)],
                                 differentiable=diff)

    a, b = make(False), make(True)
    a.run(10, substeps=8)
    b.run(10, substeps=8)
    assert np.array_equal(a.state.positions.numpy(), b.state.positions.numpy())
    first = b.state.positions.numpy().copy()
    b.rollout.reset()
    assert b.rollout.step_count == 0 and np.array_equal(b.state.positions.numpy(), b.model.particle_q.numpy())
    b.run(10, substeps=8)
    assert np.array_equal(b.state.positions.numpy(), first)


def test_gradient_of_a_reused_rollout_is_the_same():
    sim = ref.build(SCENES["springs_semi_implicit"][0])
    target = wp.zeros(2, dtype=wp.vec3, device="cpu")
    grads = []
    for _ in range(2):
        sim.rollout.reset()
        for _ in range(10):
            sim.step(0.01)
        sim.rollout.backward(sim.rollout.trajectory_loss([target]))
        grads.append(sim.model.spring_stiffness.grad.numpy().copy())
    assert grads[0][0] != 0.0 and np.array_equal(grads[0], grads[1])


# --------------------------------------------------------------------------------------
# Refusals
# --------------------------------------------------------------------------------------
def _mesh_collider():
    pts = [(-1.0, 0.0, -1.0), (1.0, 0.0, -1.0), (0.0, 0.0, 1.0)]
    return ws.TriangleMesh(pts, [(0, 1, 2)])


@pytest.mark.parametrize("kwargs, words", [
    (dict(adaptive=True, max_displacement=0.01), "adaptive sub-stepping"),
    (dict(integrator="implicit_euler"), "Newton / conjugate-gradient"),
    (dict(integrator="rk4"), "rk4"),
    (None, None),
    (dict(colliders=[ws.Sphere()]), "continuous collision detection"),
    (dict(colliders=[ws.Capsule(continuous=False, motion=lambda t: ((0.0, t, 0.0), (0.0, 0.0, 0.0, 1.0)))]), "moves"),
    (dict(colliders=[ws.ParticleCollisions()]), "ParticleCollisions"),
])
def test_what_cannot_be_differentiated_is_refused(kwargs, words):
    if words is None:  # a user force field: its kernels have no backward pass
        @wp.func
        def field(x: wp.vec3, v: wp.vec3, t: float) -> wp.vec3:
            return x

        kwargs, words = dict(forces=[ws.ForceField(field)]), "ForceField"
    with pytest.raises(ValueError, match="differentiable=True") as info:
        ws.Simulator(spring_model(), differentiable=True, **kwargs)
    assert words in str(info.value)


def test_cloth_implicit_euler_and_breakable_springs_and_fluids_are_refused():
    b = ws.ModelBuilder()
    ws.add_cloth_grid(b, (2, 2), (0.2, 0.2))
    with pytest.raises(ValueError, match="implicit_euler.*not differentiated"):
        ws.ClothSimulator(b.finalize("cpu"), "implicit_euler", differentiable=True)
    b = ws.ModelBuilder()
    b.add_particle((0.0, 0.0, 0.0))
    b.add_particle((0.1, 0.0, 0.0))
    b.add_spring(0, 1, 10.0, 0.0, break_strain=0.5)
    with pytest.raises(ValueError, match="breakable springs"):
        ws.Simulator(b.finalize("cpu"), differentiable=True)
    with pytest.raises(ValueError, match="fluid solvers"):
        check_differentiable(ws.ParticleFluid.__new__(ws.ParticleFluid))


def test_rollout_bad_input_is_named():
    sim = ws.Simulator(spring_model(), differentiable=True)
    sim.step(0.01)
    target = wp.zeros(3, dtype=wp.vec3, device="cpu")
    with pytest.raises(ValueError, match=r"2 targets for 1 step\(s\) \(steps=None means the last step only \(1\)\).*"
                       r"steps=\[k1, k2"):
        sim.rollout.trajectory_loss([target, target])
    with pytest.raises(ValueError, match=r"integrated\(2\): steps 1..1 exist"):
        sim.rollout.integrated(2)
    with pytest.raises(ValueError, match="Springs is not one of"):
        sim.rollout.coefficient_gradients(sim.forces[-1])
