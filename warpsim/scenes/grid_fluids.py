"""Eulerian grid-fluid scenes: ``smoke`` (a buoyant plume rising around a sphere), ``liquid``
(a level-set liquid sloshing in a tank) and ``flip_splash`` (a FLIP block dropped into a pool).

Every frame the fluid surface is meshed with marching cubes (``warpsim.meshing.marching_cubes``) and written as a
``Mesh`` whose topology changes per frame; smoke density also goes out as ``Points`` at the smoky
cell centres with a ``density`` primvar (displayable by any USD viewer), FLIP particles as
``Points`` with persistent ids. Each frame takes as many equal sub-steps as the CFL number asks
(at least ``--substeps``): n = ceil(max face speed x frame time / (cfl x dx)).
"""
from __future__ import annotations

import math
from typing import ClassVar

import numpy as np

from ..grid_fluids.flip import FlipLiquid
from ..grid_fluids.levelset_liquid import LevelSetLiquid
from ..grid_fluids.mac_grid import MacGrid
from ..meshing.marching_cubes import MarchingCubes
from ..grid_fluids.smoke import Smoke
from ..usd.sink import display_hints
from . import CONTAINER, Scene, add_floor, register_scene

_WATER = (0.15, 0.45, 0.9)
_SMOKE = (0.75, 0.75, 0.8)
SMOKE_CELL_BYTES = 350.0
"""Host bytes a smoke grid cell takes while building (measured: 270 at resolution 64 and 96)."""
LIQUID_CELL_BYTES, LIQUID_PARTICLE_BYTES = 300.0, 25.0
"""Host bytes a level-set liquid cell takes while building, plus per marker particle per band
cell (measured with 16 particles a cell: 653 bytes a cell at resolution 64, 536 at 96)."""
FLIP_CELL_BYTES, FLIP_PARTICLE_BYTES = 300.0, 110.0
"""Host bytes a FLIP cell takes while building, plus per particle per cell (measured with 8
particles a cell: 1,094 bytes a cell at resolution 64)."""
_COMMON = {
    "cfl": (1.0, "CFL number: sub-steps keep max speed x dt <= cfl x dx"),
    "max_substeps": (32, "most sub-steps per frame"),
    "tol": (1.0e-5, "pressure CG tolerance (relative residual)"),
    "preconditioner": ("mg", "pressure CG preconditioner (mg: multigrid V-cycle)", ("mg", "jacobi", "rbgs")),
}


def _open_box(lower, upper):
    """Points and triangles of an axis-aligned box without its top (+y) face, wound outward."""
    lo, hi = np.asarray(lower, float), np.asarray(upper, float)
    pts = np.array([[(hi if (i >> k) & 1 else lo)[k] for k in range(3)] for i in range(8)])
    quads = [[0, 4, 5, 1], [0, 2, 6, 4], [1, 5, 7, 3], [0, 1, 3, 2], [4, 6, 7, 5]]
    tris = [[q[0], q[1], q[2]] for q in quads] + [[q[0], q[2], q[3]] for q in quads]
    return pts, np.array(tris, dtype=np.int64)


def _surface_frame(mesher, field, iso=0.0):
    return mesher.mesh(field, iso).usd_frame()


