"""Particle-liquid scenes (position-based fluids, or divergence-free SPH with ``--set method=dfsph``):
``dam_break`` and ``pour``.

Each frame writes the particles as ``UsdGeom.Points`` with ``ids`` (counts may change) and the
liquid surface, splatted onto a grid and meshed with marching cubes, as a ``Mesh`` whose
topology changes every frame.
"""
from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np

from ..bodies import colliders as C
from ..particle_fluids.surface import FluidSurface
from ..particle_fluids.pbf import KERNELS, METHODS, Nozzle, ParticleFluid, Sink, fluid_block
from . import CONTAINER, Scene, add_floor, register_scene

_WATER = (0.15, 0.45, 0.9)
_COMMON = {
    "method": ("pbf", "pressure solver: pbf (position-based fluids) or dfsph (divergence-free SPH, boundary "
               "particles)", METHODS),
    "spacing": (0.025, "particle spacing [m] (the particle diameter)"),
    "iterations": (40, "most pressure iterations per sub-step (PBF stops at 0.2 % mean compression; DFSPH, "
                   "per solve, at 0.05 %)"),
    "viscosity": (0.01, "XSPH viscosity coefficient in [0, 1]"),
    "vorticity": (0.0, "vorticity confinement strength (0: off)"),
    "surface_tension": (0.0, "Akinci surface tension coefficient (0: off)"),
    "kernel": ("cubic", "smoothing kernel", tuple(KERNELS)),
    "cfl": (0.0, "CFL number: sub-steps keep v dt <= cfl * spacing (0: the fluid's default, 0.4 on the CPU, 0.2 on GPUs)"),
    "surface": (True, "mesh the liquid surface every frame"),
    "surface_cell": (0.0, "surface grid spacing [m] (0: half the particle spacing)"),
}


def open_box_mesh(lower, upper, open_faces=("top",)):
    """Points (8, 3) and triangles of an axis-aligned box without the named faces (top, bottom,
    left, right, back, front = +y, -y, -x, +x, -z, +z), wound outward."""
    lo, hi = np.asarray(lower, float), np.asarray(upper, float)
    pts = np.array([[(hi if (i >> k) & 1 else lo)[k] for k in range(3)] for i in range(8)])
    quads = {"bottom": [0, 4, 5, 1], "top": [2, 3, 7, 6], "left": [0, 2, 6, 4], "right": [1, 5, 7, 3],
             "back": [0, 1, 3, 2], "front": [4, 6, 7, 5]}
    tris = [[q[0], q[1], q[2]] for name, q in quads.items() if name not in open_faces] + \
           [[q[0], q[2], q[3]] for name, q in quads.items() if name not in open_faces]
    return pts, np.array(tris, dtype=np.int64)


def _collider(kind, *args, **kw):
    """A warpsim collider (``colliders.Sphere`` / ``colliders.TriangleMesh``); where this checkout's
    collider module predates them, a plain object with the same geometry attributes."""
    cls = getattr(C, kind, None)
    if cls is not None:
        return cls(*args, **kw)
    if kind == "Sphere":
        return SimpleNamespace(center=np.asarray(args[0], float), radius=float(args[1]))
    return SimpleNamespace(points=args[0], faces=args[1], solid=False, thickness=kw.get("thickness", 0.0))


SPH_PARTICLE_BYTES = 900.0
"""Host bytes a fluid particle takes while building (measured on the CPU: 704 in dam_break at
spacing 0.0125, 625 in pour's capacity of 400,000)."""
SURFACE_NODE_BYTES = 16.0
"""Bytes a node of the surface grid takes: the splatted field (4), marching cubes' case (1) and
vertex index (4), rounded up for the mesh written each frame."""


def _fit_spacing(value, count, fit):
    """The spacing [m] that makes about ``fit`` of ``count`` things made at ``value`` (count ~ 1/value^3)."""
    return f"{1.01 * float(value) * (float(count) / max(1, fit)) ** (1.0 / 3.0):.3g}"


