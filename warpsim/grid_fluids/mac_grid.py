"""MacGrid: a staggered (MAC) grid in 2D or 3D with cell labels, static solids and boundary conditions.

Cell (i, j, k) spans ``origin + [i, i+1] x [j, j+1] x [k, k+1] * dx`` [m]. Velocities live on faces:
``u`` (x-faces) has shape (nx+1, ny, nz), ``v`` (nx, ny+1, nz), ``w`` (nx, ny, nz+1) [m/s]. A 2D grid
(``shape=(nx, ny)``) is stored one cell thick (nz = 1) with closed z sides, so w stays 0 and every
kernel serves both dimensions. Cells are AIR (0), FLUID (1) or SOLID (2); the domain boundary is a
free-slip solid wall except on ``open_sides`` (outside is air at pressure 0).
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from ..kernels import grid as K

AIR, FLUID, SOLID = 0, 1, 2
SIDES = ("-x", "+x", "-y", "+y", "-z", "+z")
# staggering offsets (in cells) of the stored values
OFFSETS = {
    "center": (0.5, 0.5, 0.5),
    "u": (0.0, 0.5, 0.5),
    "v": (0.5, 0.0, 0.5),
    "w": (0.5, 0.5, 0.0),
}


def check_positive(value, what: str) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{what} must be a number > 0, got {value!r}") from exc
    if not (math.isfinite(x) and x > 0.0):
        raise ValueError(f"{what} must be finite and > 0, got {value!r}")
    return x


def check_finite(value, what: str) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{what} must be a finite number, got {value!r}") from exc
    if not math.isfinite(x):
        raise ValueError(f"{what} must be finite, got {value!r}")
    return x


class MacGrid:
    """A MAC grid: face velocities, cell labels and a solid signed-distance field.

    Args:
        shape: cell counts (nx, ny) for 2D or (nx, ny, nz) for 3D, each >= 2 (3D: nz >= 2).
        dx: cell size [m].
        origin: lower corner [m] (2 or 3 numbers).
        open_sides: sides of the box that are open to air, from ``"-x", "+x", "-y", "+y", "-z", "+z"``
            (2D: no z sides). Other sides are free-slip walls.
        device: Warp device; None = Warp's preferred device.

    Attributes:
        u, v, w: face velocities [m/s], shapes (nx+1, ny, nz), (nx, ny+1, nz), (nx, ny, nz+1).
        labels: wp.array3d(int) of AIR/FLUID/SOLID, shape (nx, ny, nz).
        solid_phi: signed distance to the solids at cell centres [m] (< 0 inside), shape (nx, ny, nz).
    """

    def __init__(self, shape, dx, origin=None, open_sides=(), device=None):
        try:
            dims = tuple(int(s) for s in shape)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"grid shape must be 2 or 3 cell counts, got {shape!r}") from exc
        if len(dims) not in (2, 3) or any(float(s) != float(t) for s, t in zip(dims, shape)):
            raise ValueError(f"grid shape must be 2 or 3 integer cell counts, got {shape!r}")
        if any(n < 2 for n in dims):
            raise ValueError(f"grid shape {dims} needs at least 2 cells along every axis")
        self.dim = len(dims)
        self.dx = check_positive(dx, "grid dx (cell size [m])")
        self.shape = dims if self.dim == 3 else (dims[0], dims[1], 1)
        origin = (0.0,) * self.dim if origin is None else origin
        try:
            o = [float(c) for c in origin]
        except (TypeError, ValueError) as exc:
            raise ValueError(f"grid origin must be {self.dim} numbers [m], got {origin!r}") from exc
        if len(o) != self.dim or not all(math.isfinite(c) for c in o):
            raise ValueError(f"grid origin must be {self.dim} finite numbers [m], got {origin!r}")
        self.origin = tuple(o) if self.dim == 3 else (o[0], o[1], 0.0)
        sides = (open_sides,) if isinstance(open_sides, str) else tuple(open_sides)
        mask = 0
        for s in sides:
            allowed = SIDES if self.dim == 3 else SIDES[:4]
            if s not in allowed:
                raise ValueError(f"open_sides: open side {s!r} is unknown; use some of {allowed}")
            mask |= 1 << SIDES.index(s)
        self.open_sides, self.open_mask = sides, mask
        self.device = wp.get_device(device)
        nx, ny, nz = self.shape
        d = self.device
        self.u = wp.zeros((nx + 1, ny, nz), dtype=float, device=d)
        self.v = wp.zeros((nx, ny + 1, nz), dtype=float, device=d)
        self.w = wp.zeros((nx, ny, nz + 1), dtype=float, device=d)
        self.labels = wp.full(self.shape, FLUID, dtype=int, device=d)
        self.solid_phi = wp.full(self.shape, 1.0e6, dtype=float, device=d)
        self.no_phi = wp.zeros((1, 1, 1), dtype=float, device=d)
        """A (1, 1, 1) placeholder for a kernel's level-set input when there is none."""
        self._valid = [[wp.zeros(f.shape, dtype=int, device=d) for _ in range(2)] for f in self.faces]
        self._scratch = [wp.zeros(f.shape, dtype=float, device=d) for f in self.faces]
        self.wp_origin = wp.vec3(*self.origin)
        """``origin`` [m] as a wp.vec3 (a launch argument)."""
        self.solids: list[tuple] = []

    # ------------------------------------------------------------------ geometry
    @property
    def faces(self):
        """(u, v, w): the three face-velocity arrays."""
        return (self.u, self.v, self.w)

    @property
    def cell_count(self) -> int:
        return self.shape[0] * self.shape[1] * self.shape[2]

    @property
    def lower(self):
        return self.origin

    @property
    def upper(self):
        return tuple(o + n * self.dx for o, n in zip(self.origin, self.shape))

    def positions(self, where="center") -> np.ndarray:
        """World positions [m] of the stored values of a ``"center"``, ``"u"``, ``"v"`` or ``"w"``
        field, shape (n0, n1, n2, 3)."""
        if where not in OFFSETS:
            raise ValueError(f"positions: where={where!r} is unknown; use one of {sorted(OFFSETS)}")
        shape = {"center": self.shape, "u": self.u.shape, "v": self.v.shape, "w": self.w.shape}[where]
        idx = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), axis=-1).astype(np.float64)
        return np.asarray(self.origin) + (idx + np.asarray(OFFSETS[where])) * self.dx

    def point(self, p, what: str) -> list[float]:
        """``p`` as 3 finite coordinates [m] (2D grids: 2 numbers, z set to the middle of the cell
        layer); ValueError naming ``what``."""
        try:
            c = [float(x) for x in p]
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{what} must be {self.dim} numbers [m], got {p!r}") from exc
        if len(c) == 2 and self.dim == 2:
            c.append(self.origin[2] + 0.5 * self.dx)
        if len(c) != 3 or not all(math.isfinite(x) for x in c):
            raise ValueError(f"{what} must be {self.dim} finite numbers [m], got {p!r}")
        return c

    # ------------------------------------------------------------------ solids
    def add_sphere(self, center, radius) -> None:
        """A static solid sphere (2D: a disk) of ``radius`` [m] at ``center`` [m]."""
        n = len(self.solids)
        c = self.point(center, f"solid {n} (sphere) center")
        r = check_positive(radius, f"solid {n} (sphere) radius")
        self.solids.append(("sphere", c, r))
        self._voxelize()

    def add_box(self, lower, upper) -> None:
        """A static solid axis-aligned box [lower, upper] [m] (2D: a rectangle)."""
        n = len(self.solids)
        lo, hi = self.point(lower, f"solid {n} (box) lower"), self.point(upper, f"solid {n} (box) upper")
        if self.dim == 2:
            lo[2], hi[2] = self.origin[2] - 1.0, self.origin[2] + 1.0 + self.dx
        if any(h <= l for l, h in zip(lo, hi)):
            raise ValueError(f"solid {n} (box) upper {hi} must exceed lower {lo} on every axis")
        self.solids.append(("box", lo, hi))
        self._voxelize()

    def add_mesh(self, points, indices) -> None:
        """A static closed triangle mesh (3D only): ``points`` (V, 3) [m], ``indices`` (F, 3) or flat,
        voxelised by signed distance (wp.Mesh sign queries)."""
        n = len(self.solids)
        if self.dim != 3:
            raise ValueError(f"solid {n} (mesh): triangle meshes need a 3D grid")
        pts = np.asarray(points, dtype=np.float32).reshape(-1, 3)
        idx = np.asarray(indices, dtype=np.int32).reshape(-1)
        if len(idx) == 0 or len(idx) % 3 != 0 or idx.min() < 0 or idx.max() >= len(pts):
            raise ValueError(f"solid {n} (mesh): indices must be triangles into the {len(pts)} points")
        if not np.all(np.isfinite(pts)):
            raise ValueError(f"solid {n} (mesh): points must be finite")
        mesh = wp.Mesh(points=wp.array(pts, dtype=wp.vec3, device=self.device),
                       indices=wp.array(idx, dtype=int, device=self.device))
        self.solids.append(("mesh", mesh, None))
        self._voxelize()

    def add_collider(self, collider):
        """Voxelise a collider from ``warpsim.bodies.colliders`` at its current pose: a ``Sphere`` (anything
        with ``center`` and ``radius``; an ``inside=True`` container is refused) or a closed
        ``TriangleMesh`` (anything with ``points`` and ``faces``/``indices``; ``world_points()`` is
        used when present). Walls (ws.Box, ws.Plane) are the grid's own sides: use ``open_sides``."""
        n = len(self.solids)
        if getattr(collider, "inside", 0):
            raise ValueError(f"solid {n}: an inside=True sphere is a container, not a solid; size the grid instead")
        if hasattr(collider, "center") and hasattr(collider, "radius"):
            return self.add_sphere(collider.center, collider.radius)
        faces = getattr(collider, "faces", getattr(collider, "indices", None))
        if hasattr(collider, "points") and faces is not None:
            points = collider.world_points() if hasattr(collider, "world_points") else collider.points
            return self.add_mesh(np.asarray(points), np.asarray(faces))
        raise ValueError(
            f"collider {type(collider).__name__} cannot be voxelised: give a sphere (center, radius), a mesh "
            "collider, or use MacGrid.add_box / open_sides for walls"
        )

    def _voxelize(self):
        self.solid_phi.fill_(1.0e6)
        d, o, dx = self.device, self.wp_origin, self.dx
        spheres = [s for s in self.solids if s[0] == "sphere"]
        boxes = [s for s in self.solids if s[0] == "box"]
        if spheres:
            c = wp.array(np.array([s[1] for s in spheres], dtype=np.float32), dtype=wp.vec3, device=d)
            r = wp.array(np.array([s[2] for s in spheres], dtype=np.float32), dtype=float, device=d)
            wp.launch(K.solid_phi_spheres, self.shape, inputs=[c, r, o, dx, self.solid_phi], device=d)
        if boxes:
            lo = wp.array(np.array([s[1] for s in boxes], dtype=np.float32), dtype=wp.vec3, device=d)
            hi = wp.array(np.array([s[2] for s in boxes], dtype=np.float32), dtype=wp.vec3, device=d)
            wp.launch(K.solid_phi_boxes, self.shape, inputs=[lo, hi, o, dx, self.solid_phi], device=d)
        max_dist = float(np.linalg.norm(self.shape) * dx)
        for s in self.solids:
            if s[0] == "mesh":
                wp.launch(K.solid_phi_mesh, self.shape, inputs=[s[1].id, o, dx, max_dist, self.solid_phi], device=d)
        self.label()

    # ------------------------------------------------------------------ labels and boundaries
    def label(self, phi=None) -> None:
        """Relabel cells: SOLID inside solids, else FLUID where ``phi`` < 0 (every non-solid cell
        when ``phi`` is None, as for smoke), else AIR."""
        use = phi is not None
        wp.launch(K.label_cells, self.shape, inputs=[self.solid_phi, phi if use else self.no_phi, int(use)],
                  outputs=[self.labels], device=self.device)

    def enforce_boundaries(self) -> None:
        """Free-slip static solids and walls: zero normal velocity on faces touching SOLID."""
        for axis, f in enumerate(self.faces):
            wp.launch(K.enforce_solid_faces, f.shape, inputs=[self.labels, self.open_mask, axis, f],
                      device=self.device)

    def extrapolate_velocity(self, layers: int = 4) -> None:
        """Fill face velocities that touch no FLUID cell from their neighbours, ``layers`` faces deep
        (each layer: the mean of the valid neighbours); faces beyond are set to 0. Then re-apply the
        solid boundary condition."""
        if int(layers) != layers or layers < 1:
            raise ValueError(f"extrapolation layers must be an integer >= 1, got {layers!r}")
        for axis, f in enumerate(self.faces):
            valid, scratch = self._valid[axis], self._scratch[axis]
            wp.launch(K.mark_fluid_faces, f.shape, inputs=[self.labels, self.open_mask, axis], outputs=[valid[0]],
                      device=self.device)
            src_f, dst_f = f, scratch
            for layer in range(layers):
                wp.launch(K.extrapolate_layer, f.shape, inputs=[valid[layer % 2], src_f, int(layer == layers - 1)],
                          outputs=[valid[(layer + 1) % 2], dst_f], device=self.device)
                src_f, dst_f = dst_f, src_f
            if src_f is not f:
                wp.copy(f, src_f)
        self.enforce_boundaries()

    def divergence(self, out=None) -> wp.array:
        """div(u) [1/s] at FLUID cells (0 elsewhere), shape (nx, ny, nz)."""
        out = wp.zeros(self.shape, dtype=float, device=self.device) if out is None else out
        wp.launch(K.compute_divergence, self.shape, inputs=[self.u, self.v, self.w, self.labels, self.dx],
                  outputs=[out], device=self.device)
        return out

    def checkpoint(self) -> dict:
        """Host copies of the face velocities and labels."""
        return {"u": self.u.numpy(), "v": self.v.numpy(), "w": self.w.numpy(), "labels": self.labels.numpy()}

    def restore(self, data) -> None:
        """Inverse of :meth:`checkpoint` (same grid)."""
        for key, f in (("u", self.u), ("v", self.v), ("w", self.w), ("labels", self.labels)):
            values = np.asarray(data[key])
            if values.shape != tuple(f.shape):
                raise ValueError(f"checkpoint {key!r} has shape {values.shape}; the grid's is {tuple(f.shape)}")
            f.assign(values)

    def set_velocity(self, fn) -> None:
        """Set face velocities from ``fn(points (..., 3)) -> (..., 3)`` [m/s] (host helper for setup
        and tests), then apply the solid boundary condition."""
        for axis, (f, where) in enumerate(zip(self.faces, "uvw")):
            values = np.asarray(fn(self.positions(where)), dtype=np.float64)[..., axis]
            if self.dim == 2 and axis == 2:
                values = np.zeros_like(values)
            if not np.all(np.isfinite(values)):
                raise ValueError(f"set_velocity: the {where} velocity is not finite everywhere")
            f.assign(values.astype(np.float32))
        self.enforce_boundaries()
