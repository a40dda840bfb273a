"""Scene ``teapot``: the lecture's jiggly Utah teapot, a mass-spring soft body dropped into a
box of walls, with an optional obstacle and scripted drags."""
from __future__ import annotations

import math
from typing import ClassVar

import numpy as np

import warpsim as ws

from ..bodies.colliders import Capsule, Quad, Sphere, TriangleMesh
from ..bodies.drag import parse_drag_spec, scripted_drag
from ..bodies.softbody import add_soft_body
from ..bodies.teapot import resolve_resolution, teapot_mesh
from . import CONTAINER, SimulatorScene, add_floor, register_scene
from .live import set_contact, set_gravity, set_springs

ANCHORS = ("spout", "handle", "knob", "bottom")


def anchor_vertex(points, who: str) -> int:
    """Surface vertex for a named anchor: spout tip (largest x), handle (smallest x), knob
    (highest), bottom (lowest, nearest the axis), or a vertex index given as text. ``points``:
    (N, 3) [m], the teapot as modelled (y up, axis at x = z = 0, before the scene's tilt: on the
    tilted teapot the spout's tip is higher than the knob)."""
    p = np.asarray(points)
    if who == "spout":
        return int(np.argmax(p[:, 0]))
    if who == "handle":
        return int(np.argmin(p[:, 0]))
    if who == "knob":
        return int(np.argmax(p[:, 1]))
    if who == "bottom":
        return int(np.argmin(p[:, 1] * 1e3 + np.hypot(p[:, 0], p[:, 2])))
    try:
        index = int(who)
    except ValueError:
        raise ValueError(f"drag target {who!r} is not a vertex index or one of {', '.join(ANCHORS)}") from None
    if not 0 <= index < len(p):
        raise ValueError(f"drag vertex {index} is out of range [0, {len(p)}) for this teapot resolution")
    return index


TEAPOT_PAIR_BYTES = 110.0
"""Bytes of the winding-number test that places the interior lattice, per triangle and query
point of a chunk of at most 256 (measured while building on the CPU: 98 at resolution 12, 102 at
24, where it is nearly all of the 231 MB and 967 MB taken)."""
TEAPOT_TRIANGLE_BYTES = 600.0
"""Bytes a surface triangle takes besides that test (vertices, edge and bending springs)."""
TEAPOT_CELL_BYTES = 7000.0
"""Bytes a candidate lattice cell takes while building (its distance tests, lattice and tie
springs; measured: 134 MB for lattice_cells=40, 20,000 candidate cells)."""
TEAPOT_SHAPE = (1.0, 0.49, 0.62)
"""The teapot's bounding box over its longest side (length, height, depth)."""


def check_teapot_memory(resolution, lattice_cells, available=None):
    """Refuse (ValueError naming ``resolution`` or ``lattice_cells``, the estimate and the value
    that fits) a teapot whose surface or interior lattice cannot be built in memory, before the
    mesh is made; returns the estimated bytes."""
    from ..core.memory import available_host_bytes, check_build_memory

    n = resolve_resolution(resolution)
    cells = int(lattice_cells)
    if cells < 1:
        raise ValueError(f"lattice_cells={lattice_cells}: it must be >= 1 (interior cells along the length)")
    faces = 64 * n * n  # 32 patches of n x n quads, two triangles each
    candidates = 1
    for ratio in TEAPOT_SHAPE:
        candidates *= max(1, math.ceil(ratio * cells))
    available = available_host_bytes() if available is None else int(available)
    need = check_build_memory("resolution", resolution, faces, "triangles",
                              TEAPOT_PAIR_BYTES * min(candidates, 256) + TEAPOT_TRIANGLE_BYTES,
                              lambda k: max(2, int((k / 64) ** 0.5)), available=available)
    return need + check_build_memory("lattice_cells", cells, candidates, "candidate lattice cells", TEAPOT_CELL_BYTES,
                                     lambda k: max(1, int((k / math.prod(TEAPOT_SHAPE)) ** (1 / 3))),
                                     available=max(0, available - need))