class FluidScene(Scene):
    """Shared parts: ``self.fluid`` (ParticleFluid) and ``self.surface`` (FluidSurface or None)."""

    fluid = None
    surface = None
    _frame_iterations = 0

    def check_sizes(self, p, particles, lower, upper, param="spacing"):
        """Refuse, before anything is built, ``particles`` fluid particles (made by ``param``:
        ``spacing``, or ``capacity``) and the surface grid over [lower, upper] that do not fit in
        memory: one line naming the parameter, the estimate and the value that fits (a grid at
        half the spacing grows with the particles: one figure for both)."""
        from ..core.memory import available_host_bytes, check_build_memory

        s = float(p["spacing"])
        nodes = 0.0
        if p["surface"]:
            cell = float(p["surface_cell"] or 0.5 * s)
            if not (math.isfinite(cell) and cell > 0.0):
                raise ValueError(f"surface_cell={p['surface_cell']}: it must be > 0 [m] (0: half the spacing)")
            nodes = 1.0
            for lo, hi in zip(lower, upper):
                nodes *= max(2.0, math.ceil((hi - lo) / cell) + 1.0)
        available = available_host_bytes()
        if param == "spacing" and nodes and not p["surface_cell"]:
            check_build_memory("spacing", p["spacing"], round(particles), f"particles (and {nodes:,.0f} surface grid "
                               "nodes)", SPH_PARTICLE_BYTES + SURFACE_NODE_BYTES * nodes / max(particles, 1.0),
                               lambda k: _fit_spacing(s, particles, k), available=available)
            return
        fit = (lambda k: _fit_spacing(s, particles, k)) if param == "spacing" else (lambda k: max(1, k))
        need = check_build_memory(param, p[param], round(particles), "particles", SPH_PARTICLE_BYTES, fit,
                                  available=available)
        if nodes:
            by = "surface_cell" if p["surface_cell"] else "spacing"
            check_build_memory(by, p[by], nodes, "surface grid nodes", SURFACE_NODE_BYTES,
                               lambda k: _fit_spacing(p[by], nodes, k), available=max(0, available - need))

    def make_surface(self, p):
        if p["surface"]:
            cell = p["surface_cell"] or 0.5 * p["spacing"]
            self.surface = FluidSurface(self.fluid, cell=cell)

    def declare_fluid(self, writer):
        writer.add_points("particles", count_changes=True, radius=0.5 * self.fluid.spacing, color=_WATER)
        writer.add_attribute("particles", "warpsim:densityError", "double")
        writer.add_attribute("particles", "warpsim:iterations", "int")  # density iterations during the frame
        if self.surface is not None:
            writer.add_mesh("surface", topology_changes=True, velocities=False, color=_WATER)

    def frame_data(self):
        f = self.fluid
        data = {"particles": {"points": f.positions, "velocities": f.velocities, "ids": f.ids,
                              "warpsim:densityError": f.density_error()[0],
                              "warpsim:iterations": self._frame_iterations}}
        if self.surface is not None:
            data["surface"] = self.surface.mesh().usd_frame()
        return data

    def advance(self, frame_dt, substeps):
        # substeps is a floor; the CFL condition may ask for more within each of them
        before = self.fluid.total_iterations
        for _ in range(substeps):
            self.fluid.advance(frame_dt / substeps)
        self._frame_iterations = self.fluid.total_iterations - before

    def checkpoint(self):
        return self.fluid.checkpoint()

    def restore(self, data):
        self.fluid.restore(data)

    def fluid_args(self, p):
        if not p["spacing"] > 0.0:
            raise ValueError(f"spacing={p['spacing']}: it must be > 0")
        if not p["cfl"] >= 0.0:
            raise ValueError(f"cfl={p['cfl']}: it must be > 0 (or 0: the fluid's default)")
        return {"method": p["method"], "spacing": p["spacing"], "iterations": p["iterations"], "viscosity": p["viscosity"],
                "vorticity": p["vorticity"], "surface_tension": p["surface_tension"], "kernel": p["kernel"],
                "cfl": p["cfl"] or None, "sort_every": 10, "device": self.device}


@register_scene("dam_break", "a water column collapsing in a box (position-based fluids, or DFSPH with "
                "method=dfsph), surface meshed every frame", params={
                    **_COMMON,
                    "column": ((0.4, 0.6, 0.5), "water column size x,y,z [m], in the box's -x corner"),
                    "box": ((1.6, 0.8, 0.5), "container size x,y,z [m]"),
                })
