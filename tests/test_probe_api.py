"""A hostile but fair user's probe of the Python API: every bad input below must fail early
with the expected exception type and a message that names the offending item (and, where the
table says so, the value or the fix). Table-driven: one row per bad input, ``(id, call, type,
words)``; ``call(ctx)`` gets the files made by the ``ctx`` fixture. Nothing here builds a big
model: the errors come before any kernel runs (except the few meshing/field checks, on tiny
grids)."""

import math
import struct

import numpy as np
import pytest
import warp as wp

import warpsim as ws
from warpsim.bodies import meshtools
from warpsim.core import checks
from warpsim.core.simulator import check_dt

NAN, INF = math.nan, math.inf

CUBE_V = np.array([(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1)],
                  float)
CUBE_F = np.array([(0, 2, 1), (0, 3, 2), (4, 5, 6), (4, 6, 7), (0, 1, 5), (0, 5, 4), (1, 2, 6), (1, 6, 5),
                   (2, 3, 7), (2, 7, 6), (3, 0, 4), (3, 4, 7)])
FLAT_V = np.array([(0, 0, 0), (1, 0, 0), (0, 1, 0)], float)  # a triangle and its back face: closed, no volume
FLAT_F = np.array([(0, 1, 2), (0, 2, 1)])


def obj_bytes(points, faces, head=b""):
    return head + b"".join(b"v %r %r %r\n" % tuple(float(x) for x in p) for p in points) + \
        b"".join(b"f %d %d %d\n" % tuple(int(i) + 1 for i in f) for f in faces)


@pytest.fixture(scope="module")
def ctx(tmp_path_factory):
    d = tmp_path_factory.mktemp("probe_api")
    files = {
        "nan.obj": obj_bytes(np.vstack([CUBE_V[:3], [(0, NAN, 0)], CUBE_V[4:]]), CUBE_F),
        "inf.obj": obj_bytes(np.vstack([CUBE_V[:5], [(1, 0, INF)], CUBE_V[6:]]), CUBE_F),
        "garbage.obj": b"v 1 2\nf 1 2 x\n\x00\x01\x02",
        "empty.obj": b"",
        "noface.obj": b"# only vertices\nv 0 0 0\nv 1 0 0\n",
        "badindex.obj": obj_bytes(CUBE_V, [(0, 1, 29)]),
        "garbage.stl": bytes(range(50)),
        "truncated.stl": b"\0" * 80 + struct.pack("<I", 100) + b"\0" * 60,
        "garbage.ply": b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nend_header\n1\n",
        "garbage.glb": b"glTF\x02\x00\x00\x00garbage",
        "garbage.off": b"OFF\n3 1 0\n0 0 0\n",
        "garbage.usda": b"#usda 1.0\n(((( nonsense",
        "mesh.xyz": b"1 2 3\n",
        "flat.obj": obj_bytes(FLAT_V, FLAT_F),
    }
    for name, data in files.items():
        (d / name).write_bytes(data)
    (d / "folder.obj").mkdir()
    return {"dir": d, **{name: str(d / name) for name in files}, "folder.obj": str(d / "folder.obj"),
            "missing.obj": str(d / "missing.obj")}


def two_particles():
    b = ws.ModelBuilder()
    b.add_particle((0, 0, 0))
    b.add_particle((1, 0, 0))
    return b


def coincident():
    b = ws.ModelBuilder()
    b.add_particle((0, 1, 0))
    b.add_particle((0, 1, 0))
    return b


def model():
    return two_particles().finalize("cpu")


def moved_after_spring():
    b = two_particles()
    b.add_spring(0, 1, 10.0, 0.0)  # rest length 1 m
    b.particle_q[1] = b.particle_q[0]  # edited afterwards: caught at finalize
    return b.finalize("cpu")


def soft(**kw):
    return ws.add_soft_body(ws.ModelBuilder(), CUBE_V, CUBE_F, **kw)


def mac(**kw):
    args = {"shape": (4, 4, 4), "dx": 0.1, "device": "cpu"}
    args.update(kw)
    return ws.MacGrid(**args)


def sphere_field(n=8):
    x = np.linspace(-1, 1, n)
    X, Y, Z = np.meshgrid(x, x, x, indexing="ij")
    return (np.sqrt(X**2 + Y**2 + Z**2) - 0.5).astype(np.float32)


def field_with(value, at=(3, 4, 2)):
    f = sphere_field()
    f[at] = value
    return f


V = ValueError
FNF = FileNotFoundError