class GridFluidScene(Scene):
    """Shared stepping: CFL sub-steps over a MacGrid held in ``self.grid`` by ``self.solver``."""

    grid = None
    solver = None

    def check_common(self, p):
        if not p["cfl"] > 0.0:
            raise ValueError(f"cfl={p['cfl']}: it must be > 0")
        if p["max_substeps"] < 1:
            raise ValueError(f"max_substeps={p['max_substeps']}: it must be >= 1")
        if not 0.0 < p["tol"] < 1.0:
            raise ValueError(f"tol={p['tol']}: it must be in (0, 1)")

    def check_cells(self, p, cells, bytes_each, fit_of):
        """Refuse (one line naming ``resolution``, the estimate and the value that fits) a grid of
        ``cells`` cells at ``bytes_each`` bytes a cell (measured while building, grid fields,
        pressure solver levels, particles and mesher together) before anything is allocated."""
        from ..core.memory import check_build_memory

        check_build_memory("resolution", p["resolution"], cells, "grid cells", bytes_each, fit_of)

    def max_speed(self):
        return max(float(np.abs(f.numpy()).max()) for f in self.grid.faces)

    def advance(self, frame_dt, substeps):
        p = self.params
        n = max(int(substeps), math.ceil(self.max_speed() * frame_dt / (p["cfl"] * self.grid.dx) - 1e-9))
        n = min(n, p["max_substeps"])
        for _ in range(n):
            self.solver.step(frame_dt / n)

    def checkpoint(self):
        return self.solver.checkpoint()

    def restore(self, data):
        self.solver.restore(data)

    def make_mesher(self, inside="below"):
        """Marching cubes over the cell centres, closing surfaces cut by the domain walls."""
        g = self.grid
        origin = tuple(o + 0.5 * g.dx for o in g.origin)
        return MarchingCubes(g.shape, g.dx, origin, device=self.device, close_boundary=True, inside=inside)


@register_scene("smoke", "a buoyant smoke plume rising around a sphere (MAC grid, MacCormack advection, "
                "vorticity confinement); density as points with a density primvar plus an iso-surface", params={
                    **_COMMON,
                    "resolution": (24, "cells across the 1 m wide domain (height 1.5 m)"),
                    "vorticity": (2.0, "vorticity confinement epsilon (0: off)"),
                    "temperature_buoyancy": (4.0, "buoyancy per unit temperature [m/s^2]"),
                    "density_buoyancy": (0.5, "downward pull per unit density [m/s^2]"),
                    "sphere_radius": (0.15, "radius of the obstacle sphere [m]"),
                    "iso": (0.1, "density of the written iso-surface"),
                    "threshold": (0.02, "cells above this density are written as points"),
                    "scheme": ("maccormack", "advection scheme", ("semi_lagrangian", "maccormack", "bfecc")),
                }, fps=24.0, substeps=1)
