"""The mass-spring lecture's opening video: a brittle wall that fractures (``wall``) and a heap of
soft tori (``donuts``).

``wall``: a brick wall built as one particle lattice (spacing ``spacing``); the nodes of each
brick are joined by strong springs, nodes of neighbouring bricks by weak "mortar" springs that
break past ``mortar_strength`` [N] of tension (``warpsim.core.fracture``). Rows are laid in
running bond (every other row shifted by half a brick) on a foundation (the bottom layer is
pinned unless ``anchored=false``). A heavy ball (a stiff lattice of particles inside ``ball_radius``) flies at
it with ``ball_speed``: slow balls bounce off, fast ones knock out pieces that fall and collide
with the floor and each other (``ws.ParticleCollisions``). Prims: ``wall`` (points), ``ball``
(points), ``springs`` (curves, every spring; a broken spring collapses to zero length, primvar
``broken`` per curve, custom ``warpsim:brokenCount`` and ``warpsim:brokenThisFrame``), ``floor``.

``donuts``: ``count`` soft tori (``ws.torus_mesh`` + ``ws.add_soft_body``, surface springs and
an interior lattice) dropped in layers into a box; ``ws.SoftContact`` keeps them apart
(vertices against the other tori's triangles) so they pile up and come to rest. Prims:
``donuts`` (one mesh, all tori; custom ``warpsim:kineticEnergy`` [J]) and ``walls`` (the box).
"""
from __future__ import annotations

import math
from typing import ClassVar

import numpy as np

import warpsim as ws

from ..bodies.shapes import torus_mesh
from ..bodies.soft_contact import SoftContact
from ..bodies.softbody import add_soft_body
from ..core.fracture import spring_segments
from . import CONTAINER, SimulatorScene, add_floor, register_scene

INTEGRATORS = tuple(sorted(ws.INTEGRATORS))


def _positive(p, *keys):
    for key in keys:
        value = p[key]
        if isinstance(value, tuple):
            if not all(v > 0 for v in value):
                raise ValueError(f"{key}={','.join(f'{v:g}' for v in value)}: every component must be > 0")
        elif not value > 0:
            raise ValueError(f"{key}={value}: it must be > 0")


class BrickWall:
    """A brick wall lattice added to a ModelBuilder (see module docstring).

    ``bricks`` (columns, rows); ``brick_nodes`` (nx, ny, nz) lattice nodes per brick; ``spacing``
    [m]; the wall spans x in [0, columns nx spacing), y from ``spacing / 2`` up, z in
    [0, nz spacing). After construction: ``nodes`` (particle indices), ``brick_of`` (brick id per
    node), ``brick_springs`` / ``mortar_springs`` (spring indices), ``pinned`` (node indices)."""

    def __init__(self, builder, bricks=(4, 4), brick_nodes=(4, 2, 2), spacing=0.05, density=2000.0,
                 brick_stiffness=2.0e4, mortar_stiffness=5.0e3, damping=2.0, mortar_strength=60.0,
                 anchored=True, origin=(0.0, 0.0, 0.0)):
        columns, rows = (int(b) for b in bricks)
        nx, ny, nz = (int(n) for n in brick_nodes)
        if columns < 1 or rows < 1 or min(nx, ny, nz) < 1:
            raise ValueError(f"bricks={bricks}, brick_nodes={brick_nodes}: every count must be >= 1")
        h = float(spacing)
        gx, gy, gz = columns * nx, rows * ny, nz
        ijk = np.stack(np.meshgrid(np.arange(gx), np.arange(gy), np.arange(gz), indexing="ij"), -1).reshape(-1, 3)
        row = ijk[:, 1] // ny
        shift = (row % 2) * (nx // 2)  # running bond
        column = (ijk[:, 0] + shift) // nx
        self.brick_of = row * (columns + 1) + column
        positions = np.asarray(origin, float) + (ijk + [0.5, 0.5, 0.5]) * h
        mass = density * h ** 3
        self.pinned = np.flatnonzero(ijk[:, 1] == 0) if anchored else np.zeros(0, dtype=np.int64)
        masses = np.full(len(ijk), mass)
        masses[self.pinned] = 0.0
        self.radius = 0.45 * h
        self.nodes = builder.add_particles(positions, masses=masses, radii=self.radius)
        self.pinned = self.nodes[self.pinned]
        index = -np.ones((gx, gy, gz), dtype=np.int64)
        index[tuple(ijk.T)] = np.arange(len(ijk))
        brick, mortar = [], []
        offsets = [(a, b, c) for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1) if (a, b, c) > (0, 0, 0)]
        for off in offsets:
            nb = ijk + off
            ok = np.all((nb >= 0) & (nb < [gx, gy, gz]), axis=1)
            a = np.flatnonzero(ok)
            b = index[tuple(nb[ok].T)]
            both_pinned = (masses[a] == 0.0) & (masses[b] == 0.0)
            a, b = a[~both_pinned], b[~both_pinned]
            same = self.brick_of[a] == self.brick_of[b]
            for i, j in zip(a[same], b[same]):
                brick.append(builder.add_spring(int(self.nodes[i]), int(self.nodes[j]), brick_stiffness, damping))
            for i, j in zip(a[~same], b[~same]):
                mortar.append(builder.add_spring(int(self.nodes[i]), int(self.nodes[j]), mortar_stiffness, damping,
                                                 break_force=mortar_strength))
        self.brick_springs = np.array(brick, dtype=np.int64)
        self.mortar_springs = np.array(mortar, dtype=np.int64)
        self.size = np.array([gx, gy, gz]) * h