CASES = [
    # ---- ModelBuilder.add_particle / add_particles
    ("particle-pos-str", lambda c: ws.ModelBuilder().add_particle("abc"), V,
     ["particle 0 position", "'abc'"]),
    ("particle-pos-2d", lambda c: ws.ModelBuilder().add_particle((0, 1)), V,
     ["particle 0 position", "3 components"]),
    ("particle-pos-4d", lambda c: ws.ModelBuilder().add_particle((0, 1, 2, 3)), V,
     ["particle 0 position", "3"]),
    ("particle-pos-nan", lambda c: ws.ModelBuilder().add_particle((0, NAN, 0)), V,
     ["particle 0 position", "finite"]),
    ("particle-pos-inf", lambda c: ws.ModelBuilder().add_particle((INF, 0, 0)), V,
     ["particle 0 position", "finite"]),
    ("particle-pos-none", lambda c: ws.ModelBuilder().add_particle(None), V, ["particle 0 position", "None"]),
    ("particle-pos-scalar", lambda c: ws.ModelBuilder().add_particle(1.0), V,
     ["particle 0 position", "3 numbers"]),
    ("particle-pos-component-str", lambda c: ws.ModelBuilder().add_particle((0, "d", 0)), V,
     ["particle 0 position component 1", "'d'"]),
    ("particle-vel-str", lambda c: ws.ModelBuilder().add_particle((0, 0, 0), vel="fast"), V,
     ["particle 0 velocity", "'fast'"]),
    ("particle-vel-nan", lambda c: ws.ModelBuilder().add_particle((0, 0, 0), vel=(NAN, 0, 0)), V,
     ["particle 0 velocity", "finite"]),
    ("particle-mass-neg", lambda c: ws.ModelBuilder().add_particle((0, 0, 0), mass=-1), V,
     ["particle 0", "mass -1"]),
    ("particle-mass-nan", lambda c: ws.ModelBuilder().add_particle((0, 0, 0), mass=NAN), V,
     ["particle 0", "mass nan"]),
    ("particle-mass-inf", lambda c: ws.ModelBuilder().add_particle((0, 0, 0), mass=INF), V,
     ["particle 0", "mass inf"]),
    ("particle-mass-str", lambda c: ws.ModelBuilder().add_particle((0, 0, 0), mass="heavy"), V,
     ["particle 0 mass", "'heavy'"]),
    ("particle-mass-none", lambda c: ws.ModelBuilder().add_particle((0, 0, 0), mass=None), V,
     ["particle 0 mass", "None"]),
    ("particle-radius-neg", lambda c: ws.ModelBuilder().add_particle((0, 0, 0), radius=-0.1), V,
     ["particle 0", "radius -0.1"]),
    ("particle-radius-str", lambda c: ws.ModelBuilder().add_particle((0, 0, 0), radius="r"), V,
     ["particle 0 radius", "'r'"]),
    ("particles-shape", lambda c: ws.ModelBuilder().add_particles(np.zeros((4, 2))), V,
     ["add_particles positions", "(N, 3)"]),
    ("particles-nan-row", lambda c: ws.ModelBuilder().add_particles([(0, 0, 0), (0, 0, 0), (0, NAN, 0)]), V,
     ["add_particles positions", "2", "not finite"]),
    ("particles-vel-count", lambda c: ws.ModelBuilder().add_particles(np.zeros((3, 3)), np.zeros((2, 3))), V,
     ["positions has 3", "velocities has 2"]),
    ("particles-mass-count", lambda c: ws.ModelBuilder().add_particles(np.zeros((3, 3)), masses=[1, 2]), V,
     ["add_particles masses", "2 entries", "3"]),
    ("particles-mass-neg", lambda c: ws.ModelBuilder().add_particles(np.zeros((3, 3)), masses=[1, -2, 1]), V,
     ["add_particles masses", "-2"]),
    ("particles-radii-nan", lambda c: ws.ModelBuilder().add_particles(np.zeros((2, 3)), radii=[0.1, NAN]), V,
     ["add_particles radii", "nan"]),
    ("particles-str", lambda c: ws.ModelBuilder().add_particles("points"), V,
     ["add_particles positions", "'points'"]),
    # ---- add_spring / finalize
    ("spring-self", lambda c: two_particles().add_spring(1, 1, 10.0), V,
     ["spring 0", "particle 1 to itself"]),
    ("spring-range", lambda c: two_particles().add_spring(0, 5, 10.0), V,
     ["spring 0", "j=5", "out of range"]),
    ("spring-negative-index", lambda c: two_particles().add_spring(-1, 1, 10.0), V, ["spring 0", "i=-1"]),
    ("spring-index-float", lambda c: two_particles().add_spring(0.0, 1, 10.0), V,
     ["spring 0", "i=0.0", "integer"]),
    ("spring-index-str", lambda c: two_particles().add_spring("a", 1, 10.0), V, ["spring 0", "i='a'"]),
    ("spring-stiffness-neg", lambda c: two_particles().add_spring(0, 1, -3.0), V,
     ["spring 0", "stiffness -3"]),
    ("spring-stiffness-str", lambda c: two_particles().add_spring(0, 1, "stiff"), V,
     ["spring 0 stiffness", "'stiff'"]),
    ("spring-stiffness-nan", lambda c: two_particles().add_spring(0, 1, NAN), V,
     ["spring 0", "stiffness nan"]),
    ("spring-damping-neg", lambda c: two_particles().add_spring(0, 1, 1.0, -1.0), V,
     ["spring 0", "damping -1"]),
    ("spring-damping-str", lambda c: two_particles().add_spring(0, 1, 1.0, "d"), V,
     ["spring 0 damping", "'d'"]),
    ("spring-rest-neg", lambda c: two_particles().add_spring(0, 1, 1.0, rest_length=-1.0), V,
     ["spring 0", "rest length -1"]),
    ("spring-rest-str", lambda c: two_particles().add_spring(0, 1, 1.0, rest_length="l"), V,
     ["spring 0 rest length", "'l'"]),
    ("spring-rest-inf", lambda c: two_particles().add_spring(0, 1, 1.0, rest_length=INF), V,
     ["spring 0", "rest length inf"]),
    ("spring-coincident", lambda c: coincident().add_spring(0, 1, 10.0, rest_length=0.2), V,
     ["spring 0", "particles 0 and 1 at the same position", "rest length 0.2", "rest_length=0"]),
    ("spring-coincident-finalize", lambda c: moved_after_spring(), V,
     ["spring 0", "particles 0 and 1 at the same position"]),
    # ---- Simulator and its options
    ("sim-forces-single", lambda c: ws.Simulator(model(), forces=ws.Gravity()), V,
     ["forces must be a list", "Gravity", "forces=[ws.Gravity()]"]),
    ("sim-forces-str", lambda c: ws.Simulator(model(), forces="gravity"), V, ["forces", "'gravity'"]),
    ("sim-forces-item", lambda c: ws.Simulator(model(), forces=[ws.Gravity(), "wind"]), V,
     ["forces[1] is str"]),
    ("sim-forces-number", lambda c: ws.Simulator(model(), forces=9.81), V, ["forces", "9.81"]),
    ("sim-colliders-single", lambda c: ws.Simulator(model(), colliders=ws.Plane()), V,
     ["colliders must be a list", "Plane"]),
    ("sim-colliders-item", lambda c: ws.Simulator(model(), colliders=[ws.Plane(), ws.Gravity()]), V,
     ["colliders[1] is Gravity"]),
    ("sim-collider-as-force", lambda c: ws.Simulator(model(), forces=[ws.Plane()]), V,
     ["forces[0] is Plane"]),
    ("sim-integrator-unknown", lambda c: ws.Simulator(model(), integrator="verlet"), V,
     ["unknown integrator 'verlet'", "rk4"]),
    ("sim-integrator-number", lambda c: ws.Simulator(model(), integrator=4), V, ["unknown integrator 4"]),
    ("sim-max-speed-zero", lambda c: ws.Simulator(model(), max_speed=0), V, ["max_speed", "got 0", "> 0"]),
    ("sim-max-speed-neg", lambda c: ws.Simulator(model(), max_speed=-5.0), V, ["max_speed", "-5.0"]),
    ("sim-max-speed-nan", lambda c: ws.Simulator(model(), max_speed=NAN), V, ["max_speed", "nan"]),
    ("sim-max-speed-str", lambda c: ws.Simulator(model(), max_speed="fast"), V, ["max_speed", "'fast'"]),
    ("sim-max-substeps", lambda c: ws.Simulator(model(), max_substeps=0), V, ["max_substeps", "got 0"]),
    ("sim-max-substeps-float", lambda c: ws.Simulator(model(), max_substeps=2.5), V, ["max_substeps", "2.5"]),
    ("sim-check-every", lambda c: ws.Simulator(model(), check_every=-1), V, ["check_every", "-1"]),
    ("sim-adaptive-no-disp", lambda c: ws.Simulator(model(), adaptive=True), V, ["max_displacement"]),
    ("sim-adaptive-neg-disp", lambda c: ws.Simulator(model(), adaptive=True, max_displacement=-0.1), V,
     ["max_displacement", "-0.1"]),
    ("sim-model-str", lambda c: ws.Simulator("model"), V, ["Simulator model", "'model'", "finalize"]),
    ("sim-model-builder", lambda c: ws.Simulator(ws.ModelBuilder()), V, ["Simulator model", "finalize"]),
    ("dt-zero", lambda c: check_dt(0.0), V, ["dt must be > 0"]),
    ("dt-neg", lambda c: check_dt(-0.01), V, ["dt must be > 0", "-0.01"]),
    ("dt-nan", lambda c: check_dt(NAN), V, ["dt must be > 0", "nan"]),
    ("dt-str", lambda c: check_dt("0.01"), V, ["dt must be a number", "'0.01'"]),
    ("dt-none", lambda c: check_dt(None), V, ["dt must be a number", "None"]),
    ("run-substeps", lambda c: ws.Simulator(model()).run(1, substeps=0), V, ["substeps", "got 0"]),
    ("run-frames", lambda c: ws.Simulator(model()).run(-2), V, ["frames", "-2"]),
    ("run-frames-str", lambda c: ws.Simulator(model()).run("ten"), V, ["frames", "'ten'"]),
    # ---- forces
    ("gravity-str", lambda c: ws.Gravity("down"), V, ["Gravity g", "'down'"]),
    ("gravity-scalar", lambda c: ws.Gravity(9.81), V, ["Gravity g", "9.81", "3 numbers"]),
    ("gravity-nan", lambda c: ws.Gravity((0, NAN, 0)), V, ["Gravity g", "finite"]),
    ("gravity-2d", lambda c: ws.Gravity((0, -9.81)), V, ["Gravity g", "3 components"]),
    ("constant-force-str", lambda c: ws.ConstantForce("push"), V, ["ConstantForce force", "'push'"]),
    ("constant-force-index", lambda c: ws.Simulator(model(), forces=[ws.ConstantForce((1, 0, 0), [0, 7])]), V,
     ["ConstantForce", "particle index 7", "out of range"]),
    ("constant-force-index-str",
     lambda c: ws.Simulator(model(), forces=[ws.ConstantForce((1, 0, 0), "all")]), V,
     ["ConstantForce", "'all'"]),
    ("constant-force-index-float",
     lambda c: ws.Simulator(model(), forces=[ws.ConstantForce((1, 0, 0), [0.5])]), V,
     ["ConstantForce", "integers", "0.5"]),
    ("wind-zero-dir", lambda c: ws.Wind(direction=(0, 0, 0)), V, ["Wind direction", "zero vector"]),
    ("wind-dir-str", lambda c: ws.Wind(direction="north"), V, ["Wind direction", "'north'"]),
    ("wind-speed-str", lambda c: ws.Wind(speed="fast"), V, ["Wind speed", "'fast'"]),
    ("wind-speed-nan", lambda c: ws.Wind(speed=NAN), V, ["Wind speed", "nan"]),
    ("wind-coefficient", lambda c: ws.Wind(coefficient=-1.0), V, ["Wind coefficient", "-1"]),
    ("wind-gust-inf", lambda c: ws.Wind(gust_frequency=INF), V, ["Wind gust_frequency", "inf"]),
    ("magnets-lengths", lambda c: ws.Magnets([(0, 0, 0), (1, 0, 0)], [1.0, 2.0, 3.0]), V,
     ["2 centers", "3 strengths", "one strength per center"]),
    ("magnets-lengths-short", lambda c: ws.Magnets([(0, 0, 0), (1, 0, 0), (2, 0, 0)], [1.0, 2.0]), V,
     ["3 centers", "2 strengths"]),
    ("magnets-strength-str", lambda c: ws.Magnets([(0, 0, 0)], "strong"), V,
     ["Magnets strengths", "'strong'"]),
    ("magnets-strength-nan", lambda c: ws.Magnets([(0, 0, 0), (1, 0, 0)], [1.0, NAN]), V,
     ["Magnets strengths", "strength 1", "nan"]),
    ("magnets-center-nan", lambda c: ws.Magnets([(0, 0, 0), (NAN, 0, 0)], 1.0), V,
     ["Magnets centers", "center 1", "not finite"]),
    ("magnets-center-shape", lambda c: ws.Magnets([(0, 0), (1, 0)], 1.0), V, ["Magnets centers", "(N, 3)"]),
    ("magnets-softening", lambda c: ws.Magnets([(0, 0, 0)], 1.0, softening=0.0), V,
     ["Magnets softening", "> 0"]),
    ("magnets-softening-str", lambda c: ws.Magnets([(0, 0, 0)], 1.0, softening="soft"), V,
     ["Magnets softening", "'soft'"]),
    ("magnets-cutoff", lambda c: ws.Magnets([(0, 0, 0)], 1.0, cutoff=-1.0), V, ["Magnets cutoff", "-1"]),
    ("drag-neg", lambda c: ws.Drag(linear=-1.0), V, ["Drag linear", "-1"]),
    ("drag-str", lambda c: ws.Drag(quadratic="q"), V, ["Drag quadratic", "'q'"]),
    ("drag-nan", lambda c: ws.Drag(linear=NAN), V, ["Drag linear", "nan"]),
    ("force-field-not-func", lambda c: ws.ForceField(lambda x, v, t: x), V, ["ForceField", "@wp.func"]),
    # ---- colliders
    ("plane-normal-zero", lambda c: ws.Plane(normal=(0, 0, 0)), V, ["Plane", "non-zero"]),
    ("plane-normal-str", lambda c: ws.Plane(normal="up"), V, ["Plane normal", "'up'"]),
    ("plane-offset-str", lambda c: ws.Plane(offset="ground"), V, ["Plane offset", "'ground'"]),
    ("plane-offset-nan", lambda c: ws.Plane(offset=NAN), V, ["Plane offset", "nan"]),
    ("plane-restitution-high", lambda c: ws.Plane(restitution=1.5), V, ["Plane restitution 1.5", "[0, 1]"]),
    ("plane-restitution-str", lambda c: ws.Plane(restitution="bouncy"), V, ["Plane restitution", "'bouncy'"]),
    ("plane-friction-neg", lambda c: ws.Plane(friction=-0.2), V, ["Plane friction -0.2"]),
    ("plane-friction-str", lambda c: ws.Plane(friction="rough"), V, ["Plane friction", "'rough'"]),
    ("plane-mode", lambda c: ws.Plane(mode="bounce"), V, ["Plane mode 'bounce'", "reflect"]),
    ("plane-thickness", lambda c: ws.Plane(thickness=-1.0), V, ["Plane thickness", "-1"]),
    ("plane-thickness-str", lambda c: ws.Plane(thickness="thin"), V, ["Plane thickness", "'thin'"]),
    ("plane-stiffness", lambda c: ws.Plane(stiffness=0.0), V, ["Plane stiffness", "> 0"]),
    ("planes-count", lambda c: ws.Planes([(0, 1, 0)], [0.0, 1.0]), V, ["1 normals", "2 offsets"]),
    ("planes-normal-nan", lambda c: ws.Planes([(0, 1, 0), (0, NAN, 0)], [0.0, 1.0]), V,
     ["Planes normals", "normal 1"]),
    ("box-order", lambda c: ws.Box(lower=(0, 0, 0), upper=(1, -1, 1)), V, ["Box upper", "lower"]),
    ("box-lower-str", lambda c: ws.Box(lower="min"), V, ["Box lower", "'min'"]),
    ("sphere-radius-zero", lambda c: ws.Sphere(radius=0.0), V, ["Sphere radius", "> 0"]),
    ("sphere-radius-str", lambda c: ws.Sphere(radius="big"), V, ["Sphere radius", "'big'"]),
    ("sphere-radius-nan", lambda c: ws.Sphere(radius=NAN), V, ["Sphere radius", "nan"]),
    ("sphere-center-nan", lambda c: ws.Sphere(center=(NAN, 0, 0)), V, ["Sphere center", "finite"]),
    ("sphere-restitution", lambda c: ws.Sphere(restitution=-0.5), V, ["Sphere restitution -0.5"]),
    ("capsule-radius", lambda c: ws.Capsule(radius=-1.0), V, ["Capsule radius", "-1"]),
    ("capsule-end-str", lambda c: ws.Capsule(a="top"), V, ["Capsule a", "'top'"]),
    ("quad-axis-zero", lambda c: ws.Quad(axis_u=(0, 0, 0)), V, ["Quad axis_u", "non-zero"]),
    ("quad-not-orthogonal", lambda c: ws.Quad(axis_u=(1, 0, 0), axis_v=(1, 0, 1)), V, ["Quad", "orthogonal"]),
    ("trimesh-face-range", lambda c: ws.TriangleMesh(CUBE_V, [(0, 1, 99)]), V, ["TriangleMesh", "99"]),
    ("trimesh-point-nan", lambda c: ws.TriangleMesh(np.vstack([CUBE_V[:7], [(NAN, 0, 0)]]), CUBE_F), V,
     ["TriangleMesh", "7"]),
    ("trimesh-solid-open", lambda c: ws.TriangleMesh(CUBE_V, CUBE_F[:-1], solid=True), V,
     ["TriangleMesh", "solid=True", "closed"]),
    ("particle-collisions-restitution", lambda c: ws.ParticleCollisions(restitution=2.0), V,
     ["ParticleCollisions restitution 2"]),
    ("particle-collisions-grid", lambda c: ws.ParticleCollisions(grid_dim=0), V,
     ["ParticleCollisions grid_dim"]),
    ("particle-collisions-grid-str", lambda c: ws.ParticleCollisions(grid_dim="big"), V,
     ["ParticleCollisions grid_dim", "'big'"]),
    # ---- soft bodies and meshes
    ("soft-point-nan", lambda c: ws.add_soft_body(ws.ModelBuilder(), np.vstack([CUBE_V[:7], [(0, NAN, 1)]]),
                                                   CUBE_F), V, ["soft body", "7"]),
    ("soft-face-range",
     lambda c: ws.add_soft_body(ws.ModelBuilder(), CUBE_V, np.vstack([CUBE_F, [(0, 1, 8)]])),
     V, ["soft body", "8"]),
    ("soft-scale-zero", lambda c: soft(scale=0.0), V, ["soft body scale"]),
    ("soft-scale-str", lambda c: soft(scale="big"), V, ["soft body scale", "'big'"]),
    ("soft-mass-neg", lambda c: soft(mass=-1.0), V, ["soft body mass", "-1"]),
    ("soft-total-mass-zero", lambda c: soft(total_mass=0.0), V, ["soft body total_mass"]),
    ("soft-stiffness-str", lambda c: soft(stiffness="stiff"), V, ["soft body stiffness", "'stiff'"]),
    ("soft-damping-neg", lambda c: soft(damping=-1.0), V, ["soft body damping", "-1"]),
    ("soft-lattice-zero", lambda c: soft(lattice_cells=0), V, ["soft body lattice_cells", "got 0"]),
    ("soft-lattice-str", lambda c: soft(lattice_cells="many"), V, ["soft body lattice_cells", "'many'"]),
    ("soft-ties-zero", lambda c: soft(ties=0), V, ["soft body ties", "got 0"]),
    ("soft-interior", lambda c: soft(interior="foam"), V, ["soft body interior 'foam'", "lattice"]),
    ("soft-mass-distribution", lambda c: soft(mass_distribution="volume"), V,
     ["soft body mass_distribution 'volume'"]),
    ("soft-fraction", lambda c: soft(interior_mass_fraction=1.0), V, ["soft body interior_mass_fraction"]),
    ("soft-velocity-str", lambda c: soft(velocity="up"), V, ["soft body velocity", "'up'"]),
    ("soft-open-lattice", lambda c: ws.add_soft_body(ws.ModelBuilder(), CUBE_V, CUBE_F[:-2]), V,
     ["soft body is not closed", "interior='none'"]),
    ("soft-flat-closed", lambda c: ws.add_soft_body(ws.ModelBuilder(), FLAT_V, FLAT_F), V,
     ["soft body", "encloses no volume", "interior='none'"]),
    ("soft-name-in-message", lambda c: ws.add_soft_body(ws.ModelBuilder(), FLAT_V, FLAT_F, name="pancake"), V,
     ["pancake", "encloses no volume"]),
    ("soft-non-manifold", lambda c: ws.add_soft_body(ws.ModelBuilder(), np.vstack([CUBE_V, [(0.5, -1, 0)]]),
                                                      np.vstack([CUBE_F, [(0, 1, 8)]]), interior="none"), V,
     ["soft body is non-manifold", "edge (0, 1)"]),
    ("soft-lattice-hint", lambda c: ws.add_soft_body(ws.ModelBuilder(), *ws.torus_mesh(0.1, 0.03, 24, 12),
                                                     lattice_cells=1), V,
     ["no lattice particle fits", "lattice_cells=1", "lattice_cells=4 fits one"]),
    ("mesh-missing", lambda c: ws.load_mesh(c["missing.obj"]), FNF,
     ["mesh file", "missing.obj", "does not exist"]),
    ("mesh-missing-is-valueerror", lambda c: ws.load_mesh(c["missing.obj"]), V, ["missing.obj"]),
    ("mesh-folder", lambda c: ws.load_mesh(c["folder.obj"]), V, ["folder.obj", "is a folder"]),
    ("mesh-nan-vertex", lambda c: ws.load_mesh(c["nan.obj"]), V, ["nan.obj", "vertex 3", "not finite"]),
    ("mesh-inf-vertex", lambda c: ws.load_mesh(c["inf.obj"]), V, ["inf.obj", "vertex 5", "inf"]),
    ("mesh-garbage-obj", lambda c: ws.load_mesh(c["garbage.obj"]), V, ["garbage.obj", "OBJ"]),
    ("mesh-empty-obj", lambda c: ws.load_mesh(c["empty.obj"]), V, ["empty.obj", "empty"]),
    ("mesh-no-faces", lambda c: ws.load_mesh(c["noface.obj"]), V, ["noface.obj", "no triangles"]),
    ("mesh-bad-index", lambda c: ws.load_mesh(c["badindex.obj"]), V, ["badindex.obj"]),
    ("mesh-garbage-stl", lambda c: ws.load_mesh(c["garbage.stl"]), V, ["garbage.stl"]),
    ("mesh-truncated-stl", lambda c: ws.load_mesh(c["truncated.stl"]), V, ["truncated.stl"]),
    ("mesh-garbage-ply", lambda c: ws.load_mesh(c["garbage.ply"]), V, ["garbage.ply", "PLY"]),
    ("mesh-garbage-glb", lambda c: ws.load_mesh(c["garbage.glb"]), V, ["garbage.glb", "GLB"]),
    ("mesh-garbage-off", lambda c: ws.load_mesh(c["garbage.off"]), V, ["garbage.off", "OFF"]),
    ("mesh-garbage-usd", lambda c: ws.load_mesh(c["garbage.usda"]), V, ["garbage.usda", "does not open"]),
    ("mesh-extension", lambda c: ws.load_mesh(c["mesh.xyz"]), V, ["mesh.xyz", "unknown extension", ".obj"]),
    ("mesh-weld-tolerance", lambda c: ws.load_mesh(c["flat.obj"], weld_tolerance=-1.0), V,
     ["weld_tolerance", "-1"]),
    ("meshtools-non-manifold", lambda c: meshtools.check_manifold(np.vstack([CUBE_F, [(0, 1, 3)]]), "box"), V,
     ["box is non-manifold", "edge (0, 1)"]),
    ("teapot-resolution", lambda c: ws.teapot_mesh("huge"), V, ["resolution", "'huge'"]),
    # ---- cloth
    ("cloth-resolution-zero", lambda c: ws.add_cloth_grid(ws.ModelBuilder(), resolution=(0, 4)), V,
     ["resolution"]),
    ("cloth-resolution-str", lambda c: ws.add_cloth_grid(ws.ModelBuilder(), resolution="fine"), V,
     ["resolution", "'fine'"]),
    ("cloth-size-neg", lambda c: ws.add_cloth_grid(ws.ModelBuilder(), size=(-1.0, 1.0)), V, ["size"]),
    ("cloth-density-neg", lambda c: ws.add_cloth_grid(ws.ModelBuilder(), density=-0.1), V, ["density"]),
    ("cloth-pin-range", lambda c: ws.add_cloth_grid(ws.ModelBuilder(), resolution=(2, 2), pin=[100]), V,
     ["pin"]),
    ("cloth-structural-neg", lambda c: ws.add_cloth_grid(ws.ModelBuilder(), structural=(-1.0, 1.0)), V,
     ["structural"]),
    ("cloth-mesh-faces", lambda c: ws.add_cloth_mesh(ws.ModelBuilder(), CUBE_V, [(0, 1, 50)]), V, ["50"]),
    ("cloth-implicit-newton", lambda c: ws.ClothImplicitEuler(newton_iterations=0), V, ["newton_iterations"]),
    ("cloth-implicit-solver", lambda c: ws.ClothImplicitEuler(linear_solver="lu"), V,
     ["linear_solver", "'lu'"]),
    ("cloth-semi-mode", lambda c: ws.ClothSemiImplicitEuler(mode="fast"), V, ["mode", "'fast'"]),
    # ---- integrators and the pendulum
    ("implicit-newton-zero", lambda c: ws.ImplicitEuler(newton_iterations=0), V, ["newton_iterations"]),
    ("implicit-newton-str", lambda c: ws.ImplicitEuler(newton_iterations="many"), V,
     ["newton_iterations", "'many'"]),
    ("implicit-cg-tol", lambda c: ws.ImplicitEuler(cg_tol=-1.0), V, ["cg_tol", "-1"]),
    ("implicit-solver", lambda c: ws.ImplicitEuler(linear_solver="lu"), V, ["linear_solver 'lu'"]),
    ("pendulum-length-zero", lambda c: ws.Pendulum(1.0, length=0.0, device="cpu"), V, ["length"]),
    ("pendulum-length-str", lambda c: ws.Pendulum(1.0, length="long", device="cpu"), V, ["length", "'long'"]),
    ("pendulum-angle-nan", lambda c: ws.Pendulum(NAN, device="cpu"), V, ["angle"]),
    ("pendulum-angle-str", lambda c: ws.Pendulum("steep", device="cpu"), V, ["angle", "'steep'"]),
    ("pendulum-mass-neg", lambda c: ws.Pendulum(1.0, mass=-1.0, device="cpu"), V, ["mass"]),
    ("pendulum-integrator", lambda c: ws.Pendulum(1.0, integrator="verlet", device="cpu"), V, ["'verlet'"]),
    ("exact-period-length", lambda c: ws.exact_period(1.0, length=-1.0), V, ["length"]),
    # ---- marching cubes and fields
    ("mc-nan-node", lambda c: ws.marching_cubes(field_with(NAN), device="cpu"), V,
     ["field node [3, 4, 2]", "nan", "finite"]),
    ("mc-inf-node", lambda c: ws.marching_cubes(field_with(INF), device="cpu"), V,
     ["field node [3, 4, 2]", "inf"]),
    ("mc-nan-node-device", lambda c: ws.marching_cubes(wp.array(field_with(NAN, (1, 2, 3)), device="cpu")), V,
     ["field node [1, 2, 3]"]),
    ("mc-all-nan", lambda c: ws.marching_cubes(np.full((3, 3, 3), NAN, np.float32), device="cpu"), V,
     ["field node [0, 0, 0]", "27 of 27"]),
    ("mc-2d", lambda c: ws.marching_cubes(np.zeros((4, 4)), device="cpu"), V, ["field", "3D"]),
    ("mc-thin", lambda c: ws.marching_cubes(np.zeros((4, 1, 4)), device="cpu"), V,
     ["field shape", "2 nodes"]),
    ("mc-spacing", lambda c: ws.marching_cubes(sphere_field(), spacing=0.0, device="cpu"), V, ["spacing"]),
    ("mc-spacing-str", lambda c: ws.marching_cubes(sphere_field(), spacing="fine", device="cpu"), V,
     ["spacing", "'fine'"]),
    ("mc-iso-nan", lambda c: ws.marching_cubes(sphere_field(), iso=NAN, device="cpu"), V, ["iso"]),
    ("mc-iso-str", lambda c: ws.marching_cubes(sphere_field(), iso="half", device="cpu"), V,
     ["iso", "'half'"]),
    ("mc-origin", lambda c: ws.marching_cubes(sphere_field(), origin=(0, 0), device="cpu"), V, ["origin"]),
    ("mc-inside", lambda c: ws.marching_cubes(sphere_field(), inside="outside", device="cpu"), V, ["inside"]),
    ("mc-dtype", lambda c: ws.marching_cubes(np.array([["a"] * 3] * 3 * 3).reshape(3, 3, 3), device="cpu"), V,
     ["field", "real numbers"]),
    ("mc-capacity", lambda c: ws.MarchingCubes((4, 4, 4), device="cpu", max_vertices=-1), V,
     ["max_vertices"]),
    ("mc-block", lambda c: ws.MarchingCubes((4, 4, 4), device="cpu", block_size=0), V, ["block_size"]),
    ("mc-shape-mismatch", lambda c: ws.MarchingCubes((4, 4, 4), device="cpu").mesh(sphere_field()), V,
     ["field shape", "(8, 8, 8)", "(4, 4, 4)"]),
    ("metaballs-resolution", lambda c: ws.Metaballs(resolution=2, device="cpu"), V, ["metaballs resolution"]),
    ("metaballs-count", lambda c: ws.Metaballs(blob_count=0, device="cpu"), V, ["blob"]),
    ("metaballs-radius", lambda c: ws.Metaballs(radius=0.0, device="cpu"), V, ["radius"]),
    # ---- agents
    ("terrain-kind-number", lambda c: ws.Terrain(5), V, ["Terrain kind 5", "Terrain.flat"]),
    ("terrain-kind-name", lambda c: ws.Terrain("mountain"), V, ["Terrain kind 'mountain'", "'heights'"]),
    ("terrain-kind-bool", lambda c: ws.Terrain(True), V, ["Terrain kind True"]),
    ("terrain-height-str", lambda c: ws.Terrain(0, height="high"), V, ["Terrain height", "'high'"]),
    ("terrain-height-nan", lambda c: ws.Terrain("flat", height=NAN), V, ["Terrain height", "nan"]),
    ("terrain-spacing-zero", lambda c: ws.Terrain("flat", spacing=0.0), V, ["Terrain spacing", "got 0"]),
    ("terrain-origin-str", lambda c: ws.Terrain("flat", origin="centre"), V, ["Terrain origin"]),
    ("terrain-heights-missing", lambda c: ws.Terrain("heights"), V, ["needs heights="]),
    ("terrain-heights-1d", lambda c: ws.Terrain(1, heights=[0.0, 1.0]), V, ["terrain heights", "2-D"]),
    ("terrain-heights-nan", lambda c: ws.Terrain(1, heights=[[0, 1], [1, NAN]]), V,
     ["terrain heights[1, 1]"]),
    ("terrain-mesh-missing", lambda c: ws.Terrain("mesh", points=CUBE_V), V, ["needs points= and faces="]),
    ("terrain-mesh-index", lambda c: ws.Terrain(2, points=CUBE_V, faces=[(0, 1, 8)]), V,
     ["terrain mesh triangle 0", "[0, 8)"]),
    ("terrain-flat-str", lambda c: ws.Terrain.flat("sea level"), V, ["terrain height", "'sea level'"]),
    ("terrain-from-heights-spacing", lambda c: ws.Terrain.from_heights([[0, 1], [1, 2]], -1.0), V,
     ["Terrain spacing", "-1"]),
    ("terrain-from-function-spacing",
     lambda c: ws.Terrain.from_function(lambda x, z: x, (0, 0), (1, 1), "s"), V,
     ["terrain spacing", "'s'"]),
    ("flock-positions-nan", lambda c: ws.Flock([(0, 0, 0), (NAN, 0, 0)], device="cpu"), V,
     ["positions", "1"]),
    ("flock-empty", lambda c: ws.Flock(np.zeros((0, 3)), device="cpu"), V, ["positions", "empty"]),
    ("flock-params-type", lambda c: ws.Flock([(0, 0, 0)], params=["fast"], device="cpu"), V, ["params[0]"]),
    ("flock-species-range", lambda c: ws.Flock([(0, 0, 0), (1, 0, 0)], species=[0, 3], device="cpu"), V,
     ["species[1]"]),
    ("flock-food-type", lambda c: ws.Flock([(0, 0, 0)], food=[(0, 0, 0)], device="cpu"), V, ["food"]),
    ("boid-max-speed", lambda c: ws.Flock([(0, 0, 0)], params=ws.BoidParams(max_speed=-1.0), device="cpu"), V,
     ["max_speed"]),
    ("walker-max-speed", lambda c: ws.Crowd([(0, 0, 0)], [(1, 0, 1)], params=ws.WalkerParams(max_speed=0.0),
                                            device="cpu"), V, ["max_speed"]),
    ("crowd-goals-count", lambda c: ws.Crowd([(0, 0, 0), (1, 0, 0)], [(1, 0, 1)] * 3, device="cpu"), V,
     ["goals"]),
    ("food-lengths", lambda c: ws.FoodSources([(0, 0, 0), (1, 0, 0)], [1.0]), V, ["amounts"]),
    # ---- grid and particle fluids
    ("mac-shape-zero", lambda c: mac(shape=(0, 4, 4)), V, ["shape"]),
    ("mac-shape-str", lambda c: mac(shape="cube"), V, ["shape", "'cube'"]),
    ("mac-dx-zero", lambda c: mac(dx=0.0), V, ["dx"]),
    ("mac-dx-str", lambda c: mac(dx="small"), V, ["dx", "'small'"]),
    ("mac-open-sides", lambda c: mac(open_sides=("top",)), V, ["open_sides", "'top'", "+y"]),
    ("pressure-tol", lambda c: ws.PressureSolver(mac(), tol=-1.0), V, ["tol"]),
    ("pressure-preconditioner", lambda c: ws.PressureSolver(mac(), preconditioner="ilu"), V,
     ["preconditioner", "'ilu'"]),
    ("advector-scheme", lambda c: ws.Advector(mac(), scheme="upwind"), V, ["scheme", "'upwind'"]),
    ("viscosity-nu", lambda c: ws.Viscosity(mac(), nu=-1.0), V, ["nu"]),
    ("fluid-positions-nan",
     lambda c: ws.ParticleFluid([(0, 0, 0), (0, NAN, 0)], spacing=0.1, device="cpu"), V,
     ["positions", "1"]),
    ("fluid-spacing-zero", lambda c: ws.ParticleFluid([(0, 0, 0)], spacing=0.0, device="cpu"), V,
     ["spacing"]),
    ("fluid-spacing-str", lambda c: ws.ParticleFluid([(0, 0, 0)], spacing="fine", device="cpu"), V,
     ["spacing", "'fine'"]),
    ("fluid-density",
     lambda c: ws.ParticleFluid([(0, 0, 0)], spacing=0.1, rest_density=-1.0, device="cpu"), V,
     ["rest_density"]),
    ("fluid-kernel", lambda c: ws.ParticleFluid([(0, 0, 0)], spacing=0.1, kernel="gauss", device="cpu"), V,
     ["kernel", "'gauss'"]),
    ("fluid-iterations", lambda c: ws.ParticleFluid([(0, 0, 0)], spacing=0.1, iterations=0, device="cpu"), V,
     ["iterations"]),
    ("fluid-max-speed", lambda c: ws.ParticleFluid([(0, 0, 0)], spacing=0.1, max_speed=0.0, device="cpu"), V,
     ["max_speed"]),
    ("fluid-velocities-count", lambda c: ws.ParticleFluid([(0, 0, 0)], np.zeros((2, 3)), spacing=0.1,
                                                          device="cpu"), V, ["velocities"]),
    ("nozzle-radius", lambda c: ws.Nozzle((0, 1, 0), radius=0.0), V, ["Nozzle radius"]),
    ("nozzle-direction", lambda c: ws.Nozzle((0, 1, 0), direction=(0, 0, 0)), V, ["Nozzle direction"]),
    ("nozzle-center-str", lambda c: ws.Nozzle("top"), V, ["Nozzle center", "'top'"]),
    ("sink-order", lambda c: ws.Sink((0, 0, 0), (1, -1, 1)), V, ["Sink"]),
    ("fluid-block-spacing", lambda c: ws.fluid_block((0, 0, 0), (1, 1, 1), 0.0), V, ["spacing"]),
    ("fluid-block-order", lambda c: ws.fluid_block((0, 0, 0), (-1, 1, 1), 0.1), V, ["upper"]),
    # ---- the validator itself
    ("checks-finite-str", lambda c: checks.finite("x", "widget size", "m"), V, ["widget size", "'x'", "[m]"]),
    ("checks-positive-zero", lambda c: checks.positive(0, "widget size"), V, ["widget size", "> 0", "got 0"]),
    ("checks-count-bool", lambda c: checks.count(True, "widget count"), V, ["widget count", "True"]),
    ("checks-count-float", lambda c: checks.count(2.5, "widget count"), V, ["widget count", "2.5"]),
    ("checks-vec3-len", lambda c: checks.vec3((1, 2), "widget axis"), V, ["widget axis", "3 components"]),
    ("checks-vec3-zero", lambda c: checks.vec3((0, 0, 0), "widget axis", nonzero=True), V,
     ["widget axis", "zero vector"]),
    ("checks-vectors-row",
     lambda c: checks.vectors([(0, 0, 0), (1, INF, 0)], "widget points", item="point"), V,
     ["widget points", "point 1", "inf"]),
    ("checks-same-length", lambda c: checks.same_length(centers=[1, 2], strengths=[1]), V,
     ["centers has 2", "strengths has 1"]),
    ("checks-sequence-single",
     lambda c: checks.sequence_of(ws.Gravity(), "forces", ws.Force, "forces=[...]"), V,
     ["forces must be a list", "Gravity"]),
    ("checks-choice", lambda c: checks.choice("rk5", "integrator", ("rk2", "rk4")), V,
     ["integrator 'rk5'", "did you mean"]),
    ("checks-mesh-vertices", lambda c: checks.mesh_vertices([(0, 0, 0), (NAN, 0, 0)], "bunny"), V,
     ["bunny vertices", "vertex 1"]),
    ("checks-missing-file", lambda c: checks.existing_file(c["missing.obj"], "scene file"), FNF,
     ["scene file", "missing.obj"]),
]


