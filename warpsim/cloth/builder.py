"""Cloth builder: particle grids or triangle meshes joined by structural, shear and bend springs.

    builder = ws.ModelBuilder()
    cloth = add_cloth_grid(builder, resolution=(20, 20), size=(1.0, 1.0), origin=(-0.5, 1.5, 0.0),
                           u_axis=(1, 0, 0), v_axis=(0, 0, 1), density=0.2, pin=["corner_00", "corner_10"])
    model = builder.finalize()

Spring kinds (each with its own stiffness [N/m] and damping [N s/m]):
- grid: ``structural`` joins neighbours along u and v, ``shear`` both diagonals of every cell,
  ``bend`` the skip-one neighbours along u and v (particles two apart);
- mesh: ``structural`` every edge, ``shear`` the two vertices opposite each interior edge (the
  diagonal of the quad two triangles form), ``bend`` skip-one neighbours: for every edge i-j the
  neighbour k of j that continues the line i->j most straightly (within 30 degrees).

Mass comes from an area ``density`` [kg/m^2] (lumped: each particle gets its share of the
surrounding area) or a uniform ``particle_mass`` [kg]. Pinned particles get mass 0 (they never
move under forces). The returned :class:`Cloth` keeps the triangle topology for USD meshes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..core import checks

SPRING_KINDS = ("structural", "shear", "bend")
GRID_PIN_NAMES = ("corners", "corner_00", "corner_10", "corner_01", "corner_11", "edge_u0", "edge_u1", "edge_v0",
                  "edge_v1")


@dataclass
class Cloth:
    """One cloth added to a ModelBuilder.

    particle_offset / particle_count: its particles are [offset, offset + count) in the model.
    triangles: (T, 3) int32 model particle indices, counter-clockwise seen from the front (for
        grids the side the normal u x v points to).
    springs: kind -> (first spring index, count) in the model, kinds ``structural``, ``shear``,
        ``bend``.
    pinned: model indices of pinned particles, int64 (P,).
    grid_shape: (rows, columns) = (resolution v + 1, resolution u + 1) for grids, else None;
        particle (i along u, j along v) is ``index(i, j)``.
    """

    particle_offset: int
    particle_count: int
    triangles: np.ndarray
    springs: dict = field(default_factory=dict)
    pinned: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    grid_shape: tuple | None = None

    def index(self, i: int, j: int) -> int:
        """Model index of grid particle (i along u, j along v)."""
        if self.grid_shape is None:
            raise ValueError("Cloth.index(i, j) needs a grid cloth (add_cloth_grid)")
        rows, cols = self.grid_shape
        if not (0 <= i < cols and 0 <= j < rows):
            raise ValueError(f"grid particle ({i}, {j}) is outside the {cols} x {rows} grid")
        return self.particle_offset + j * cols + i

    @property
    def spring_count(self) -> int:
        return sum(count for _, count in self.springs.values())

    @property
    def face_vertex_counts(self) -> np.ndarray:
        """USD faceVertexCounts: 3 per triangle."""
        return np.full(len(self.triangles), 3, dtype=np.int32)

    @property
    def face_vertex_indices(self) -> np.ndarray:
        """USD faceVertexIndices, local to this cloth's points (index - particle_offset)."""
        return (self.triangles - self.particle_offset).reshape(-1).astype(np.int32)


def _spring_params(stiffness, damping, kinds=SPRING_KINDS):
    """Per-kind (stiffness, damping) from dicts or scalars; validated."""
    out = {}
    for kind in kinds:
        k = stiffness.get(kind, 0.0) if isinstance(stiffness, dict) else stiffness
        d = damping.get(kind, 0.0) if isinstance(damping, dict) else damping
        for name, value in (("stiffness", k), ("damping", d)):
            if not math.isfinite(float(value)) or float(value) < 0.0:
                raise ValueError(f"cloth {kind} {name} is {value}; it must be finite and >= 0")
        out[kind] = (float(k), float(d))
    return out