def add_ball(builder, center, radius, spacing, mass, velocity, stiffness, damping) -> np.ndarray:
    """A heavy ball: lattice nodes (``spacing`` [m], collision radius 0.45 spacing) inside a sphere
    of ``radius`` [m] at ``center``, ``mass`` [kg] shared equally, each joined to its 26 lattice
    neighbours by springs of ``stiffness`` [N/m]. Returns the particle indices."""
    h = float(spacing)
    k = math.ceil(radius / h)
    g = np.arange(-k, k + 1)
    ijk = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    ijk = ijk[np.linalg.norm(ijk * h, axis=1) <= max(radius - 0.45 * h, 0.0) + 1e-9]
    velocities = np.tile(np.asarray(velocity, float), (len(ijk), 1))
    nodes = builder.add_particles(np.asarray(center, float) + ijk * h, velocities, masses=mass / len(ijk),
                                  radii=0.45 * h)
    where = {tuple(c): int(n) for c, n in zip(ijk, nodes)}
    for c, n in zip(ijk, nodes):
        for off in ((a, b, d) for a in (-1, 0, 1) for b in (-1, 0, 1) for d in (-1, 0, 1) if (a, b, d) > (0, 0, 0)):
            other = where.get((c[0] + off[0], c[1] + off[1], c[2] + off[2]))
            if other is not None:
                builder.add_spring(int(n), other, stiffness, damping)
    return nodes


def pieces(spring_indices, broken, particles) -> np.ndarray:
    """Connected-component label of each particle in ``particles`` through intact springs (host
    union-find); labels are 0 .. number of pieces - 1."""
    particles = np.asarray(particles)
    local = {int(p): k for k, p in enumerate(particles)}
    parent = np.arange(len(particles))

    def find(a):
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    pairs = np.asarray(spring_indices).reshape(-1, 2)[~np.asarray(broken).astype(bool)]
    for i, j in pairs:
        a, b = local.get(int(i)), local.get(int(j))
        if a is not None and b is not None:
            ra, rb = find(a), find(b)
            if ra != rb:
                parent[ra] = rb
    roots = np.array([find(a) for a in range(len(particles))])
    return np.unique(roots, return_inverse=True)[1]


class FractureScene(SimulatorScene):
    """Per-frame break reports (``sim.fracture``), written as springs curves with a per-curve
    ``broken`` primvar."""

    def advance(self, frame_dt, substeps):
        super().advance(frame_dt, substeps)
        self._frames_done = getattr(self, "_frames_done", 0) + 1
        self.last_report = self.sim.fracture.end_frame(self._frames_done)

    def declare_springs(self, writer):
        m = self.sim.model.spring_count
        writer.add_curves("springs", curve_vertex_counts=np.full(m, 2), width=0.004, color=(0.35, 0.3, 0.25))
        writer.add_primvar("springs", "broken", "int[]", "uniform")
        writer.add_attribute("springs", "warpsim:brokenCount", "int")
        writer.add_attribute("springs", "warpsim:brokenThisFrame", "int[]")

    def springs_frame(self, x):
        model = self.sim.model
        broken = model.spring_broken.numpy()
        report = getattr(self, "last_report", None)
        new = report.springs if report is not None else np.zeros(0, dtype=np.int64)
        return {"points": spring_segments(x, model.spring_indices, broken), "broken": broken.astype(np.int32),
                "warpsim:brokenCount": int(broken.sum()), "warpsim:brokenThisFrame": new.astype(np.int32)}

    def checkpoint(self):
        data = super().checkpoint()
        data["frames_done"] = np.int64(getattr(self, "_frames_done", 0))
        return data

    def restore(self, data):
        super().restore(data)
        self._frames_done = int(data.get("frames_done", 0))