@pytest.mark.parametrize("case_id, call, exc_type, words", CASES, ids=[c[0] for c in CASES])
def test_bad_input_is_a_clear_error(ctx, case_id, call, exc_type, words):
    with pytest.raises(exc_type) as info:
        call(ctx)
    message = str(info.value)
    for word in words:
        assert word in message, f"{case_id}: {word!r} not in {message!r}"
    assert "could not convert" not in message and "\n" not in message, message


def test_probe_size_and_ids_unique():
    ids = [c[0] for c in CASES]
    assert len(ids) == len(set(ids))
    assert len(CASES) >= 180


def test_fixed_cases_still_work(ctx):
    """The other side of the probe: inputs next to the rejected ones are accepted, and the
    repaired paths give the right result."""
    latin1 = ctx["dir"] / "latin1.obj"  # a comment in Latin-1: loaded with charset-normalizer installed
    latin1.write_bytes(obj_bytes(CUBE_V, CUBE_F, b"# mod\xe8le caf\xe9\n"))
    points, faces = ws.load_mesh(latin1)
    assert points.shape == (8, 3) and faces.shape == (12, 3)
    assert meshtools.signed_volume(points, faces) == pytest.approx(1.0)
    body = ws.add_soft_body(ws.ModelBuilder(), points, faces, lattice_cells=2)
    assert body.interior_count > 0
    b = coincident()
    assert b.add_spring(0, 1, 10.0) == 0 and b.spring_rest_length[0] == 0.0  # zero rest length: fine
    ws.Magnets([(0, 0, 0), (1, 0, 0)], 2.0)  # one strength for all centres
    ws.Simulator(model(), forces=(ws.Gravity(),), colliders=(ws.Plane(),), max_speed=5.0)
    assert ws.Terrain("heights", heights=[[0.0, 1.0], [1.0, 2.0]], spacing=0.5).kind == 1
    v, f, _ = ws.marching_cubes(sphere_field(24), spacing=2 / 23, origin=(-1, -1, -1), device="cpu").numpy()
    assert len(f) > 0 and np.isfinite(v).all()
    assert meshtools.signed_volume(v, f) == pytest.approx(4 / 3 * np.pi * 0.5**3, rel=0.03)