def _check_count(value, what):
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ValueError(f"{what} = {value!r}; give an integer >= 1")
    return int(value)


def _positive(value, what):
    value = float(value)
    if not math.isfinite(value) or value <= 0.0:
        raise ValueError(f"{what} = {value}; it must be > 0")
    return value


def _add_cloth(builder, positions, velocity, masses, radius, triangles, spring_pairs, params, pinned_local):
    """Append particles and springs to ``builder`` (validated here, appended in bulk so that
    million-particle sheets build in seconds); returns a Cloth."""
    offset = builder.particle_count
    n = len(positions)
    pinned_local = np.unique(np.asarray(pinned_local, dtype=np.int64).reshape(-1))
    masses = np.array(masses, dtype=np.float64)
    masses[pinned_local] = 0.0
    positions = np.asarray(positions, dtype=np.float64)
    builder.particle_q.extend(map(tuple, positions.tolist()))
    builder.particle_qd.extend([tuple(velocity)] * n)
    builder.particle_mass.extend(masses.tolist())
    builder.particle_radius.extend([radius] * n)
    springs = {}
    for kind in SPRING_KINDS:
        pairs = np.asarray(spring_pairs.get(kind, np.zeros((0, 2))), dtype=np.int64).reshape(-1, 2)
        k, d = params[kind]
        first = builder.spring_count
        if len(pairs) and (k > 0.0 or d > 0.0):
            rest = np.linalg.norm(positions[pairs[:, 0]] - positions[pairs[:, 1]], axis=1)
            builder.spring_indices.extend(map(tuple, (pairs + offset).tolist()))
            builder.spring_rest_length.extend(rest.tolist())
            builder.spring_stiffness.extend([k] * len(pairs))
            builder.spring_damping.extend([d] * len(pairs))
        springs[kind] = (first, builder.spring_count - first)
    return Cloth(offset, n, (np.asarray(triangles, dtype=np.int64) + offset).astype(np.int32), springs,
                 pinned_local + offset)


def grid_springs(nu: int, nv: int) -> dict:
    """Spring pairs (local indices, row-major, particle (i, j) = j * (nu + 1) + i) of a grid with
    ``nu`` x ``nv`` cells: dict kind -> (S, 2) int64."""
    cols, rows = nu + 1, nv + 1
    idx = np.arange(rows * cols).reshape(rows, cols)

    def pairs(a, b):
        return np.stack([a.reshape(-1), b.reshape(-1)], axis=1)

    structural = np.concatenate([pairs(idx[:, 1:], idx[:, :-1]), pairs(idx[1:, :], idx[:-1, :])])
    shear = np.concatenate([pairs(idx[1:, 1:], idx[:-1, :-1]), pairs(idx[1:, :-1], idx[:-1, 1:])])
    bend = np.concatenate([pairs(idx[:, 2:], idx[:, :-2]), pairs(idx[2:, :], idx[:-2, :])])
    return {"structural": structural, "shear": shear, "bend": bend}


def grid_pins(pin, nu: int, nv: int) -> np.ndarray:
    """Local indices named by ``pin``: None, or a list of grid pin names (see GRID_PIN_NAMES) and
    local particle indices."""
    if pin is None:
        return np.zeros(0, dtype=np.int64)
    if isinstance(pin, (str, int, np.integer)):
        pin = [pin]
    cols, rows = nu + 1, nv + 1
    idx = np.arange(rows * cols).reshape(rows, cols)
    named = {
        "corner_00": idx[0, 0], "corner_10": idx[0, -1], "corner_01": idx[-1, 0], "corner_11": idx[-1, -1],
        "corners": idx[[0, 0, -1, -1], [0, -1, 0, -1]],
        "edge_u0": idx[:, 0], "edge_u1": idx[:, -1], "edge_v0": idx[0, :], "edge_v1": idx[-1, :],
    }
    out = []
    for item in pin:
        if isinstance(item, str):
            if item not in named:
                raise ValueError(f"unknown pin {item!r}; use one of {', '.join(GRID_PIN_NAMES)} or particle indices")
            out.append(np.atleast_1d(named[item]))
        else:
            out.append(_local_indices([item], rows * cols, "pin"))
    return np.unique(np.concatenate(out)) if out else np.zeros(0, dtype=np.int64)