@register_scene("teapot", "the jiggly Utah teapot: a mass-spring soft body bouncing in a box of walls", params={
    "resolution": ("low", ("teapot tessellation: low (4 segments per patch edge), high (12; needs dt <= 1e-4 "
                           "with semi-implicit Euler) or an integer >= 2")),
    "size": (0.1, "teapot scale [m per data unit] (0.1: 0.65 m long, 0.315 m tall)"),
    "mass": (1.0, "total mass [kg], equal on every surface vertex (a quarter on the interior lattice)"),
    "stiffness": (40.0, "spring stiffness [N/m] (edges, bending, interior)"),
    "damping": (0.05, "spring damping [N s/m]"),
    "lattice_cells": (6, "interior lattice cells along the teapot's length (shape-keeping springs)"),
    "restitution": (0.5, "wall restitution in [0, 1]"),
    "friction": (0.3, "wall Coulomb friction"),
    "collision": ("reflect", "wall handling: reflect (at the time of impact), project, penalty or seed (the lecture's "
                            "mirror, which gains energy at large steps)", ("reflect", "project", "penalty", "seed")),
    "wall_stiffness": (300.0, "penalty spring stiffness of the walls [N/m] (collision=penalty)"),
    "box": (0.7, "half width of the box of walls [m] (height 2 x box)"),
    "height": (0.6, "drop height of the teapot's bottom [m]"),
    "velocity": ((1.0, 0.0, 0.6), "initial velocity [m/s]"),
    "tilt": (20.0, "initial tilt about the z axis [degrees]"),
    "gravity": (9.81, "gravitational acceleration [m/s^2]"),
    "obstacle": ("none", "an extra collider on the floor", ("none", "sphere", "capsule", "ramp", "paddle")),
    "drag": ("", "scripted drags WHO:X,Y,Z[>X,Y,Z...]@T0-T1[;...], WHO a vertex index or spout/handle/knob/bottom"),
    "drag_stiffness": (2.0, "drag spring stiffness [N/m]"),
    "drag_damping": (0.2, "drag spring damping [N s/m]"),
    "springs": (True, "write the springs as curves"),
    "dt": (1.0 / 600.0, "time step [s]"),
    "integrator": ("semi_implicit_euler", "time integrator", tuple(sorted(ws.INTEGRATORS))),
}, substeps=10)
class TeapotScene(SimulatorScene):
    """Prims: ``teapot`` (Mesh, fixed topology), ``springs`` (BasisCurves, optional),
    ``walls`` (the box), ``obstacle`` (static geometry or, for the paddle, a mesh moved every
    frame) and ``drag`` (a two-point curve from the dragged vertex to its target)."""

    smoke_params: ClassVar[dict] = {"resolution": "3", "drag": "spout:0.3,0.6,0@0-0.05", "obstacle": "paddle"}
    substeps_auto = True  # dt = 1/600 s sits at the limit (stiffness 40 N/m); stiffer or lighter blows up
    track_anchors = ANCHORS  # warpsim sweep --track spout (the spout tip's vertex)

    def anchor_particle(self, name) -> int:
        """The surface vertex of anchor ``name`` (``spout``, ``handle``, ``knob``, ``bottom``)."""
        return anchor_vertex(self.rest_points, name)

    def build(self, p):
        for key in ("mass", "size", "box", "gravity"):
            if not p[key] > 0:
                raise ValueError(f"{key}={p[key]}: it must be > 0")
        for key in ("stiffness", "damping", "drag_stiffness", "drag_damping"):
            if not p[key] >= 0:
                raise ValueError(f"{key}={p[key]}: it must be >= 0")
        check_teapot_memory(p["resolution"], p["lattice_cells"])
        mesh = teapot_mesh(p["resolution"], scale=p["size"])
        self.rest_points = mesh.points  # the surface vertices untilted: where the anchors are named
        b = ws.ModelBuilder()
        tilt = math.radians(p["tilt"])
        rotation = (0.0, 0.0, math.sin(tilt / 2), math.cos(tilt / 2))
        self.body = add_soft_body(
            b, mesh.points, mesh.faces, position=(0.0, p["height"], 0.0), rotation=rotation,
            velocity=p["velocity"], total_mass=p["mass"], mass_distribution="uniform", stiffness=p["stiffness"], damping=p["damping"],
            lattice_cells=p["lattice_cells"], name="teapot")
        self.model = b.finalize(self.device)
        q0 = self.model.particle_q.numpy()
        half = p["box"]
        self.lower, self.upper = (-half, 0.0, -half), (half, 2.0 * half, half)
        if np.any(q0 < np.array(self.lower)) or np.any(q0 > np.array(self.upper)):
            raise ValueError(f"the teapot does not fit in the box at height={p['height']}: raise box or lower height")
        kw = {"restitution": p["restitution"], "friction": p["friction"], "mode": p["collision"],
              "stiffness": p["wall_stiffness"]}
        colliders = [ws.Box(self.lower, self.upper, **kw)]
        self.obstacle = self._obstacle(p["obstacle"], half, kw)
        if self.obstacle is not None:
            colliders.append(self.obstacle)
        forces = [ws.Gravity((0.0, -p["gravity"], 0.0))]
        self.drags, self.drag_vertices = [], []
        for who, points, t0, t1 in parse_drag_spec(p["drag"]):
            vertex = anchor_vertex(self.rest_points, who)
            self.drags.append(scripted_drag(vertex, points, t0, t1, p["drag_stiffness"], p["drag_damping"]))
            self.drag_vertices.append(vertex)
        # a teapot dropped from a metre moves at a few m/s; 100 m/s means it has blown up (the walls
        # would otherwise keep an exploded teapot bouncing inside the box)
        self.sim = ws.Simulator(self.model, integrator=p["integrator"], forces=forces + self.drags,
                                colliders=colliders, max_speed=100.0)

    def _obstacle(self, kind, half, kw):
        if kind == "sphere":
            return Sphere((0.3 * half, 0.0, 0.0), 0.3 * half, **kw)
        if kind == "capsule":
            return Capsule((-0.6 * half, 0.1 * half, 0.4 * half), (0.6 * half, 0.1 * half, -0.4 * half), 0.1 * half, **kw)
        if kind == "ramp":
            pts = np.array([[half, 0.0, -half], [0.0, 0.0, -half], [0.0, 0.0, half], [half, 0.0, half],
                            [half, 0.4 * half, -half], [half, 0.4 * half, half]])  # a wedge rising to +x
            faces = np.array([[0, 1, 4], [1, 2, 5], [1, 5, 4], [2, 3, 5], [0, 4, 5], [0, 5, 3], [0, 3, 2], [0, 2, 1]])
            return TriangleMesh(pts, faces, solid=True, **kw)
        if kind == "paddle":
            def sweep(t):
                angle = 0.8 * math.sin(2.0 * t)
                return (0.0, 0.0, 0.0), (0.0, math.sin(angle / 2), 0.0, math.cos(angle / 2))

            return Quad((0.0, 0.15 * half, 0.0), (0.9 * half, 0.0, 0.0), (0.0, 0.15 * half, 0.0), motion=sweep, **kw)
        return None

    # ------------------------------------------------------------------ live parameters, dragging
    live_params = ("restitution", "friction", "wall_stiffness", "stiffness", "damping", "gravity",
                   "drag_stiffness", "drag_damping")

    def apply_param(self, key, value):
        if key in ("restitution", "friction", "wall_stiffness"):
            set_contact(self.sim.colliders, **{"stiffness" if key == "wall_stiffness" else key: value})
        elif key in ("stiffness", "damping"):  # every spring of the body shares them
            set_springs(self.model, key, value)
        elif key == "gravity":
            set_gravity(self.sim.forces, value)
        else:
            if not value >= 0:
                raise ValueError(f"{key}={value}: it must be >= 0")
            for d in self.drags:
                setattr(d, key.split("_", 1)[1], float(value))

    def drag_map(self):
        return {"teapot": None}  # surface vertex i is particle i

    # ------------------------------------------------------------------ output
    def declare(self, writer):
        faces = self.body.faces - self.body.particle_start
        writer.add_mesh("teapot", np.full(len(faces), 3), faces.reshape(-1), color=(0.85, 0.85, 0.9))
        if self.params["springs"]:
            writer.add_curves("springs", self.model.spring_indices.numpy(), width=0.001, color=(0.3, 0.3, 0.3))
        writer.add_box("walls", self.lower, self.upper, **CONTAINER)
        add_floor(writer, self.lower, self.upper)
        ob = self.obstacle
        if isinstance(ob, Sphere):
            writer.add_sphere("obstacle", tuple(ob.center), ob.radius)
        elif isinstance(ob, Capsule):
            writer.add_static_mesh("obstacle", *_capsule_mesh(ob.a, ob.b, ob.radius))
        elif isinstance(ob, TriangleMesh):
            writer.add_static_mesh("obstacle", ob.world_points(), np.full(len(ob.faces), 3), ob.faces.reshape(-1))
        elif isinstance(ob, Quad):
            writer.add_mesh("obstacle", [4], [0, 1, 2, 3], velocities=False, double_sided=True)
        if self.drags:
            writer.add_curves("drag", curve_vertex_counts=[2] * len(self.drags), width=0.004, color=(0.9, 0.2, 0.1))

    def _described(self):
        from ..usd.frame_arrays import Particles, Shared

        n = self.body.surface_count
        data = {"teapot": {"points": Particles("positions", slice(0, n)),
                           "velocities": Particles("velocities", slice(0, n))}}
        if self.params["springs"]:
            data["springs"] = {"points": Particles("positions", slice(None))}
        if isinstance(self.obstacle, Quad):
            data["obstacle"] = {"points": Shared(self.obstacle.corners)}
        return data

    def frame_arrays(self):
        """The teapot's surface and springs from the particle arrays, a moving quad's corners
        shared by every world; None with drags (their lines end at targets on the simulator's
        clock: a batch asks each world in turn)."""
        return None if self.drags else self._described()

    def frame_data(self):
        from ..usd.frame_arrays import frame_data_from

        state = self.sim.state
        data = frame_data_from(self._described(), state.positions, state.velocities)
        if self.drags:
            x = state.positions.numpy()
            segs = []
            for drag, p in zip(self.drags, self.drag_vertices):
                end = drag.target_at(self.sim.time) if drag.active_at(self.sim.time) else x[p]
                segs += [x[p], end]
            data["drag"] = {"points": np.array(segs)}
        return data

    def checkpoint(self):
        data = super().checkpoint()
        if self.obstacle is not None and hasattr(self.obstacle, "clock"):
            data["obstacle_clock"] = np.float64(self.obstacle.clock)
        return data

    def restore(self, data):
        super().restore(data)
        if "obstacle_clock" in data and self.obstacle is not None:
            self.obstacle.set_clock(float(data["obstacle_clock"]))


