"""Mass-spring soft bodies from triangle meshes.

``add_soft_body(builder, points, faces, ...)`` turns any triangle mesh into particles joined
by damped springs:

- edge springs: one per mesh edge;
- bending springs: one per interior edge (an edge shared by two faces), joining the two
  vertices opposite that edge, so folding the surface stretches them;
- shape-keeping interior springs (``interior="lattice"``, closed meshes only): a coarse cubic
  lattice of extra particles inside the mesh (generalised winding number > 1/2), each joined
  to its 26 lattice neighbours, and every surface vertex tied to its ``ties`` nearest lattice
  particles. The lattice resists volume change, so a closed shape cannot collapse.

Mass: ``mass`` [kg] per particle, or ``total_mass`` [kg] spread over the surface by vertex area
(a third of each adjacent face's area; ``mass_distribution="area"``) or equally over the
vertices (``"uniform"``, the lecture's point masses: no tiny masses where triangles are small,
so larger stable steps), with ``interior_mass_fraction`` of it shared equally by the lattice
particles.

Loaders: ``load_mesh(path)`` reads OBJ, STL, PLY, GLB/GLTF and OFF through trimesh and USD
(.usd/.usda/.usdc) through pxr (imported only then); vertices are welded by position so that
formats storing unshared vertices (STL) give a connected mesh.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from . import meshtools
from ..core import checks
from .colliders import parse_pose, check_triangles, quat_rotate
from .mesh_io import MESH_EXTENSIONS, USD_EXTENSIONS, load_mesh, load_usd_mesh, triangulate  # noqa: F401 (moved)

INTERIOR_MODES = ("lattice", "none")

# 13 of the 26 lattice neighbour offsets (the other 13 are their negatives)
_LATTICE_OFFSETS = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)
                             if (i, j, k) > (0, 0, 0)], dtype=np.int64)


@dataclass
class SoftBody:
    """Where a soft body lives in its builder (all indices global to the builder).

    Particles ``particle_start .. particle_start + particle_count``: the ``surface_count`` mesh
    vertices first, then the ``interior_count`` lattice particles. ``faces`` (F, 3) are the
    surface triangles in particle indices. Springs ``spring_start ..`` come in the order edges,
    bends, lattice, ties, with the counts below."""

    particle_start: int
    surface_count: int
    interior_count: int
    faces: np.ndarray
    spring_start: int
    edge_count: int
    bend_count: int
    lattice_count: int
    tie_count: int

    @property
    def particle_count(self) -> int:
        return self.surface_count + self.interior_count

    @property
    def spring_count(self) -> int:
        return self.edge_count + self.bend_count + self.lattice_count + self.tie_count

    @property
    def surface_indices(self) -> np.ndarray:
        return np.arange(self.particle_start, self.particle_start + self.surface_count)

    @property
    def interior_indices(self) -> np.ndarray:
        s = self.particle_start + self.surface_count
        return np.arange(s, s + self.interior_count)

    def spring_range(self, kind: str) -> range:
        """Spring indices of one kind: "edge", "bend", "lattice" or "tie"."""
        counts = {"edge": self.edge_count, "bend": self.bend_count, "lattice": self.lattice_count,
                  "tie": self.tie_count}
        if kind not in counts:
            raise ValueError(f"spring kind {kind!r} is unknown; use one of {list(counts)}")
        start = self.spring_start
        for name, count in counts.items():
            if name == kind:
                break
            start += count
        return range(start, start + counts[kind])


def bending_pairs(faces) -> np.ndarray:
    """For every interior edge (two faces), the two vertices opposite it, shape (E_interior, 2)."""
    faces = np.asarray(faces)
    edges, counts, edge_of = meshtools.edge_topology(faces)
    n_faces = len(faces)
    # vertex opposite directed edge k of face f: edge (0,1) -> 2, (1,2) -> 0, (2,0) -> 1
    opposite = np.concatenate([faces[:, 2], faces[:, 0], faces[:, 1]])
    order = np.argsort(edge_of, kind="stable")
    sorted_edges = edge_of[order]
    interior = np.flatnonzero(counts == 2)
    starts = np.searchsorted(sorted_edges, interior)
    a = opposite[order[starts]]
    b = opposite[order[starts + 1]]
    if np.any(a == b):
        k = int(interior[np.flatnonzero(a == b)[0]])
        raise ValueError(f"mesh edge {tuple(edges[k])} joins two faces with the same third vertex (a duplicated "
                         f"face among {n_faces}); remove duplicate faces")
    return np.stack([a, b], axis=1)


def interior_lattice(points, faces, cells: int):
    """Lattice particles inside a closed mesh and their neighbour pairs.

    The bounding box's longest side is split into ``cells`` cells; cell centres with winding
    number > 1/2 that lie at least a quarter cell from every vertex are kept. Returns
    (positions (N, 3), pairs (M, 2) of lattice indices, spacing [m])."""
    points = np.asarray(points, dtype=np.float64)
    lo, hi = points.min(axis=0), points.max(axis=0)
    h = float((hi - lo).max()) / cells
    counts = np.maximum(1, np.ceil((hi - lo) / h - 1e-9).astype(np.int64))
    origin = 0.5 * (lo + hi) - 0.5 * h * counts
    ijk = np.stack(np.meshgrid(*[np.arange(c) for c in counts], indexing="ij"), -1).reshape(-1, 3)
    centers = origin + (ijk + 0.5) * h
    inside = meshtools.winding_number(points, faces, centers) > 0.5
    near = np.zeros(len(centers), dtype=bool)
    for s in range(0, len(centers), 512):
        d2 = ((centers[s:s + 512, None, :] - points[None, :, :]) ** 2).sum(-1)
        near[s:s + 512] = d2.min(axis=1) < (0.25 * h) ** 2
    keep = inside & ~near
    grid = -np.ones(tuple(counts), dtype=np.int64)
    kept = ijk[keep]
    grid[tuple(kept.T)] = np.arange(len(kept))
    pairs = []
    for off in _LATTICE_OFFSETS:
        nb = kept + off
        ok = np.all((nb >= 0) & (nb < counts), axis=1)
        j = np.full(len(kept), -1)
        j[ok] = grid[tuple(nb[ok].T)]
        sel = j >= 0
        pairs.append(np.stack([np.flatnonzero(sel), j[sel]], axis=1))
    pair_array = np.concatenate(pairs) if pairs else np.zeros((0, 2), dtype=np.int64)
    return centers[keep], pair_array, h


def _lattice_hint(points, faces, cells, budget=2.0e7):
    """The fix for an empty lattice: the smallest larger ``lattice_cells`` (up to 64, within a
    winding-number cost budget) that fits a particle, or interior='none' when none does."""
    c = tried = cells
    while c < 64:
        c = min(64, 2 * c)
        if (c ** 3) * len(faces) > budget:
            break
        if len(interior_lattice(points, faces, c)[0]):
            return f"lattice_cells={c} fits one (raise lattice_cells), or pass interior='none'"
        tried = c
    return (f"the mesh is too thin for a lattice of up to lattice_cells={tried}; pass interior='none' (surface "
            "springs only) or thicken the mesh")


def _check_coefficient(owner, name, value, positive=False):
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{owner} {name} must be a number, got {value!r}") from None
    if not math.isfinite(v) or v < 0.0 or (positive and v == 0.0):
        bound = "> 0" if positive else ">= 0"
        raise ValueError(f"{owner} {name} is {value}; it must be finite and {bound}")
    return v


def add_soft_body(builder, points, faces, *, position=(0.0, 0.0, 0.0), rotation=None, scale=1.0,
                  velocity=(0.0, 0.0, 0.0), mass=None, total_mass=1.0, mass_distribution="area",
                  interior_mass_fraction=0.25,
                  stiffness=1.0e3, damping=1.0, bend_stiffness=None, bend_damping=None, interior="lattice",
                  lattice_cells=4, interior_stiffness=None, interior_damping=None, ties=4, radius=0.0,
                  name="soft body") -> SoftBody:
    """Add a mass-spring soft body made from a triangle mesh to ``builder`` (see module doc).

    Args:
        points: (V, 3) mesh vertices [m] (local frame); faces: (F, 3) vertex indices.
        position, rotation, scale: placement: x = position + R (scale p); rotation a quaternion
            (x, y, z, w) or a 3x3 matrix.
        velocity: initial velocity of every particle [m/s].
        mass: mass of every particle [kg]; if None, ``total_mass`` [kg] is spread over the surface
            by ``mass_distribution`` ("area" or "uniform"), ``interior_mass_fraction`` of it on the
            lattice particles.
        stiffness, damping: edge springs [N/m], [N s/m]; ``bend_*`` and ``interior_*`` default to
            the same values (interior covers lattice and tie springs).
        interior: "lattice" (closed meshes) or "none".
        lattice_cells: lattice cells along the mesh's longest bounding-box side.
        ties: springs from each surface vertex to its nearest lattice particles.
        radius: collision radius of every particle [m].

    Returns a SoftBody describing the particle and spring index ranges."""
    points, faces = check_triangles(points, faces, name)
    meshtools.check_manifold(faces, name)
    unused = np.setdiff1d(np.arange(len(points)), np.unique(faces))
    if len(unused):
        raise ValueError(f"{name}: vertex {int(unused[0])} belongs to no face; remove unused vertices "
                         "(warpsim.bodies.meshtools.compact)")
    if mass_distribution not in ("area", "uniform"):
        raise ValueError(f"{name} mass_distribution {mass_distribution!r} is unknown; use 'area' or 'uniform'")
    if interior not in INTERIOR_MODES:
        raise ValueError(f"{name} interior {interior!r} is unknown; use one of {list(INTERIOR_MODES)}")
    k_edge = _check_coefficient(name, "stiffness", stiffness)
    c_edge = _check_coefficient(name, "damping", damping)
    k_bend = _check_coefficient(name, "bend_stiffness", k_edge if bend_stiffness is None else bend_stiffness)
    c_bend = _check_coefficient(name, "bend_damping", c_edge if bend_damping is None else bend_damping)
    k_in = _check_coefficient(name, "interior_stiffness", k_edge if interior_stiffness is None else interior_stiffness)
    c_in = _check_coefficient(name, "interior_damping", c_edge if interior_damping is None else interior_damping)
    scale = _check_coefficient(name, "scale", scale, positive=True)
    radius = _check_coefficient(name, "radius", radius)
    fraction = _check_coefficient(name, "interior_mass_fraction", interior_mass_fraction)
    if fraction >= 1.0:
        raise ValueError(f"{name} interior_mass_fraction {fraction} must be < 1 (the surface needs mass)")
    if mass is not None:
        mass = _check_coefficient(name, "mass", mass, positive=True)
    else:
        total_mass = _check_coefficient(name, "total_mass", total_mass, positive=True)
    ties = checks.count(ties, f"{name} ties", fix="each surface vertex needs >= 1 tie to the lattice")
    pos, rot = parse_pose(position, rotation, name)
    velocity = checks.vec3(velocity, f"{name} velocity")

    world = pos + quat_rotate(rot, scale * points) if len(points) else points  # (N, 3) at once, the same bits
    lattice = np.zeros((0, 3))
    lattice_pairs = np.zeros((0, 2), dtype=np.int64)
    tie_pairs = np.zeros((0, 2), dtype=np.int64)
    if interior == "lattice":
        if not meshtools.is_closed(faces):
            loops = meshtools.boundary_loops(faces)
            raise ValueError(f"{name} is not closed ({len(loops)} boundary loop(s), e.g. around vertex "
                             f"{int(loops[0][0]) if loops else -1}) or not consistently wound; the shape-keeping "
                             "lattice needs a closed, consistently wound mesh: pass interior='none' or close it")
        cells = checks.count(lattice_cells, f"{name} lattice_cells", fix="give lattice cells along the longest side, "
                             "e.g. 4")
        volume = meshtools.signed_volume(world, faces)
        size = float(np.ptp(world, axis=0).max())
        if abs(volume) <= 1e-9 * size**3:
            raise ValueError(f"{name} is closed but encloses no volume (signed volume {volume:.3g} m^3 for a "
                             f"{size:.3g} m wide mesh: it is flat or folded onto itself), so no lattice fits inside; "
                             "pass interior='none' or give a mesh that encloses a volume")
        if volume < 0.0:
            faces = faces[:, ::-1]
        lattice, lattice_pairs, _ = interior_lattice(world, faces, cells)
        if len(lattice) == 0:
            raise ValueError(f"{name}: no lattice particle fits inside the mesh with lattice_cells={cells}; "
                             f"{_lattice_hint(world, faces, cells)}")
        k = min(ties, len(lattice))
        nearest = np.empty((len(world), k), dtype=np.int64)
        for s in range(0, len(world), 512):
            d2 = ((world[s:s + 512, None, :] - lattice[None, :, :]) ** 2).sum(-1)
            nearest[s:s + 512] = np.argsort(d2, axis=1)[:, :k]
        tie_pairs = np.stack([np.repeat(np.arange(len(world)), k), nearest.reshape(-1)], axis=1)

    nv, ni = len(world), len(lattice)
    if mass is not None:
        masses = np.full(nv + ni, mass)
    else:
        surface_share = total_mass * (1.0 - fraction) if ni else total_mass
        areas = meshtools.vertex_areas(world, faces)
        if mass_distribution == "uniform":
            areas = np.ones(nv)
        if areas.sum() <= 0.0:
            raise ValueError(f"{name} has zero surface area; cannot spread total_mass by area")
        masses = np.concatenate([surface_share * areas / areas.sum(), np.full(ni, (total_mass - surface_share) / max(ni, 1))])
        zero = np.flatnonzero(masses[:nv] <= 0.0)
        if len(zero):
            raise ValueError(f"{name}: vertex {int(zero[0])} touches only zero-area faces and would get no mass; "
                             "remove degenerate faces or give mass=")

    start = builder.particle_count
    spring_start = builder.spring_count
    builder.add_particles(np.concatenate([world, lattice]), np.tile(velocity, (nv + ni, 1)), masses, radius)
    edges, _, _ = meshtools.edge_topology(faces)
    bends = bending_pairs(faces)
    groups = [(edges, 0, 0, k_edge, c_edge), (bends, 0, 0, k_bend, c_bend), (lattice_pairs, nv, nv, k_in, c_in),
              (tie_pairs, 0, nv, k_in, c_in)]  # (pairs, offsets of their two ends, stiffness, damping)
    pairs = [np.asarray(g, dtype=np.int64).reshape(-1, 2) + (start + a, start + b) for g, a, b, _, _ in groups]
    counts = [len(g) for g in pairs]
    builder.add_springs(np.concatenate(pairs), np.repeat([g[3] for g in groups], counts),
                        np.repeat([g[4] for g in groups], counts))  # rest lengths rounded as add_spring's
    return SoftBody(start, nv, ni, faces + start, spring_start, len(edges), len(bends), len(lattice_pairs),
                    len(tie_pairs))