class SmokeScene(GridFluidScene):
    """Domain [-0.5, 0.5] x [0, 1.5] x [-0.5, 0.5] m, open at the top; a hot, dense source near the
    floor under a sphere at (0, 0.6, 0)."""

    smoke_params: ClassVar[dict] = {"resolution": 8}

    def build(self, p):
        self.check_common(p)
        n = p["resolution"]
        if n < 4:
            raise ValueError(f"resolution={n}: it must be >= 4")
        if not 0.0 < p["sphere_radius"] < 0.4:
            raise ValueError(f"sphere_radius={p['sphere_radius']}: it must be in (0, 0.4) m")
        # measured while building on the CPU: 270 bytes a cell (resolution 64 and 96)
        self.check_cells(p, n * (3 * n // 2) * n, SMOKE_CELL_BYTES, lambda k: max(4, int((k / 1.5) ** (1 / 3))))
        self.grid = MacGrid((n, 3 * n // 2, n), 1.0 / n, origin=(-0.5, 0.0, -0.5), open_sides=("+y",),
                            device=self.device)
        self.sphere = ((0.0, 0.6, 0.0), p["sphere_radius"])
        self.grid.add_sphere(*self.sphere)
        self.solver = Smoke(self.grid, scheme=p["scheme"], density_buoyancy=p["density_buoyancy"],
                            temperature_buoyancy=p["temperature_buoyancy"], vorticity=p["vorticity"], tol=p["tol"],
                            preconditioner=p["preconditioner"])
        h = max(0.1, 1.5 / n)
        self.solver.add_source((-0.12, 0.05, -0.12), (0.12, 0.05 + h, 0.12), density=1.0, temperature=1.0)
        self.mesher = self.make_mesher(inside="above")
        self._centres = self.grid.positions("center").reshape(-1, 3).astype(np.float32)

    def declare(self, writer):
        # cell-centre samples: widths (diameters) grow and displayOpacity rises with the density, so
        # point-drawing tools show a plume; warpsim:cellSize lets volume renderers rebuild the grid
        writer.add_points("smoke", count_changes=True, dynamic_widths=True, velocities=False, color=_SMOKE)
        writer.add_primvar("smoke", "density", "float[]", "vertex")
        writer.add_primvar("smoke", "displayOpacity", "float[]", "vertex")
        writer.add_attribute("smoke", "warpsim:cellSize", "double", value=self.grid.dx)
        # the iso-surface is a guide (shown on request) so that it does not hide the plume
        display_hints(writer.add_mesh("smoke_surface", topology_changes=True, velocities=False, color=_SMOKE),
                      purpose="guide")
        writer.add_sphere("obstacle", *self.sphere, color=(0.8, 0.4, 0.2))
        writer.add_plane("floor", size=1.0)

    def frame_data(self):
        rho = self.solver.density.numpy().reshape(-1)
        keep = np.flatnonzero(rho > self.params["threshold"])
        rho = rho[keep].astype(np.float32)
        fill = np.clip(rho, 0.0, 1.0)
        return {"smoke": {"points": self._centres[keep], "ids": keep.astype(np.int32), "density": rho,
                          "widths": self.grid.dx * (0.4 + 0.6 * fill), "displayOpacity": 0.8 * fill},
                "smoke_surface": _surface_frame(self.mesher, self.solver.density, self.params["iso"])}


@register_scene("liquid", "a level-set liquid sloshing in a tank (particle level set, ghost-fluid free surface), "
                "surface meshed every frame", params={
                    **_COMMON,
                    "resolution": (32, "cells along the 1 m long tank (0.6 m high, 0.4 m deep)"),
                    "tilt": (0.3, "initial surface slope (height change per metre along x)"),
                    "depth": (0.3, "mean liquid depth [m]"),
                    "particle_level_set": (True, "correct the level set with marker particles"),
                    "particles_per_cell": (16, "marker particles per band cell"),
                }, fps=30.0, substeps=1)
class LiquidScene(GridFluidScene):
    """Tank [0, 1] x [0, 0.6] x [0, 0.4] m; the surface starts as the plane
    y = depth + tilt (x - 0.5) and sloshes under gravity."""

    smoke_params: ClassVar[dict] = {"resolution": 10, "particles_per_cell": 4}

    def build(self, p):
        self.check_common(p)
        n = p["resolution"]
        if n < 8:
            raise ValueError(f"resolution={n}: it must be >= 8")
        if not (0.05 < p["depth"] < 0.55 and abs(p["tilt"]) < 1.0):
            raise ValueError(f"depth={p['depth']} must be in (0.05, 0.55) m and |tilt|={abs(p['tilt'])} below 1")
        dx = 1.0 / n
        # the band's marker particles scale with the surface (n^2), the fields with n^3: bounded per cell
        self.check_cells(p, n * max(4, round(0.6 / dx)) * max(4, round(0.4 / dx)),
                         LIQUID_CELL_BYTES + LIQUID_PARTICLE_BYTES * max(0, int(p["particles_per_cell"])),
                         lambda k: max(8, int((k / 0.24) ** (1 / 3))))
        self.grid = MacGrid((n, max(4, round(0.6 / dx)), max(4, round(0.4 / dx))), dx, device=self.device)
        depth, tilt = p["depth"], p["tilt"]
        self.solver = LevelSetLiquid(self.grid, lambda x: x[..., 1] - (depth + tilt * (x[..., 0] - 0.5)),
                                     particle_level_set=p["particle_level_set"], tol=p["tol"],
                                     preconditioner=p["preconditioner"], particles_per_cell=p["particles_per_cell"])
        self.mesher = self.make_mesher()

    def declare(self, writer):
        writer.add_mesh("surface", topology_changes=True, velocities=False, color=_WATER)
        writer.add_attribute("surface", "warpsim:volume", "double")
        pts, tris = _open_box(self.grid.lower, self.grid.upper)
        writer.add_static_mesh("tank", pts, np.full(len(tris), 3), tris.reshape(-1), color=(0.7, 0.7, 0.7),
                               **CONTAINER)
        add_floor(writer, self.grid.lower, self.grid.upper)

    def frame_data(self):
        data = _surface_frame(self.mesher, self.solver.phi)
        data["warpsim:volume"] = self.solver.volume()
        return {"surface": data}


@register_scene("flip_splash", "a FLIP liquid block dropped into a pool (FLIP/PIC blend, density correction, "
                "reseeding); particles and their surface meshed every frame", params={
                    **_COMMON,
                    "resolution": (24, "cells along the 1 m wide domain (0.8 m high, 0.5 m deep)"),
                    "flip_ratio": (0.95, "FLIP share of the velocity update (1: FLIP, 0: PIC)"),
                    "pool_depth": (0.2, "depth of the pool [m]"),
                    "block": ((0.35, 0.45, 0.1, 0.65, 0.7, 0.4), "falling block lower,upper corners [m]"),
                    "particles_per_cell": (8, "particles seeded per cell"),
                    "reseed": (True, "reseed sparse interior cells and cull crowded ones every step"),
                    "density_correction": (1.0, "volume correction strength in [0, 1] (0: off)"),
                }, fps=30.0, substeps=1)
class FlipSplashScene(GridFluidScene):
    """Domain [0, 1] x [0, 0.8] x [0, 0.5] m: a pool fills y < pool_depth, the block falls into it."""

    smoke_params: ClassVar[dict] = {"resolution": 8, "particles_per_cell": 2, "block": (0.3, 0.5, 0.1, 0.7, 0.7, 0.4)}

    def build(self, p):
        self.check_common(p)
        n = p["resolution"]
        if n < 8:
            raise ValueError(f"resolution={n}: it must be >= 8")
        dx = 1.0 / n
        self.check_cells(p, n * max(4, round(0.8 / dx)) * max(4, round(0.5 / dx)),
                         FLIP_CELL_BYTES + FLIP_PARTICLE_BYTES * max(0, int(p["particles_per_cell"])),
                         lambda k: max(8, int((k / 0.4) ** (1 / 3))))
        self.grid = MacGrid((n, max(4, round(0.8 / dx)), max(4, round(0.5 / dx))), dx, device=self.device)
        b = np.asarray(p["block"], float)
        lo, hi = b[:3], b[3:]
        if np.any(hi <= lo) or np.any(lo < 0) or np.any(hi > np.asarray(self.grid.upper)):
            raise ValueError(f"block={tuple(b)}: need lower < upper inside the domain {self.grid.upper}")
        if not 0.0 < p["pool_depth"] < 0.5:
            raise ValueError(f"pool_depth={p['pool_depth']}: it must be in (0, 0.5) m")
        self.solver = FlipLiquid(self.grid, flip_ratio=p["flip_ratio"], particles_per_cell=p["particles_per_cell"],
                                 reseed_every=1 if p["reseed"] else 0, tol=p["tol"],
                                 preconditioner=p["preconditioner"], capacity=None,
                                 density_correction=p["density_correction"])
        c = self.grid.positions("center")
        pool = c[..., 1] < p["pool_depth"]
        block = np.all((c >= lo) & (c <= hi), axis=-1)
        self.solver.add_cells(pool | block)
        self.mesher = self.make_mesher()

    def declare(self, writer):
        writer.add_points("particles", count_changes=True, radius=0.25 * self.grid.dx, color=_WATER)
        writer.add_mesh("surface", topology_changes=True, velocities=False, color=_WATER)
        pts, tris = _open_box(self.grid.lower, self.grid.upper)
        writer.add_static_mesh("tank", pts, np.full(len(tris), 3), tris.reshape(-1), color=(0.7, 0.7, 0.7),
                               **CONTAINER)
        add_floor(writer, self.grid.lower, self.grid.upper)

    def frame_data(self):
        P = self.solver.particles
        return {"particles": {"points": P.numpy("x"), "velocities": P.numpy("v"), "ids": P.numpy("id")},
                "surface": _surface_frame(self.mesher, self.solver.surface())}