def _capsule_mesh(a, b, radius, segments=16, rings=8):
    """A capsule surface as quads and triangles for USD: (points, counts, indices)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    axis = b - a
    length = np.linalg.norm(axis)
    w = axis / length if length > 0 else np.array([0.0, 1.0, 0.0])
    helper = np.array([1.0, 0.0, 0.0]) if abs(w[0]) < 0.9 else np.array([0.0, 0.0, 1.0])
    u = np.cross(w, helper)
    u /= np.linalg.norm(u)
    v = np.cross(w, u)
    rows = []
    for k in range(rings + 1):  # hemisphere at a (phi from -pi/2 to 0), then at b (0 to pi/2)
        phi = -0.5 * math.pi + 0.5 * math.pi * k / rings
        rows.append((a, phi))
    for k in range(rings + 1):
        rows.append((b, 0.5 * math.pi * k / rings))
    pts = []
    for c, phi in rows:
        for s in range(segments):
            th = 2.0 * math.pi * s / segments
            pts.append(c + radius * (math.cos(phi) * (math.cos(th) * u + math.sin(th) * v) + math.sin(phi) * w))
    idx = []
    for r in range(len(rows) - 1):
        for s in range(segments):
            i0, i1 = r * segments + s, r * segments + (s + 1) % segments
            idx += [i0, i1, i1 + segments, i0 + segments]
    return np.array(pts), [4] * (len(idx) // 4), idx