@register_scene("wall", "a brick wall of strong springs and weak breakable mortar hit by a heavy ball; fast balls "
                "break it into pieces, slow ones bounce off", params={
    "ball_speed": (12.0, "ball speed towards the wall [m/s]"),
    "ball_mass": (60.0, "ball mass [kg]"),
    "ball_radius": (0.15, "ball radius [m] (a lattice of particles, spacing as the wall's)"),
    "ball_stiffness": (1.0e5, "spring stiffness inside the ball [N/m]"),
    "ball_height": (0.0, "height of the ball's path [m] (0: the wall's middle)"),
    "mortar_strength": (60.0, "tension [N] at which a mortar spring breaks"),
    "mortar_stiffness": (5.0e3, "mortar spring stiffness [N/m]"),
    "brick_stiffness": (2.0e4, "spring stiffness inside a brick [N/m]"),
    "damping": (2.0, "spring damping [N s/m]"),
    "bricks": ((5.0, 6.0), "bricks per row, rows"),
    "brick_size": ((0.2, 0.1, 0.1), "brick length, height, depth [m] (multiples of spacing)"),
    "spacing": (0.05, "lattice spacing [m]"),
    "density": (2000.0, "brick density [kg/m^3]"),
    "anchored": (True, "pin the bottom layer of nodes (a foundation)"),
    "restitution": (0.2, "restitution of particle-particle and floor contacts"),
    "friction": (0.5, "Coulomb friction of contacts"),
    "gravity": (9.81, "gravitational acceleration [m/s^2]"),
    "dt": (1.0 / 1800.0, "time step [s]"),
    "integrator": ("semi_implicit_euler", "time integrator", INTEGRATORS),
}, substeps=30)
class WallScene(FractureScene):
    """See the module docstring; ``self.wall`` is the :class:`BrickWall`, ``self.ball`` the ball's
    particle indices."""

    smoke_params: ClassVar[dict] = {"bricks": (2.0, 2.0), "ball_speed": 20.0}

    def build(self, p):
        _positive(p, "ball_mass", "ball_radius", "mortar_strength", "spacing", "density", "bricks", "brick_size",
                  "gravity")
        h = p["spacing"]
        nodes = tuple(round(s / h) for s in p["brick_size"])
        if min(nodes) < 1 or any(abs(n * h - s) > 1e-6 for n, s in zip(nodes, p["brick_size"])):
            raise ValueError(f"brick_size={','.join(f'{s:g}' for s in p['brick_size'])} is not a multiple of "
                             f"spacing={h:g}; give sizes that are whole numbers of spacings")
        columns, rows = (int(b) for b in p["bricks"])
        if columns != p["bricks"][0] or rows != p["bricks"][1] or columns < 1 or rows < 1:
            raise ValueError(f"bricks={p['bricks']}: give whole numbers >= 1, e.g. bricks=5,6")
        b = ws.ModelBuilder()
        self.wall = BrickWall(b, (columns, rows), nodes, h, p["density"], p["brick_stiffness"], p["mortar_stiffness"],
                              p["damping"], p["mortar_strength"], p["anchored"])
        size = self.wall.size
        height = p["ball_height"] or 0.5 * size[1]
        start = (0.5 * size[0], height, -p["ball_radius"] - 0.05)
        self.ball = add_ball(b, start, p["ball_radius"], h, p["ball_mass"], (0.0, 0.0, p["ball_speed"]),
                             p["ball_stiffness"], p["damping"])
        model = b.finalize(self.device)
        kw = {"restitution": p["restitution"], "friction": p["friction"]}
        self.sim = ws.Simulator(model, integrator=p["integrator"], forces=[ws.Gravity((0.0, -p["gravity"], 0.0))],
                                colliders=[ws.ParticleCollisions(grid_dim=32, **kw), ws.Plane(**kw)], max_speed=500.0)

    def declare(self, writer):
        writer.add_points("wall", radius=self.wall.radius, color=(0.7, 0.35, 0.25))
        writer.add_points("ball", radius=self.wall.radius, color=(0.3, 0.3, 0.35))
        self.declare_springs(writer)
        writer.add_plane("floor", size=4.0 * max(self.wall.size))

    def frame_data(self):
        st = self.sim.state
        x, v = st.positions.numpy(), st.velocities.numpy()
        n = self.wall.nodes
        return {"wall": {"points": x[n], "velocities": v[n]},
                "ball": {"points": x[self.ball], "velocities": v[self.ball]},
                "springs": self.springs_frame(x)}