class DamBreak(FluidScene):
    """The column fills [0, column] inside the box [0, box]; the front runs along +x."""

    def build(self, p):
        col, box = np.array(p["column"]), np.array(p["box"])
        if np.any(col <= 0) or np.any(col > box):
            raise ValueError(f"column={tuple(col)} must be positive and fit in box={tuple(box)}")
        if not p["spacing"] > 0.0:
            raise ValueError(f"spacing={p['spacing']}: it must be > 0")
        self.check_sizes(p, float(np.prod(col / p["spacing"])), (0.0, 0.0, 0.0), box)
        self.fluid = ParticleFluid(fluid_block((0, 0, 0), col, p["spacing"]), domain=((0, 0, 0), box),
                                   **self.fluid_args(p))
        self.make_surface(p)

    def declare(self, writer):
        self.declare_fluid(writer)
        pts, tris = open_box_mesh((0, 0, 0), self.params["box"], open_faces=("top", "front"))
        writer.add_static_mesh("container", pts, np.full(len(tris), 3), tris.reshape(-1), color=(0.7, 0.7, 0.7),
                               **CONTAINER)
        add_floor(writer, pts.min(0), pts.max(0))


@register_scene("pour", "a stream poured from a nozzle into a container around a sphere; overflow drains "
                "into sinks", params={
                    **_COMMON,
                    "rate_speed": (2.0, "jet speed at the nozzle [m/s]"),
                    "nozzle_radius": (0.06, "nozzle radius [m]"),
                    "pour_time": (4.0, "how long the nozzle pours [s]"),
                    "capacity": (20000, "most particles alive at once"),
                    "obstacle_radius": (0.08, "radius of the sphere inside the container [m]"),
                })
class Pour(FluidScene):
    """Domain [-0.5, 0.5] x [0, 1] x [-0.5, 0.5] m; an open-top container (a thin triangle-mesh
    collider) of 0.4 x 0.3 x 0.4 m centred on the floor holds a solid sphere; a nozzle at
    y = 0.9 m pours down, slightly off the sphere's axis; what spills over the rim reaches the
    floor around the container, where four sink slabs remove it."""

    def build(self, p):
        if not (p["rate_speed"] > 0 and p["nozzle_radius"] > 0 and p["pour_time"] > 0 and p["obstacle_radius"] > 0):
            raise ValueError("rate_speed, nozzle_radius, pour_time and obstacle_radius must be > 0")
        s = p["spacing"]
        if not 0.0 < s < 0.1:  # the container walls are 0.5 spacing thick; sinks sit 1.5 spacings out
            raise ValueError(f"spacing={s:g}: it must be in (0, 0.1) m for the 0.4 m container")
        if int(p["capacity"]) < 1:
            raise ValueError(f"capacity={p['capacity']}: it must be >= 1 (most particles alive at once)")
        self.check_sizes(p, int(p["capacity"]), (-0.5, 0.0, -0.5), (0.5, 1.0, 0.5), param="capacity")
        half, height = 0.2, 0.3
        self.container = open_box_mesh((-half, 0.0, -half), (half, height, half))
        container = _collider("TriangleMesh", *self.container, thickness=0.5 * s)
        sphere = _collider("Sphere", (0.0, 0.5 * height, 0.0), p["obstacle_radius"])
        nozzle = Nozzle((0.05, 0.9, 0.02), (0.0, -1.0, 0.0), p["nozzle_radius"], p["rate_speed"], stop=p["pour_time"])
        gap = half + 1.5 * s  # sinks on the floor outside the container walls
        sinks = [Sink((-0.5, 0.0, -0.5), (-gap, 0.05, 0.5)), Sink((gap, 0.0, -0.5), (0.5, 0.05, 0.5)),
                 Sink((-gap, 0.0, -0.5), (gap, 0.05, -gap)), Sink((-gap, 0.0, gap), (gap, 0.05, 0.5))]
        self.fluid = ParticleFluid(np.zeros((0, 3)), capacity=p["capacity"], domain=((-0.5, 0, -0.5), (0.5, 1.0, 0.5)),
                                   colliders=[container, sphere], emitters=[nozzle], sinks=sinks,
                                   **self.fluid_args(p))
        self.sphere = sphere
        self.make_surface(p)

    def declare(self, writer):
        self.declare_fluid(writer)
        pts, tris = self.container
        writer.add_static_mesh("container", pts, np.full(len(tris), 3), tris.reshape(-1), color=(0.7, 0.7, 0.7),
                               **CONTAINER)
        writer.add_sphere("obstacle", tuple(self.sphere.center), self.sphere.radius, color=(0.8, 0.4, 0.2))
        writer.add_plane("floor", size=1.0)
