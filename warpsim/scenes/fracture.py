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
an interior lattice, built once and copied in NumPy: ``replicate_model``, ``SoftContact.copies``;
1,000 tori x 2,000 vertices build in 3.5 s) dropped in layers into a box sized to the count;
``ws.SoftContact`` keeps them apart (vertices against the other tori's triangles, edges against
their edges) so they pile up and come to rest. Each step ``dt`` is split into the inner steps
the springs' stability limit needs (:func:`stable_inner_steps`). With ``integrator=implicit_euler``
the springs set no limit and a frame can take 4 steps (``warpsim run donuts --set
integrator=implicit_euler --fps 60 --substeps 4``: 1/240 s); the contacts then enter the implicit solve
as a penalty (``contact_stiffness``) with a speculative ``contact_reach`` and 16 passes after each
step. Held at 1/240 s (no vertex deeper than the thickness, no edge through a triangle) for this
scene's 12 tori over 45 frames, 14 x 7 tori (4 stacked, 24 landing) and 2 tori of 2,000 vertices; not
yet for 12 tori of 2,000 vertices (benchmarks/RESULTS.md). With ``integrator=vbd`` (``warpsim run donuts
--set integrator=vbd --substeps 4``: 1/240 s) ``ws.VBD`` steps the heap by vertex block descent with the
contacts, floor and walls inside the descent (``ws.VBDContact``, no collider after the step) and a step bound
that provably keeps every edge out of every triangle; held over 600 frames at 1/240 s (tests/test_vbd.py). Prims:
``donuts`` (one mesh, all tori; custom ``warpsim:kineticEnergy`` [J])
and ``walls`` (the box).
"""
from __future__ import annotations

import dataclasses
import math
import warnings
from typing import ClassVar

import numpy as np
import warp as wp

import warpsim as ws

from ..bodies.shapes import torus_mesh
from ..bodies.soft_contact import SoftContact
from ..bodies.softbody import add_soft_body
from ..bodies.vbd_contact import cut_guess_line, guess_length
from ..core.fracture import spring_segments
from ..core.memory import available_host_bytes, check_build_memory
from ..core.model import Model
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

    def frame_arrays(self):
        """None: the springs drawn are each world's unbroken ones, not a function of the particle
        arrays alone, so a batch asks each world in turn (``WorldBatch.world_frame_data``)."""
        return None

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
    "density": (2000.0, "brick density [kg/m^3] (the viewer's slider stops at 20, foam: at 1 the ball's contact "
                        "throws brick nodes past the 500 m/s speed bound)", None, 20.0),
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
    substeps_auto = True  # sub-step inside the stiff brick springs' stability limit

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
        # at most (nodes + 1) lattice nodes a brick (shared faces make fewer; measured 2,458 bytes a
        # particle, 918 a bound node, at 10 x 10 bricks), before building
        per_brick = math.prod(n + 1 for n in nodes)
        check_build_memory("bricks", f"{columns},{rows}", columns * rows * per_brick, "lattice nodes", 1000.0,
                           lambda k: f"{max(1, int((k / per_brick) ** 0.5))},{max(1, int((k / per_brick) ** 0.5))}")
        b = ws.ModelBuilder()
        self.wall = BrickWall(b, (columns, rows), nodes, h, p["density"], p["brick_stiffness"], p["mortar_stiffness"],
                              p["damping"], p["mortar_strength"], p["anchored"])
        size = self.wall.size
        lowest = p["ball_radius"] + 0.45 * h  # the ball's lowest node clears the floor by its collision radius
        if p["ball_height"] and p["ball_height"] < lowest:
            raise ValueError(f"ball_height={p['ball_height']:g}: a ball of radius {p['ball_radius']:g} m would start in "
                             f"the floor (its springs stretched by the floor's push: energy from nowhere); give "
                             f"ball_height >= {lowest:g} or 0 (the wall's middle)")
        # the wall's middle, or just above the floor for a wall lower than the ball (bricks=2,2: the ball's
        # bottom node started at y = 0 and the floor's push put 747 J into its springs in the first step)
        height = p["ball_height"] or max(0.5 * size[1], lowest)
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


def _largest_spring_eigenvalue(q, mass, springs, coefficient, iterations: int = 300) -> float:
    """Largest eigenvalue of M^-1 A for the spring matrix A = sum_s a_s (e_i - e_j)(e_i - e_j)^T
    (x) n_s n_s^T at positions q (n_s the spring direction; at rest the stiffness matrix when
    a = k, the damping matrix when a = c), by power iteration on M^-1/2 A M^-1/2 [1/s^2 or 1/s]."""
    i, j = springs[:, 0], springs[:, 1]
    n = q[i] - q[j]
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
    scale = 1.0 / np.sqrt(mass)[:, None]
    x = np.random.default_rng(0).normal(size=q.shape)
    value = 0.0
    for _ in range(iterations):
        norm = np.linalg.norm(x)
        if norm == 0.0:  # A x = 0: every coefficient is 0
            return 0.0
        x /= norm
        y = x * scale
        f = (coefficient * ((y[i] - y[j]) * n).sum(1))[:, None] * n
        out = np.stack([np.bincount(i, f[:, c], len(q)) - np.bincount(j, f[:, c], len(q)) for c in range(3)], 1)
        out *= scale
        value = float((out * x).sum())
        x = out
    return value


def stable_inner_steps(q, mass, springs, stiffness, damping, integrator: str, dt: float, safety: float = 0.8) -> int:
    """Integration steps per scene step ``dt`` [s] that keep semi-implicit Euler inside its
    stability limit for one torus's springs (q, mass, springs (S, 2), stiffness, damping: its
    rest positions [m], masses [kg], springs and coefficients; every torus is a rotated copy, so
    one limit holds for all). 1 for every other integrator: implicit Euler is unconditionally
    stable, the explicit ones are the user's choice to study.

    Stand-in until ``Simulator(substeps="auto")`` lands (engineer ``stab``). With omega^2 and
    gamma the largest eigenvalues of M^-1 K and M^-1 C, semi-implicit Euler on
    x'' = -omega^2 x - gamma x' is stable for h^2 omega^2 + 2 h gamma <= 4, so
    h <= (sqrt(gamma^2 + 4 omega^2) - gamma) / omega^2, taken with a ``safety`` factor (the
    springs stretch, the contact adds its pushes). The soft contact sets no limit of its own: it
    moves positions by a fraction of the depth and applies impulses (no contact stiffness)."""
    if integrator != "semi_implicit_euler" or len(springs) == 0:
        return 1
    omega2 = _largest_spring_eigenvalue(q, mass, springs, stiffness)
    gamma = _largest_spring_eigenvalue(q, mass, springs, damping)
    h_max = safety * (math.sqrt(gamma * gamma + 4.0 * omega2) - gamma) / omega2
    return max(1, math.ceil(dt / h_max))


def rotate_points(quats, points) -> np.ndarray:
    """``points`` (P, 3) rotated by each unit quaternion (x, y, z, w) of ``quats`` (N, 4): shape (N, P, 3)
    (``quat_rotate`` for many rotations at once)."""
    u, w = quats[:, None, :3], quats[:, None, 3:]
    v = points[None]
    return v + 2.0 * np.cross(u, np.cross(u, v) + w * v)


def replicate_model(template, count: int, positions, device) -> Model:
    """``count`` copies of a finalized ``template`` Model (host arrays are read once) on ``device``,
    copy k's particles at ``positions[k P:(k + 1) P]`` (P = template.particle_count) and its
    springs joining its own particles: per-particle and per-spring arrays are tiled, spring ends
    and the spring adjacency shifted, in NumPy (no per-copy Python work)."""
    P, S = template.particle_count, template.spring_count
    if P == S or P == 2 * S:
        raise ValueError(f"replicate_model: {P} particles and {S} springs cannot be told apart by length")
    model = Model(device)
    model.particle_count, model.spring_count = count * P, count * S
    model.breakable_spring_count = count * template.breakable_spring_count
    k = np.arange(count)
    for name, arr in vars(template).items():
        if not isinstance(arr, wp.array):
            continue
        host = arr.numpy()
        if name == "particle_q":
            host = np.asarray(positions, dtype=np.float32).reshape(count * P, 3)
        elif name == "spring_indices":
            host = (host[None, :] + (k * P)[:, None]).reshape(-1)
        elif name == "particle_spring_offsets":
            host = np.append((host[None, :-1] + (k * 2 * S)[:, None]).reshape(-1), count * 2 * S)
        elif name == "particle_springs":
            host = (host[None, :] + (k * S)[:, None]).reshape(-1)
        elif len(host) in (P, S):
            host = np.tile(host, (count,) + (1,) * (host.ndim - 1))
        else:
            raise ValueError(f"replicate_model: the template's {name} (length {len(host)}) is neither per particle "
                             f"({P}) nor per spring ({S})")
        setattr(model, name, wp.array(np.ascontiguousarray(host), dtype=arr.dtype, device=model.device))
    return model


def check_donut_box(box: float, major_radius: float, minor_radius: float) -> float:
    """ValueError naming ``box`` and the smallest box that fits when a torus (turned any way: it
    reaches major_radius + minor_radius from its centre) would start through the walls of a box
    of half width ``box`` [m] (0: sized to the count, always wide enough); returns the smallest."""
    reach = major_radius + minor_radius
    smallest = reach + 0.01  # a torus and a centimetre of room on each side
    if box and box < smallest - 1.0e-9:
        raise ValueError(f"box={box:g}: a torus reaches {reach:g} m from its centre (major_radius {major_radius:g} + "
                         f"minor_radius {minor_radius:g}, {2 * reach:g} m across), so in a box of half width {box:g} m "
                         f"it starts through the walls; give box>={smallest:.3g}, or box=0 to size the box to the count")
    return smallest


def check_donut_memory(count: int, torus, device, list_capacity: int = 0, extra_bytes: int = 0) -> None:
    """ValueError (with the figures) when ``count`` copies of ``torus`` (a SoftBody) would not fit
    in the device's free memory, or the host's for the build. Per torus: about 300 B per particle
    (state, model, integrator and contact buffers), 120 B per spring (model, adjacency), 260 B per
    surface triangle (BVHs, edges, contact slots), and with a candidate list of ``list_capacity``
    candidates a query 2 (4 capacity + 8) B per triangle (about two queries, a vertex's and 1.5 edges',
    per triangle); the Python build holds about 250 B per spring and 200 B per particle on the host.
    ``extra_bytes``: more device bytes per torus (``integrator=vbd``: its pair lists, ``VBDContact.list_bytes``,
    and about 10 vectors a particle of the descent's positions and bounds)."""
    faces = len(torus.faces)
    per_face = 260 + (2 * (4 * list_capacity + 8) if list_capacity else 0)
    device_bytes = count * (300 * torus.particle_count + 120 * torus.spring_count + per_face * faces + extra_bytes)
    host_bytes = count * (200 * torus.particle_count + 250 * torus.spring_count)
    need = [("host", host_bytes, available_host_bytes(unknown=0))]
    if device.is_cuda:
        need.append((str(device), device_bytes, int(device.free_memory)))
    else:
        need[0] = ("host", host_bytes + device_bytes, need[0][2])
    for where, needed, free in need:
        if free and needed > 0.8 * free:
            per = needed / count
            raise ValueError(f"count={count} tori of {torus.particle_count} particles and {torus.spring_count} springs "
                             f"need about {needed / 2**30:.1f} GiB on the {where} ({per / 2**20:.2f} MiB a torus) but "
                             f"{free / 2**30:.1f} GiB are free; lower count to {max(1, int(0.8 * free / per))} or "
                             "fewer, or use fewer segments/sides/lattice_cells")


@register_scene("donuts", "a dozen soft tori dropped into a heap that comes to rest (soft body against soft body)",
                params={
    "count": (12, ("number of tori (up to what fits in memory: 1,000 x 2,000 vertices are estimated at 5.6 GB of "
                   "host memory to build, 4.2 GB on the device)")),
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
    "box": (0.0, "half width of the box the tori fall into [m]; 0: sized to the count (0.35 m for 12 tori)"),
    "self_contact": (False, "also collide each torus with itself"),
    "edge_contact": (True, "edge-edge contact beside vertex-triangle contact"),
    "broad_phase": ("bvh", ("contact search: 'bvh' (search every step), 'list' (a candidate list searched again "
                            "only when a vertex moved more than the pad, or every search_every steps: faster on a "
                            "settled heap, much slower while tori fall; benchmarks/RESULTS.md), 'all_pairs' "
                            "(reference); all find the same contacts"), ("bvh", "list", "all_pairs")),
    "seed": (1, "random orientations"),
    "gravity": (9.81, "gravitational acceleration [m/s^2]"),
    "dt": (1.0 / 1200.0, "time step [s] (split further where the springs' stability limit needs it)"),
    "integrator": ("semi_implicit_euler", ("time integrator; fast_mass_spring: backward Euler by local-global "
                                           "iterations with one prefactored matrix for all tori (ws.FastMassSpring); "
                                           "vbd: backward Euler by vertex block descent with the contacts, floor and "
                                           "walls inside the descent and a step bound that keeps every edge out of "
                                           "every triangle (ws.VBD; e.g. --substeps 4 for 1/240 s)"),
                   INTEGRATORS + ("fast_mass_spring", "vbd")),
    "contact_stiffness": (2000.0, ("implicit_euler: penalty stiffness of the contacts inside the implicit solve "
                                   "[N/m] (SoftContact.implicit_force; 0: off, contact only after the step); "
                                   "fast_mass_spring: stiffness of the proximal pull toward the pushed contact "
                                   "vertices (FastMassSpring contact_stiffness); vbd: k_c of the contact energy "
                                   "k_c/2 (thickness - d)^2 (VBDContact stiffness)")),
    "contact_damping": (0.0, "implicit_euler only: damping of the contacts inside the implicit solve [N s/m]"),
    "contact_reach": (0.012, ("implicit_euler and fast_mass_spring: speculative contact distance beyond the thickness [m] "
                              "(SoftContact reach): pairs that close during a large step are in the implicit "
                              "solve before they touch")),
    "contact_edge_reach": (0.0, ("implicit_euler and fast_mass_spring: speculative distance of edge-edge pairs [m] "
                                 "(SoftContact edge_reach; edges that pass through each other are found after the "
                                 "step anyway): 0 held the heaps as well as the reach and cuts the edge search")),
    "contact_iterations": (16, ("implicit_euler and fast_mass_spring: contact passes after each step (SoftContact iterations; "
                                "4 with semi_implicit_euler)")),
    "newton_iterations": (4, "implicit_euler only: Newton iterations per step (1: linearly implicit, no host read-back)"),
    "vbd_detect_every": (5, ("vbd only: iterations between contact searches inside a step (a search opens "
                             "every step; each lets a vertex move at most vbd_max_displacement more; at rest "
                             "they are skipped)")),
    "vbd_max_displacement": (0.0, ("vbd only: the most a vertex moves between two contact searches [m] (0: the "
                                   "thickness, or the initial guess of the scene's fall at its step dt if longer: a "
                                   "guess cut by the bound slows the fall); a pair's search radius is the thickness "
                                   "+ its two sides' caps")),
    "vbd_min_displacement": (0.0, ("vbd only: the smallest cap [m] (0: a quarter of the thickness): each vertex's "
                                   "cap, the most it moves before the next search, is 4 x its step's length at "
                                   "its speed within [this, vbd_max_displacement]; equal to it: fixed caps")),
    "vbd_line_search": (4, ("vbd only: halvings of a vertex's Newton step tried when the force at the step's end "
                            "pushes back harder than at its start (ws.VBD line_search; 0: every step taken whole, "
                            "and a heap pressed by contacts much stiffer than its springs can jitter)")),
    "vbd_chebyshev_rho": (0.0, ("vbd only: spectral radius estimate of the Chebyshev acceleration in [0, 1) (0: "
                                "off; 0.9 with 12 iterations gained 13 % energy at the heap's first impacts)")),
    "solver_chebyshev": (True, ("fast_mass_spring only: Chebyshev acceleration of the iterations (ws.FastMassSpring; "
                                "12 accelerated iterations leave 0.010 of a step's error in the scene's tori, 20 plain "
                                "ones 0.16; benchmarks/RESULTS.md)")),
    "solver_iterations": (12, ("fast_mass_spring and vbd: iterations per step (vbd: colour sweeps; fast_mass_spring: "
                               "local-global iterations; the scene's heap at 1/240 s "
                               "held with 12 accelerated or 20 plain ones, let edges through with 10 plain; the "
                               "2,000-vertex tori of bench_donuts.py need 12 accelerated ones; benchmarks/RESULTS.md)")),
}, substeps=20)
class DonutsScene(SimulatorScene):
    """See the module docstring; ``self.torus`` is the first torus's SoftBody record and
    ``self.offsets`` the particle offset of each (``self.bodies`` makes the records on demand), ``self.contact``
    the SoftContact, ``self.inner_steps`` the integration steps per scene step ``dt`` (from the
    springs' stability limit, :func:`stable_inner_steps`: 1 at the default 288 vertices a torus,
    2 at 2,000)."""

    smoke_params: ClassVar[dict] = {"count": 2, "segments": 10, "sides": 6, "lattice_cells": 5}
    substeps_auto = True  # sub-step inside the tori's spring limit

    def build(self, p):
        _positive(p, "count", "segments", "sides", "major_radius", "minor_radius", "mass", "stiffness",
                  "lattice_cells", "thickness", "gravity", "newton_iterations", "contact_iterations", "solver_iterations")
        for key, unit in (("contact_stiffness", "N/m"), ("contact_damping", "N s/m"), ("contact_reach", "m"),
                          ("contact_edge_reach", "m")):
            if not (math.isfinite(p[key]) and p[key] >= 0.0):
                raise ValueError(f"{key}={p[key]}: give a number >= 0 [{unit}] (contact_stiffness 0: no contact "
                                 "force in the implicit solve)")
        if not (math.isfinite(p["box"]) and p["box"] >= 0.0):
            raise ValueError(f"box={p['box']}: give a half width > 0 [m], or 0 to size the box to the count")
        check_donut_box(p["box"], p["major_radius"], p["minor_radius"])  # before anything is built
        points, faces = torus_mesh(p["major_radius"], p["minor_radius"], p["segments"], p["sides"])
        # one torus at the origin, copied (rotated, moved) count times: the lattice and springs are
        # built once, so 1,000 tori build in seconds
        template_builder = ws.ModelBuilder()
        template = add_soft_body(template_builder, points, faces, total_mass=p["mass"], mass_distribution="uniform",
                                 stiffness=p["stiffness"], damping=p["damping"], lattice_cells=p["lattice_cells"],
                                 name="torus")
        broad_phase = p["broad_phase"]
        extra = 0
        if p["integrator"] == "vbd":  # its pair lists (no SoftContact list) and descent buffers
            faces_n = len(faces)
            extra = ws.VBDContact.list_bytes(len(points), faces_n, 3 * faces_n // 2) + 120 * template.particle_count
        check_donut_memory(p["count"], template, wp.get_device(self.device),
                           SoftContact.DEFAULT_CAPACITY if broad_phase == "list" else 0, extra)
        reach = p["major_radius"] + p["minor_radius"]
        box = p["box"] or max(0.35 * p["major_radius"] / 0.1 * (p["count"] / 12.0) ** (1.0 / 3.0), reach + 0.01)
        per_side = max(1, int((2.0 * box) // (2.0 * reach + 0.02)))
        per_layer = per_side * per_side
        pitch = 2.0 * box / per_side
        rng = np.random.default_rng(p["seed"])
        local = np.asarray(template_builder.particle_q, dtype=np.float64)
        masses = np.asarray(template_builder.particle_mass, dtype=np.float64)
        springs = np.asarray(template_builder.spring_indices, dtype=np.int64)
        stiffness = np.asarray(template_builder.spring_stiffness, dtype=np.float64)
        damping = np.asarray(template_builder.spring_damping, dtype=np.float64)
        count = p["count"]
        k = np.arange(count)
        layer, slot = np.divmod(k, per_layer)
        ix, iz = np.divmod(slot, per_side)
        centres = np.stack([-box + (ix + 0.5) * pitch, reach + 0.05 + layer * (2.0 * reach + 0.05),
                            -box + (iz + 0.5) * pitch], 1)
        quats = np.empty((count, 4))
        for i in range(count):  # the same draws, in the same order, as one torus at a time
            axis = rng.normal(size=3)
            axis /= np.linalg.norm(axis)
            angle = rng.uniform(0.0, 0.5 * math.pi)
            quats[i] = (*(math.sin(angle / 2) * axis), math.cos(angle / 2))
        positions = centres[:, None, :] + rotate_points(quats, local)
        self.torus = template
        """The first torus's SoftBody record (particle_start 0); torus k is it shifted by ``self.offsets[k]``."""
        self.offsets = k * template.particle_count
        """Particle offset of each torus, shape (count,)."""
        model = replicate_model(template_builder.finalize("cpu"), count, positions.reshape(-1, 3), self.device)
        kw = {"restitution": p["restitution"], "friction": p["friction"]}
        top = max(2.0 * box, float(model.particle_q.numpy()[:, 1].max()) + reach)
        self.lower, self.upper = (-box, 0.0, -box), (box, top, box)
        self.contact = None  # one torus without self contact touches nothing but the box
        self.vbd_contact = None  # integrator=vbd: the ws.VBDContact inside the descent
        # at implicit Euler's large steps: speculative pairs in the solve and more passes after it
        # (measured: 2 tori of 2,000 vertices at 1/240 s cross with 4 passes, not with 8 or 16)
        implicit_contact = ({"reach": p["contact_reach"], "edge_reach": p["contact_edge_reach"],
                             "iterations": int(p["contact_iterations"])}
                            if p["integrator"] in ("implicit_euler", "fast_mass_spring") else {})
        if p["integrator"] == "vbd":
            self._build_vbd(p, model, template, box)
            return
        if count > 1 or p["self_contact"]:
            self.contact = SoftContact.copies(template.faces, self.offsets, thickness=p["thickness"],
                                              self_contact=p["self_contact"], edge_contact=p["edge_contact"],
                                              broad_phase=broad_phase, **kw, **implicit_contact)
        colliders = [ws.Box(self.lower, self.upper, **kw)] + ([self.contact] if self.contact else [])
        forces: list = [ws.Gravity((0.0, -p["gravity"], 0.0))]
        integrator = p["integrator"]
        if integrator == "fast_mass_spring":
            # the springs implicit; the contacts pushed apart inside the iterations, then resolved after the step
            integrator = ws.FastMassSpring(iterations=int(p["solver_iterations"]), body_size=template.particle_count,
                                           contacts=[self.contact] if self.contact is not None else [],
                                           contact_stiffness=p["contact_stiffness"],
                                           chebyshev=bool(p["solver_chebyshev"]))
        elif integrator == "implicit_euler":
            integrator = ws.ImplicitEuler(newton_iterations=p["newton_iterations"])
            if self.contact is not None and p["contact_stiffness"] > 0.0:
                forces.append(self.contact.implicit_force(p["contact_stiffness"], p["contact_damping"]))
        self.sim = ws.Simulator(model, integrator=integrator, forces=forces, colliders=colliders, max_speed=100.0)
        self.inner_steps = stable_inner_steps(local, masses, springs, stiffness, damping, p["integrator"], p["dt"])
        self._finish_build(template, count)

    def _finish_build(self, template, count: int) -> None:
        """The surface vertices and triangles of all tori (the prims' indices)."""
        k = np.arange(count)
        surface = template.surface_count
        self.surface = (np.arange(surface)[None, :] + self.offsets[:, None]).reshape(-1)
        self.faces = (template.faces[None] + (k * surface)[:, None, None]).reshape(-1, 3)  # in surface order

    def _build_vbd(self, p, model, template, box) -> None:
        """``integrator=vbd``: the tori, floor and walls in one ws.VBD (contact energies inside the descent,
        the step bound; no collider after the step), copies of one torus (one colouring, one CSR)."""
        for key, zero in (("vbd_detect_every", "one contact search a step"),
                          ("vbd_line_search", "every Newton step taken whole")):
            if p[key] < 0:
                raise ValueError(f"{key}={p[key]}: give an integer >= 0 (0: {zero})")
        quarter = "a quarter of the thickness"
        for key, zero in (("vbd_max_displacement", "the thickness or the fall's initial guess"),
                          ("vbd_min_displacement", quarter)):
            if not (math.isfinite(p[key]) and p[key] >= 0.0):
                raise ValueError(f"{key}={p[key]}: give a distance >= 0 [m] (0: {zero})")
        # 0: the thickness, or the initial guess of the scene's fall at its own step dt if longer (a guess the bound
        # cuts slows the fall: guess_step)
        largest = p["vbd_max_displacement"] or max(p["thickness"], self.guess_step(p["dt"], model))
        if p["vbd_min_displacement"] > largest:
            raise ValueError(f"vbd_min_displacement={p['vbd_min_displacement']}: it must be at most "
                             f"vbd_max_displacement ({largest:g} m); give e.g. {0.25 * largest:g}")
        planes = [((0.0, 1.0, 0.0), 0.0), ((1.0, 0.0, 0.0), -box), ((-1.0, 0.0, 0.0), -box),
                  ((0.0, 0.0, 1.0), -box), ((0.0, 0.0, -1.0), -box)]
        P = template.particle_count
        self.vbd_contact = ws.VBDContact(
            template.faces - template.particle_start, body_size=P, thickness=p["thickness"],
            stiffness=p["contact_stiffness"], friction=p["friction"], self_contact=p["self_contact"],
            max_displacement=largest,
            min_displacement=p["vbd_min_displacement"] or None, planes=planes)
        integrator = ws.VBD(int(p["solver_iterations"]), contact=self.vbd_contact, body_size=P,
                            chebyshev_rho=p["vbd_chebyshev_rho"],
                            detect_every=int(p["vbd_detect_every"]), line_search=int(p["vbd_line_search"]))
        self.sim = ws.Simulator(model, integrator=integrator, forces=[ws.Gravity((0.0, -p["gravity"], 0.0))],
                                colliders=[], max_speed=100.0)
        self.inner_steps = 1
        self._finish_build(template, p["count"])

    @property
    def bodies(self) -> list:
        """SoftBody records of the tori, made on demand (the scene holds one template and offsets)."""
        t = self.torus
        return [dataclasses.replace(t, particle_start=int(o), faces=t.faces + o,
                                    spring_start=k * t.spring_count) for k, o in enumerate(self.offsets)]

    def advance(self, frame_dt, substeps):
        h = frame_dt / (substeps * self.inner_steps)
        for _ in range(substeps * self.inner_steps):
            self.sim.step(h)
        if self.contact is not None and self.contact.broad_phase == "list" and not self.device_capturing():
            # one read-back a frame (not while a sweep captures the frame as a CUDA graph)
            overflow = self.contact.candidate_overflow
            if overflow > getattr(self, "_overflow_seen", 0):
                self._overflow_seen = overflow
                warnings.warn(f"donuts: {overflow} contact queries had more than {self.contact.capacity} candidates "
                              "so far (contacts may have been missed); raise SoftContact capacity", stacklevel=2)

    def device_capturing(self) -> bool:
        return bool(wp.get_device(self.sim.model.device).is_capturing)

    def fall_speed(self, model=None) -> tuple:
        """(height [m], speed [m/s]): the largest of the tori's lowest points above the floor as built, and the speed
        sqrt(2 g height) a torus reaches falling from there to the floor (the fastest any torus meets another or the
        floor); ``model``: the scene's (default) or the one being built."""
        q = (model if model is not None else self.sim.model).particle_q
        P = len(q) // len(self.offsets)
        height = float(q.numpy()[:, 1].reshape(-1, P).min(1).max()) - self.lower[1]
        return height, math.sqrt(2.0 * self.params["gravity"] * max(height, 0.0))

    def guess_step(self, h: float, model=None) -> float:
        """The longest initial guess of ``ws.VBD`` in a step of ``h`` [s] while the tori fall: the fall's speed
        (:meth:`fall_speed`) x h + g h^2 [m], rounded up to 0.1 mm. A guess longer than the bound (at most
        ``vbd_max_displacement``) is cut, and the sweeps do not carry a whole torus's translation on (its springs
        hold each vertex to its neighbours' cut positions): the fall is slowed. Measured (one torus of 24 x 12 in
        the air, 1/240 s, 12 sweeps, b_max 6 mm): released at 1 m/s (4.3 mm a step) it falls as backward Euler to
        1e-4 for 10 steps, at 2 m/s it is 5 % slow after 20 steps and at 3 m/s 16 %; with b_max 30 mm at 3 m/s,
        within 1e-4 (and 14 searches in 20 steps instead of 59)."""
        _, fall = self.fall_speed(model)
        return guess_length(fall, self.params["gravity"], h)

    def scene_warning(self, frame_dt, substeps):
        """One line when a fall is faster than the contact can follow (:meth:`fall_speed`): with
        ``integrator=vbd`` when the step bound would slow it (the fall's initial guess longer than b_max,
        :meth:`guess_step`), naming the steps a frame and the b_max that let it fall freely; with ``implicit_euler`` and
        ``fast_mass_spring`` (the SoftContact inside the solve) when a step at that speed carries a vertex farther than
        the thickness + ``contact_reach``, the distance within which the contact lists a pair before the step (a pair
        farther apart can close and cross unseen: the 12-torus heap of 10 x 6 tori at 1/60 s let 55 edges through by
        frame 19 with fast mass-spring, 326 by frame 29 with implicit Euler, and a reach of 61 mm did not help),
        naming the steps a frame that keep it within that: needed, not always enough (at 1/240 s the same heap came
        apart again by frame 35 with fast mass-spring, but implicit Euler kept two pairs of tori through each other)."""
        contact = getattr(self, "vbd_contact", None)
        if contact is None:
            return self._soft_contact_warning(frame_dt, substeps)
        height, fall = self.fall_speed()
        return cut_guess_line("donuts: with integrator=vbd a torus", height, fall, self.params["gravity"], frame_dt,
                              self.frame_steps(frame_dt, substeps), contact.max_displacement,
                              "vbd_max_displacement", setting="vbd_max_displacement")

    def _soft_contact_warning(self, frame_dt, substeps):
        """The SoftContact's line of :meth:`scene_warning` (None without one, or when the fall stays within
        the distance the contact lists pairs at)."""
        if self.contact is None or self.params["integrator"] not in ("implicit_euler", "fast_mass_spring"):
            return None
        inner = self.frame_steps(frame_dt, substeps) * self.inner_steps
        h = frame_dt / inner
        listed = self.contact.thickness + self.contact.reach  # [m]
        height, fall = self.fall_speed()
        if fall * h <= listed:
            return None
        return (f"donuts: a torus falling from {height:.3g} m meets the heap at {fall:.3g} m/s, "
                f"{fall * h * 1e3:.3g} mm in a step of {h:.3g} s, farther than the {listed * 1e3:.3g} mm within which "
                "the contact lists a pair before the step (thickness + contact_reach): tori can pass through each "
                "other unseen; take "
                f"--substeps {math.ceil(fall * frame_dt / (listed * self.inner_steps))} at least, or integrator=vbd "
                "(its step bound keeps every pair apart at any step)")

    def kinetic_energy(self, velocities=None) -> float:
        """Kinetic energy of every particle [J] (``velocities`` (P, 3); None: the state's, read back)."""
        v = (self.sim.state.velocities.numpy() if velocities is None else velocities).astype(np.float64)
        return float(0.5 * (self.sim.model.particle_mass.numpy() * (v * v).sum(1)).sum())

    def declare(self, writer):
        writer.add_mesh("donuts", np.full(len(self.faces), 3), self.faces.reshape(-1), color=(0.85, 0.6, 0.35))
        writer.add_attribute("donuts", "warpsim:kineticEnergy", "double")
        writer.add_box("walls", self.lower, self.upper, **CONTAINER)  # see-through walls
        add_floor(writer, self.lower, self.upper)

    def frame_arrays(self):
        """The donuts' surface vertices from the particle arrays and each world's kinetic energy."""
        from ..usd.frame_arrays import Particles, PerWorld

        return {"donuts": {"points": Particles("positions", self.surface),
                           "velocities": Particles("velocities", self.surface),
                           "warpsim:kineticEnergy": PerWorld(lambda x, v: self.kinetic_energy(v))}}

    def frame_data(self):
        from ..usd.frame_arrays import frame_data_from

        st = self.sim.state
        return frame_data_from(self.frame_arrays(), st.positions, st.velocities)