@register_scene("donuts", "a dozen soft tori dropped into a heap that comes to rest (soft body against soft body)",
                params={
    "count": (12, "number of tori"),
    "segments": (24, "torus segments around its axis"),
    "sides": (12, "torus segments around its tube"),
    "major_radius": (0.1, "torus radius [m]"),
    "minor_radius": (0.04, "tube radius [m]"),
    "mass": (1.0, "mass of one torus [kg]"),
    "stiffness": (150.0, "spring stiffness [N/m] (surface, bending, interior)"),
    "damping": (0.05, "spring damping [N s/m]"),
    "lattice_cells": (8, "interior lattice cells across a torus (shape keeping)"),
    "thickness": (0.006, "contact thickness between tori [m]"),
    "friction": (0.5, "Coulomb friction between tori, on the floor and walls"),
    "restitution": (0.0, "restitution between tori, on the floor and walls"),
    "box": (0.35, "half width of the box the tori fall into [m]"),
    "self_contact": (False, "also collide each torus with itself"),
    "seed": (1, "random orientations"),
    "gravity": (9.81, "gravitational acceleration [m/s^2]"),
    "dt": (1.0 / 1200.0, "time step [s]"),
    "integrator": ("semi_implicit_euler", "time integrator", INTEGRATORS),
}, substeps=20)
class DonutsScene(SimulatorScene):
    """See the module docstring; ``self.bodies`` are the tori's SoftBody records, ``self.contact``
    the SoftContact."""

    smoke_params: ClassVar[dict] = {"count": 2, "segments": 10, "sides": 6, "lattice_cells": 5}

    def build(self, p):
        _positive(p, "count", "segments", "sides", "major_radius", "minor_radius", "mass", "stiffness",
                  "lattice_cells", "thickness", "box", "gravity")
        points, faces = torus_mesh(p["major_radius"], p["minor_radius"], p["segments"], p["sides"])
        reach = p["major_radius"] + p["minor_radius"]
        per_side = max(1, int((2.0 * p["box"]) // (2.0 * reach + 0.02)))
        per_layer = per_side * per_side
        pitch = 2.0 * p["box"] / per_side
        rng = np.random.default_rng(p["seed"])
        b = ws.ModelBuilder()
        self.bodies = []
        for k in range(p["count"]):
            layer, slot = divmod(k, per_layer)
            ix, iz = divmod(slot, per_side)
            x = -p["box"] + (ix + 0.5) * pitch
            z = -p["box"] + (iz + 0.5) * pitch
            y = reach + 0.05 + layer * (2.0 * reach + 0.05)
            axis = rng.normal(size=3)
            axis /= np.linalg.norm(axis)
            angle = rng.uniform(0.0, 0.5 * math.pi)
            rotation = (*(math.sin(angle / 2) * axis), math.cos(angle / 2))
            self.bodies.append(add_soft_body(
                b, points, faces, position=(x, y, z), rotation=rotation, total_mass=p["mass"],
                mass_distribution="uniform", stiffness=p["stiffness"], damping=p["damping"],
                lattice_cells=p["lattice_cells"], name=f"torus {k}"))
        model = b.finalize(self.device)
        kw = {"restitution": p["restitution"], "friction": p["friction"]}
        top = max(2.0 * p["box"], float(model.particle_q.numpy()[:, 1].max()) + reach)
        self.lower, self.upper = (-p["box"], 0.0, -p["box"]), (p["box"], top, p["box"])
        self.contact = SoftContact(self.bodies, thickness=p["thickness"], self_contact=p["self_contact"], **kw)
        self.sim = ws.Simulator(model, integrator=p["integrator"], forces=[ws.Gravity((0.0, -p["gravity"], 0.0))],
                                colliders=[ws.Box(self.lower, self.upper, **kw), self.contact], max_speed=100.0)
        self.surface = np.concatenate([body.surface_indices for body in self.bodies])
        where = np.full(model.particle_count, -1, dtype=np.int64)
        where[self.surface] = np.arange(len(self.surface))
        self.faces = np.concatenate([where[body.faces] for body in self.bodies])

    def kinetic_energy(self) -> float:
        """Kinetic energy of every particle [J] (reads the state back)."""
        v = self.sim.state.velocities.numpy().astype(np.float64)
        return float(0.5 * (self.sim.model.particle_mass.numpy() * (v * v).sum(1)).sum())

    def declare(self, writer):
        writer.add_mesh("donuts", np.full(len(self.faces), 3), self.faces.reshape(-1), color=(0.85, 0.6, 0.35))
        writer.add_attribute("donuts", "warpsim:kineticEnergy", "double")
        writer.add_box("walls", self.lower, self.upper, **CONTAINER)  # see-through walls
        add_floor(writer, self.lower, self.upper)

    def frame_data(self):
        st = self.sim.state
        return {"donuts": {"points": st.positions.numpy()[self.surface],
                           "velocities": st.velocities.numpy()[self.surface],
                           "warpsim:kineticEnergy": self.kinetic_energy()}}
