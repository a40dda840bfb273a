"""Marching cubes: welded, watertight triangle meshes from scalar fields on regular grids.

Conventions:

* ``field[i, j, k]`` is the value at position ``origin + (i, j, k) * spacing`` [m] (x, y, z order).
* ``inside="below"`` (default, signed distances): a node is inside when ``field < iso``;
  ``inside="above"`` (densities, metaballs): inside when ``field > iso``. Nodes exactly at ``iso``
  count as outside, and every edge vertex keeps at least ``EDGE_T_MIN`` (0.1 %) of the edge from
  both nodes, so an iso value that hits grid nodes exactly gives no zero-area triangles and no
  two vertices at one position.
* Every node must be finite: a NaN or infinite node is a ValueError naming it (index, position,
  value, how many), also for an all-NaN field, instead of a mesh with a bubble around it.
* Faces are counter-clockwise seen from outside; normals point from inside to outside (for a
  signed distance: toward increasing field) and are unit length. A closed surface has positive
  signed volume.
* Vertices are welded: one per grid edge the surface crosses, shared by all its triangles.
  Closed surfaces are watertight (every edge in exactly two faces). ``close_boundary=True`` treats
  everything outside the grid as outside, so a surface cut by the domain boundary is closed by a
  cap lying ``EDGE_T_MIN * spacing`` outside the domain faces.

Each call reads two counts back to the host (one synchronization) to size the output; the
reusable :class:`MarchingCubes` allocates nothing when its capacity suffices. Besides the output it
holds 5 bytes per grid node (a case code and a first-vertex index) and 16 bytes per block.
"""
from __future__ import annotations

import math
import numbers
import warnings

import numpy as np
import warp as wp

from warpsim.kernels import marching_cubes as mck

__all__ = ["MarchingCubes", "MarchingCubesResult", "marching_cubes", "topology_changed"]

_GROWTH = 1.5