def _local_indices(indices, count, what):
    try:
        idx = np.asarray(indices, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{what} must be particle indices or names, got {indices!r}") from exc
    if np.any(idx != np.round(idx)):
        raise ValueError(f"{what} holds a non-integer index; give integer particle indices")
    idx = idx.astype(np.int64)
    bad = idx[(idx < 0) | (idx >= count)]
    if len(bad):
        raise ValueError(f"{what}: particle index {int(bad[0])} is outside the cloth's [0, {count})")
    return idx


def _axes(u_axis, v_axis):
    u = np.asarray(checks.vec3(u_axis, "u_axis"))
    v = np.asarray(checks.vec3(v_axis, "v_axis"))
    if np.linalg.norm(u) == 0.0 or np.linalg.norm(v) == 0.0:
        raise ValueError("u_axis and v_axis must be non-zero vectors")
    u = u / np.linalg.norm(u)
    v = v - np.dot(v, u) * u
    if np.linalg.norm(v) < 1.0e-6:
        raise ValueError(f"v_axis {tuple(v_axis)} is parallel to u_axis {tuple(u_axis)}; give two directions")
    return u, v / np.linalg.norm(v)


def add_cloth_grid(builder, resolution=(16, 16), size=(1.0, 1.0), origin=(0.0, 0.0, 0.0), u_axis=(1.0, 0.0, 0.0),
                   v_axis=(0.0, 0.0, -1.0), *, centered=False, density=0.1, particle_mass=None,
                   stiffness=None, damping=None, structural=(1.0e3, 1.0), shear=(1.0e3, 1.0), bend=(1.0e2, 0.1),
                   pin=None, velocity=(0.0, 0.0, 0.0), radius=0.0) -> Cloth:
    """Add a rectangular cloth of ``resolution`` = (cells along u, cells along v) spanning
    ``size`` = (width along u, height along v) [m].

    Placement: particle (i, j) sits at origin + i du u + j dv v, with u / v the normalised
    ``u_axis`` / ``v_axis`` (v is orthogonalised against u); ``centered=True`` puts the sheet's
    centre at ``origin`` instead. Default u = +X, v = -Z: a horizontal sheet whose front side
    (normal u x v) faces +Y; give v_axis=(0, -1, 0) for a curtain hanging down from its v = 0 edge.
    Springs: ``structural``, ``shear``, ``bend`` are (stiffness [N/m], damping [N s/m]) pairs;
    ``stiffness`` / ``damping`` (scalars) override every kind at once. A kind with stiffness and
    damping 0 adds no springs.
    Mass: ``density`` [kg/m^2] lumped per particle (a quarter cell per corner), or a uniform
    ``particle_mass`` [kg] when given. ``pin``: names from GRID_PIN_NAMES (``"corners"``,
    ``"corner_00"``, ``"corner_10"`` (i = nu, j = 0), ``"corner_01"``, ``"corner_11"``,
    ``"edge_v0"`` (the row j = 0), ``"edge_v1"``, ``"edge_u0"``, ``"edge_u1"``) and/or local
    particle indices. ``radius`` [m]: collision radius (cloth thickness offset) of every particle.
    """
    res = np.atleast_1d(np.asarray(resolution))
    if res.size == 1:
        res = np.repeat(res, 2)
    if res.size != 2:
        raise ValueError(f"resolution = {resolution!r}; give (cells along u, cells along v)")
    nu = _check_count(res[0].item() if hasattr(res[0], "item") else res[0], "resolution[0]")
    nv = _check_count(res[1].item() if hasattr(res[1], "item") else res[1], "resolution[1]")
    sz = np.atleast_1d(np.asarray(size, dtype=np.float64))
    if sz.size == 1:
        sz = np.repeat(sz, 2)
    if sz.size != 2:
        raise ValueError(f"size = {size!r}; give (width along u, height along v) [m]")
    width, height = _positive(sz[0], "size[0]"), _positive(sz[1], "size[1]")
    u, v = _axes(u_axis, v_axis)
    o = np.asarray(checks.vec3(origin, "origin"))
    du, dv = width / nu, height / nv
    ii, jj = np.meshgrid(np.arange(nu + 1), np.arange(nv + 1))
    positions = o + (ii.reshape(-1, 1) * du) * u + (jj.reshape(-1, 1) * dv) * v
    if centered:
        positions -= 0.5 * width * u + 0.5 * height * v
    n = len(positions)
    if particle_mass is not None:
        masses = np.full(n, _positive(particle_mass, "particle_mass"))
    else:
        rho = _positive(density, "density")
        wu = np.full(nu + 1, du)
        wu[[0, -1]] *= 0.5
        wv = np.full(nv + 1, dv)
        wv[[0, -1]] *= 0.5
        masses = rho * np.outer(wv, wu).reshape(-1)
    cols = nu + 1
    a = (jj[:-1, :-1] * cols + ii[:-1, :-1]).reshape(-1)
    tris = np.concatenate([np.stack([a, a + 1, a + cols + 1], 1), np.stack([a, a + cols + 1, a + cols], 1)])
    params = _kind_params(structural, shear, bend, stiffness, damping)
    pins = grid_pins(pin, nu, nv)
    cloth = _add_cloth(builder, positions, checks.vec3(velocity, "velocity"), masses, _radius(radius), tris,
                       grid_springs(nu, nv), params, pins)
    cloth.grid_shape = (nv + 1, nu + 1)
    return cloth


def _radius(radius):
    r = float(radius)
    if not math.isfinite(r) or r < 0.0:
        raise ValueError(f"radius = {radius}; it must be finite and >= 0 [m]")
    return r


def _kind_params(structural, shear, bend, stiffness, damping):
    params = {}
    for kind, pair in (("structural", structural), ("shear", shear), ("bend", bend)):
        try:
            k, d = (float(c) for c in pair)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{kind} = {pair!r}; give (stiffness [N/m], damping [N s/m])") from exc
        params[kind] = (k if stiffness is None else float(stiffness), d if damping is None else float(damping))
    return _spring_params({k: p[0] for k, p in params.items()}, {k: p[1] for k, p in params.items()})


def mesh_springs(vertices: np.ndarray, triangles: np.ndarray, bend_angle_deg: float = 30.0) -> dict:
    """Spring pairs of a triangle mesh (see module docstring): dict kind -> (S, 2) int64."""
    t = np.asarray(triangles, dtype=np.int64)
    e = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
    opposite = np.concatenate([t[:, 2], t[:, 0], t[:, 1]])
    key = np.sort(e, axis=1)
    structural, inverse = np.unique(key, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    # interior edges: two triangles share them -> join the two opposite vertices
    order = np.argsort(inverse, kind="stable")
    sorted_edges = inverse[order]
    same = np.flatnonzero(sorted_edges[1:] == sorted_edges[:-1])
    shear = np.stack([opposite[order[same]], opposite[order[same + 1]]], axis=1)
    shear = shear[shear[:, 0] != shear[:, 1]]
    shear = np.unique(np.sort(shear, axis=1), axis=0) if len(shear) else np.zeros((0, 2), dtype=np.int64)
    # skip-one neighbours along the straightest continuation
    n = len(vertices)
    x = np.asarray(vertices, dtype=np.float64)
    nbrs = [[] for _ in range(n)]
    for a, b in structural:
        nbrs[a].append(b)
        nbrs[b].append(a)
    cos_min = math.cos(math.radians(bend_angle_deg))
    bend_pairs: set[tuple[int, int]] = set()
    for i in range(n):
        for j in nbrs[i]:
            d0 = x[j] - x[i]
            d0 /= max(np.linalg.norm(d0), 1e-30)
            best, best_cos = -1, cos_min
            for k in nbrs[j]:
                if k == i:
                    continue
                d1 = x[k] - x[j]
                c = float(np.dot(d0, d1) / max(np.linalg.norm(d1), 1e-30))
                if c > best_cos:
                    best, best_cos = k, c
            if best >= 0 and best != i:
                bend_pairs.add((min(i, best), max(i, best)))
    edge_set = {tuple(p) for p in structural.tolist()}
    bend = np.array(sorted(p for p in bend_pairs if p not in edge_set), dtype=np.int64).reshape(-1, 2)
    return {"structural": structural.astype(np.int64), "shear": shear.astype(np.int64), "bend": bend}


def add_cloth_mesh(builder, vertices, triangles, *, density=0.1, particle_mass=None, stiffness=None, damping=None,
                   structural=(1.0e3, 1.0), shear=(1.0e3, 1.0), bend=(1.0e2, 0.1), pin=None,
                   velocity=(0.0, 0.0, 0.0), radius=0.0, bend_angle_deg=30.0) -> Cloth:
    """Add a cloth from any triangle mesh: ``vertices`` (V, 3) [m], ``triangles`` (T, 3) vertex
    indices. Mass: ``density`` [kg/m^2] (a third of each triangle's area to each corner) or a
    uniform ``particle_mass`` [kg]; ``pin``: local vertex indices. Springs as in add_cloth_grid
    (kinds defined in the module docstring)."""
    x = np.asarray(vertices, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 3 or len(x) == 0:
        raise ValueError(f"vertices must have shape (V, 3), got {x.shape}")
    if not np.all(np.isfinite(x)):
        raise ValueError(f"vertex {int(np.flatnonzero(~np.all(np.isfinite(x), axis=1))[0])} is not finite")
    t = np.asarray(triangles)
    if t.ndim != 2 or t.shape[1] != 3 or len(t) == 0:
        raise ValueError(f"triangles must have shape (T, 3), got {t.shape}")
    t = _local_indices(t, len(x), "triangles").reshape(-1, 3)
    degenerate = np.flatnonzero((t[:, 0] == t[:, 1]) | (t[:, 1] == t[:, 2]) | (t[:, 0] == t[:, 2]))
    if len(degenerate):
        raise ValueError(f"triangle {int(degenerate[0])} repeats a vertex {t[degenerate[0]].tolist()}")
    area = 0.5 * np.linalg.norm(np.cross(x[t[:, 1]] - x[t[:, 0]], x[t[:, 2]] - x[t[:, 0]]), axis=1)
    if particle_mass is not None:
        masses = np.full(len(x), _positive(particle_mass, "particle_mass"))
    else:
        rho = _positive(density, "density")
        masses = np.zeros(len(x))
        for c in range(3):
            np.add.at(masses, t[:, c], rho * area / 3.0)
        lonely = np.flatnonzero(masses <= 0.0)
        if len(lonely):
            raise ValueError(f"vertex {int(lonely[0])} belongs to no triangle of non-zero area, so it gets no mass; "
                             "remove it or give particle_mass")
    params = _kind_params(structural, shear, bend, stiffness, damping)
    pins = np.zeros(0, dtype=np.int64) if pin is None else _local_indices(pin, len(x), "pin")
    return _add_cloth(builder, x, checks.vec3(velocity, "velocity"), masses, _radius(radius), t,
                      mesh_springs(x, t, bend_angle_deg), params, pins)