class MarchingCubesResult:
    """An indexed triangle mesh. Arrays live on the mesher's device.

    Attributes:
        vertices: wp.array(dtype=wp.vec3), shape (vertex_count,): positions [m].
        faces: wp.array(dtype=wp.int32), shape (face_count, 3): vertex indices per triangle,
            counter-clockwise seen from outside (``faces.flatten()`` gives the flat index list
            that ``wp.Mesh`` and USD ``faceVertexIndices`` take).
        normals: wp.array(dtype=wp.vec3), shape (vertex_count,): unit normals pointing outside.

    From :class:`MarchingCubes` these are views of its buffers, overwritten by its next call.
    """

    def __init__(self, vertices, faces, normals):
        self.vertices = vertices
        self.faces = faces
        self.normals = normals

    @property
    def vertex_count(self) -> int:
        return self.vertices.shape[0]

    @property
    def face_count(self) -> int:
        return self.faces.shape[0]

    def usd_frame(self, normals: bool = False) -> dict:
        """This mesh as one frame of a USD Mesh prim for the cache writers: points,
        faceVertexCounts (3 per triangle), faceVertexIndices and, with ``normals``, normals.
        Reads the faces back once (the counts need their number)."""
        faces = self.faces.numpy().reshape(-1)
        data = {"points": self.vertices, "faceVertexCounts": np.full(len(faces) // 3, 3, np.int32),
                "faceVertexIndices": faces}
        if normals:
            data["normals"] = self.normals
        return data

    def numpy(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(vertices (V, 3) float32, faces (F, 3) int32, normals (V, 3) float32) as NumPy copies."""
        v = self.vertices.numpy().reshape(-1, 3).copy()
        f = self.faces.numpy().reshape(-1, 3).copy()
        n = self.normals.numpy().reshape(-1, 3).copy()
        return v, f, n


def _check_shape(shape):
    try:
        shape = tuple(int(s) for s in shape)
    except TypeError:
        raise ValueError(f"field shape must be 3 node counts (nx, ny, nz), got {shape!r}") from None
    if len(shape) != 3:
        raise ValueError(
            f"field must be 3D, indexed [i, j, k] = x, y, z; got {len(shape)} dimensions (shape {shape})"
        )
    if min(shape) < 2:
        raise ValueError(f"field shape {shape} needs at least 2 nodes on every axis (one cell)")
    return shape


def _check_vec3(value, name, positive):
    if isinstance(value, numbers.Real):
        value = (value, value, value)
    if isinstance(value, (str, bytes)) or any(isinstance(v, (str, bytes)) for v in np.ravel(np.asarray(value, object))):
        raise ValueError(f"{name} must be a number or 3 numbers, got {value!r}")
    try:
        values = tuple(float(v) for v in value)
    except TypeError:
        raise ValueError(f"{name} must be a number or 3 numbers, got {value!r}") from None
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise ValueError(f"{name} must be 3 finite numbers, got {value!r}")
    if positive and min(values) <= 0.0:
        raise ValueError(f"{name} must be > 0 on every axis [m], got {values}")
    return values


def _check_iso(iso):
    if not isinstance(iso, numbers.Real) or not math.isfinite(float(iso)):
        raise ValueError(f"iso must be a finite number, got {iso!r}")
    return float(iso)


def _check_inside(inside):
    if inside not in ("below", "above"):
        raise ValueError(f'inside must be "below" (field < iso is inside) or "above", got {inside!r}')
    return inside


class MarchingCubes:
    """Reusable marching cubes for fields of one shape: buffers are allocated once and reused.

    Args:
        shape: node counts (nx, ny, nz), each >= 2.
        spacing: node spacing [m], a number or 3 numbers, > 0.
        origin: position of node (0, 0, 0) [m].
        device: Warp device; None means Warp's preferred device.
        max_vertices, max_triangles: initial capacities; None sizes them on the first call
            (with 1.5x headroom).
        close_boundary: treat everything outside the grid as outside, closing cut surfaces.
        inside: "below" (field < iso is inside) or "above" (field > iso is inside).
        block_size: nodes per block and axis for empty-block skipping (default 8 on the CPU,
            2 on CUDA, where more threads beat skipping more).

    When a field needs more room than the buffers hold, they grow by at least 1.5x and
    ``reallocation_count`` goes up (with a RuntimeWarning if capacities were given explicitly).
    """

    def __init__(
        self,
        shape,
        spacing=1.0,
        origin=(0.0, 0.0, 0.0),
        device=None,
        max_vertices=None,
        max_triangles=None,
        *,
        close_boundary=False,
        inside="below",
        block_size=None,
    ):
        self.shape = _check_shape(shape)
        self.spacing = _check_vec3(spacing, "spacing", positive=True)
        self.origin = _check_vec3(origin, "origin", positive=False)
        self.inside = _check_inside(inside)
        self.close_boundary = bool(close_boundary)
        self.device = wp.get_device(device)
        for name, cap in (("max_vertices", max_vertices), ("max_triangles", max_triangles)):
            if cap is not None and (not isinstance(cap, numbers.Integral) or cap < 0):
                raise ValueError(f"{name} must be a non-negative integer or None, got {cap!r}")
        if block_size is None:
            block_size = 2 if self.device.is_cuda else 8
        if not isinstance(block_size, numbers.Integral) or block_size < 1:
            raise ValueError(f"block_size must be a positive integer, got {block_size!r}")
        self.block_size = int(block_size)
        self._explicit_capacity = max_vertices is not None or max_triangles is not None
        self._first_headroom = _GROWTH  # spare room when sizing on the first call
        self.reallocation_count = 0

        pad = 1 if self.close_boundary else 0
        node_count = tuple(n + 2 * pad for n in self.shape)
        block_count = tuple(-(-n // self.block_size) for n in node_count)
        self._block_total = block_count[0] * block_count[1] * block_count[2]

        grid = mck.GridSpec()
        grid.sign = -1.0 if self.inside == "above" else 1.0
        grid.pad = pad
        grid.node_count = wp.vec3i(*node_count)
        grid.lower = wp.vec3(*(o - pad * h for o, h in zip(self.origin, self.spacing)))
        grid.spacing = wp.vec3(*self.spacing)
        grid.block = self.block_size
        grid.block_count = wp.vec3i(*block_count)
        self._grid = grid

        d = self.device
        self._case_tri_count, self._case_edges = mck.case_tables(d)
        self._block_counts = wp.empty(self._block_total, dtype=wp.vec2i, device=d)
        self._block_offsets = wp.empty(self._block_total, dtype=wp.vec2i, device=d)
        node_total = node_count[0] * node_count[1] * node_count[2]
        self._node_total = self.shape[0] * self.shape[1] * self.shape[2]  # field nodes (no padding)
        self._node_case = wp.empty(node_total, dtype=wp.uint8, device=d)
        self._node_vertex = wp.empty(node_total, dtype=wp.int32, device=d)
        self._totals_host = wp.empty(1, dtype=wp.vec2i, device="cpu", pinned=d.is_cuda)
        self._first_bad = wp.empty(1, dtype=wp.int32, device=d)
        self._first_bad_host = wp.empty(1, dtype=wp.int32, device="cpu", pinned=d.is_cuda)
        self._vertices = self._normals = self._faces = None
        self._vertex_capacity = self._face_capacity = 0
        if max_vertices is not None or max_triangles is not None:
            self._reserve(max_vertices or 0, max_triangles or 0, report=False)

    @property
    def vertex_capacity(self) -> int:
        return self._vertex_capacity

    @property
    def triangle_capacity(self) -> int:
        return self._face_capacity

    def _reserve(self, vertex_count, face_count, report=True):
        d = self.device
        grew = False
        if self._vertices is None and report:  # sized by the first call
            vertex_count = int(vertex_count * self._first_headroom)
            face_count = int(face_count * self._first_headroom)
        if vertex_count > self._vertex_capacity or self._vertices is None:
            cap = max(vertex_count, int(self._vertex_capacity * _GROWTH), 1)
            grew = self._vertices is not None
            self._vertices = wp.empty(cap, dtype=wp.vec3, device=d)
            self._normals = wp.empty(cap, dtype=wp.vec3, device=d)
            self._vertex_capacity = cap
        if face_count > self._face_capacity or self._faces is None:
            cap = max(face_count, int(self._face_capacity * _GROWTH), 1)
            grew = grew or self._faces is not None
            self._faces = wp.empty((cap, 3), dtype=wp.int32, device=d)
            self._face_capacity = cap
        if grew and report:
            self.reallocation_count += 1
            if self._explicit_capacity:
                warnings.warn(
                    f"MarchingCubes grew its buffers to {self._vertex_capacity} vertices and "
                    f"{self._face_capacity} triangles; pass larger max_vertices/max_triangles to avoid it",
                    RuntimeWarning,
                    stacklevel=3,
                )

    def _as_field(self, field):
        if isinstance(field, wp.array):
            if field.ndim != 3:
                raise ValueError(
                    f"field must be 3D, indexed [i, j, k] = x, y, z; got {field.ndim} dimensions "
                    f"(shape {field.shape})"
                )
            if field.dtype != wp.float32:
                raise ValueError(
                    f"field must have dtype wp.float32, got {wp.types.type_repr(field.dtype)}; "
                    "convert it, e.g. wp.array(field.numpy(), dtype=wp.float32)"
                )
            if field.device != self.device:
                raise ValueError(
                    f"field is on device {field.device} but the mesher runs on {self.device}; "
                    f"pass field.to('{self.device}') or build the mesher with device='{field.device}'"
                )
        else:
            arr = np.asarray(field)
            if arr.ndim != 3:
                raise ValueError(
                    f"field must be 3D, indexed [i, j, k] = x, y, z; got {arr.ndim} dimensions "
                    f"(shape {arr.shape})"
                )
            if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
                raise ValueError(f"field must hold real numbers, got dtype {arr.dtype}")
            if tuple(arr.shape) == self.shape and not np.isfinite(arr).all():
                self._non_finite(np.flatnonzero(~np.isfinite(arr).reshape(-1))[0], arr)
            field = wp.array(np.ascontiguousarray(arr, dtype=np.float32), dtype=wp.float32, device=self.device)
        if tuple(field.shape) != self.shape:
            raise ValueError(f"field shape {tuple(field.shape)} does not match the mesher's shape {self.shape}")
        return field

    def _non_finite(self, flat_index, field):
        """ValueError naming the first NaN/infinite node: its index, position and value."""
        i, j, k = (int(x) for x in np.unravel_index(int(flat_index), self.shape))
        value = (field.numpy() if isinstance(field, wp.array) else np.asarray(field))[i, j, k]
        count = int((~np.isfinite(field.numpy() if isinstance(field, wp.array) else np.asarray(field))).sum())
        pos = tuple(round(o + n * h, 6) for o, n, h in zip(self.origin, (i, j, k), self.spacing))
        raise ValueError(f"field node [{i}, {j}, {k}] (position {pos} m) is {value} ({count} of "
                         f"{self._node_total} nodes are not finite); marching cubes needs a finite value at every "
                         "node: fill them (e.g. np.nan_to_num(field, nan=<an outside value>)) or fix the solver "
                         "that produced them")

    def mesh(self, field, iso=0.0) -> MarchingCubesResult:
        """Mesh the ``iso`` level of ``field`` (wp.array float32 or NumPy, shape ``self.shape``).
        A NaN or infinite node is a ValueError naming the node (checked on the host for NumPy
        fields, on the device for wp.array fields and read back with the output counts).

        Returns views of this mesher's buffers, valid until the next call.
        """
        iso = _check_iso(iso)
        field = self._as_field(field)
        grid = self._grid
        grid.field = field
        grid.iso = iso
        d = self.device
        nb = self._block_total

        self._first_bad.fill_(self._node_total)
        wp.launch(mck.find_non_finite_node, dim=self.shape, inputs=[field], outputs=[self._first_bad], device=d)
        wp.copy(self._first_bad_host, self._first_bad)
        wp.launch(
            mck.count_block_elements,
            dim=nb,
            inputs=[grid, self._case_tri_count],
            outputs=[self._block_counts, self._node_case],
            device=d,
        )
        wp.utils.array_scan(self._block_counts, self._block_offsets, inclusive=True)
        # The one host read-back per call: (vertices, triangles) to size the output.
        wp.copy(self._totals_host, self._block_offsets, src_offset=nb - 1, count=1)
        if d.is_cuda:
            wp.synchronize_stream(d.stream)
        first_bad = int(self._first_bad_host.numpy()[0])
        if first_bad < self._node_total:
            self._non_finite(first_bad, field)
        vertex_count, face_count = (int(x) for x in self._totals_host.numpy()[0])
        self._reserve(vertex_count, face_count)

        if vertex_count > 0:
            wp.launch(
                mck.emit_block_vertices,
                dim=nb,
                inputs=[grid, self._block_counts, self._block_offsets, self._node_case],
                outputs=[self._node_vertex, self._vertices, self._normals],
                device=d,
            )
        if face_count > 0:
            wp.launch(
                mck.emit_block_triangles,
                dim=nb,
                inputs=[
                    grid,
                    self._case_tri_count,
                    self._case_edges,
                    self._block_counts,
                    self._block_offsets,
                    self._node_case,
                    self._node_vertex,
                ],
                outputs=[self._faces],
                device=d,
            )
        return MarchingCubesResult(
            self._vertices[:vertex_count], self._faces[:face_count], self._normals[:vertex_count]
        )

    __call__ = mesh


def marching_cubes(
    field,
    spacing=1.0,
    origin=(0.0, 0.0, 0.0),
    iso=0.0,
    device=None,
    *,
    close_boundary=False,
    inside="below",
) -> MarchingCubesResult:
    """Triangle mesh of the ``iso`` level of a 3D scalar field (see the module docstring).

    Args:
        field: wp.array(dtype=wp.float32) or NumPy array, shape (nx, ny, nz), each >= 2,
            ``field[i, j, k]`` sampled at ``origin + (i, j, k) * spacing``.
        spacing: node spacing [m], a number or 3 numbers, > 0.
        origin: position of node (0, 0, 0) [m].
        iso: iso value (finite).
        device: Warp device; None means the field's device for a wp.array, else Warp's preferred one.
        close_boundary: treat everything outside the grid as outside, closing cut surfaces.
        inside: "below" (field < iso is inside, e.g. signed distance) or "above" (densities).

    Returns:
        MarchingCubesResult with vertices (V,) vec3, faces (F, 3) int32, normals (V,) vec3.
    """
    iso = _check_iso(iso)
    if isinstance(field, wp.array):
        shape = field.shape
        if device is None:
            device = field.device
    else:
        shape = np.shape(field)
    mesher = MarchingCubes(
        _check_shape(shape), spacing, origin, device, close_boundary=close_boundary, inside=inside
    )
    mesher._first_headroom = 1.0  # one-shot: exact sizes
    return mesher.mesh(field, iso)


def _faces_numpy(faces):
    if faces is None:
        return None
    if isinstance(faces, MarchingCubesResult):
        faces = faces.faces
    if isinstance(faces, wp.array):
        faces = faces.numpy()
    return np.asarray(faces).reshape(-1)


def topology_changed(previous_faces, faces) -> bool:
    """True when a mesh's connectivity differs between two frames.

    Both arguments are face index arrays (NumPy, wp.array or MarchingCubesResult, any shape
    holding triangles); ``previous_faces=None`` (first frame) counts as changed. All faces are
    triangles, so USD ``faceVertexCounts`` changes exactly when the face count does, and
    ``faceVertexIndices`` exactly when this returns True. Keep a *copy* of the previous frame's
    faces: a MarchingCubes result is overwritten by the next call.
    """
    prev = _faces_numpy(previous_faces)
    if prev is None:
        return True
    cur = _faces_numpy(faces)
    return prev.shape != cur.shape or not np.array_equal(prev, cur)
