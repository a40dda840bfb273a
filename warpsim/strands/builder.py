"""``add_strands``: hair strands as chains of particles, and the :class:`Strands` handle.

Each strand of ``segments`` segments adds ``segments + 2`` consecutive particles: a pinned ghost
one segment inside the head, the pinned root on the scalp, and ``segments`` free vertices. The
ghost-root edge clamps the root direction (the strand leaves the scalp as groomed); both move
with the head (``StrandRoots``). Forces (``StrandForce``): a stretch spring per segment and a
bending spring per vertex whose rest state is the groomed shape (see ``warpsim.kernels.strands``).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import warp as wp

from ..core import checks
from ..kernels import strands as K

__all__ = ["Strands", "add_strands", "head_signed_distance"]


def _per_strand(value, name, count, unit, lo=0.0, lo_open=False):
    arr = np.asarray(value, dtype=object)
    if arr.ndim == 0:
        v = checks.number(value, f"add_strands {name}", unit)
        return checks.numbers_array(np.full(count, v), f"add_strands {name}", count, lo=lo, lo_open=lo_open,
                                    item="strand", unit=unit)
    return checks.numbers_array(value, f"add_strands {name}", count, lo=lo, lo_open=lo_open, item="strand",
                                unit=unit, fix=f"give one {name} per strand or a single number")


def _resample(polyline, segments, s):
    """``segments + 1`` points at equal arc length along polyline (K, 3) of strand ``s``."""
    seg = np.linalg.norm(np.diff(polyline, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    if arc[-1] <= 0.0:
        raise ValueError(f"add_strands: strand {s} polyline has length 0; give distinct points")
    target = np.linspace(0.0, arc[-1], segments + 1)
    return np.stack([np.interp(target, arc, polyline[:, c]) for c in range(3)], axis=1)


def _rotate(q, v):
    """Vectors v (N, 3) rotated by the unit quaternion q (x, y, z, w)."""
    u, w = np.asarray(q[:3], np.float64), float(q[3])
    return v + 2.0 * np.cross(u, np.cross(u, v) + w * v)


def head_signed_distance(head, points) -> np.ndarray:
    """Signed distance [m] of ``points`` (N, 3) to the surface of ``head`` (a ``ws.Sphere`` /
    ``ws.Capsule`` or a solid ``ws.TriangleMesh`` at its current pose): negative inside."""
    from ..bodies.colliders import Capsule, TriangleMesh

    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if isinstance(head, Capsule):
        a, b = np.asarray(head.a), np.asarray(head.b)
        ab = b - a
        denom = float(np.dot(ab, ab))
        t = np.zeros(len(points)) if denom == 0.0 else np.clip((points - a) @ ab / denom, 0.0, 1.0)
        return np.linalg.norm(points - (a + t[:, None] * ab), axis=1) - head.radius
    if isinstance(head, TriangleMesh):
        p, q = head.world_pose()
        inv = np.array([-q[0], -q[1], -q[2], q[3]])
        local = _rotate(inv, points - p)
        mesh = wp.Mesh(points=wp.array(head.points.astype(np.float32), dtype=wp.vec3, device="cpu"),
                       indices=wp.array(head.faces.astype(np.int32).reshape(-1), dtype=int, device="cpu"))
        out = wp.zeros(len(points), dtype=float, device="cpu")
        wp.launch(K.mesh_signed_distance, len(points),
                  inputs=[mesh.id, wp.array(local.astype(np.float32), dtype=wp.vec3, device="cpu"), out],
                  device="cpu")
        return out.numpy().astype(np.float64)
    raise ValueError(f"add_strands head must be a ws.Sphere, ws.Capsule or solid ws.TriangleMesh collider, got "
                     f"{checks.show(head)}")


class Strands:
    """Hair strands added by :func:`add_strands` (host data; device arrays per model after ``bind``).

    Attributes:
      strand_count, segments; stride = segments + 2 particles per strand; first: particle index of
      strand 0's ghost (strand s, local vertex v is particle first + s stride + v: 0 ghost, 1 root,
      2 .. segments + 1 free, the last the tip).
      rest_length (strand_count * stride,) [m]; stretch_stiffness, bend_stiffness [N/m] (spring
      constants from the rigidities),
      stretch_damping, bend_damping [N s/m], mass [kg], radius [m]: per strand, (strand_count,).
      ghost_local, root_local, normal_local (strand_count, 3): ghost, root and root-frame normal in
      the head's frame at build time.
    """

    strand_count: int
    segments: int
    stride: int
    first: int
    rest_length: np.ndarray
    stretch_stiffness: np.ndarray
    bend_stiffness: np.ndarray
    stretch_damping: np.ndarray
    bend_damping: np.ndarray
    mass: np.ndarray
    radius: np.ndarray
    ghost_local: np.ndarray
    root_local: np.ndarray
    normal_local: np.ndarray
    normal_world: np.ndarray
    head: Any

    def __init__(self):
        self._device_data = {}

    # ------------------------------------------------------------------ indices
    def particles(self) -> np.ndarray:
        """Particle indices (strand_count, stride): ghost, root, free vertices."""
        return self.first + np.arange(self.strand_count * self.stride).reshape(self.strand_count, self.stride)

    def curve_particles(self) -> np.ndarray:
        """Particle indices drawn as curves, root to tip: (strand_count, segments + 1)."""
        return self.particles()[:, 1:]

    def tip_particles(self) -> np.ndarray:
        return self.particles()[:, -1]

    def root_particles(self) -> np.ndarray:
        return self.particles()[:, 1]

    def free_particles(self) -> np.ndarray:
        return self.particles()[:, 2:].reshape(-1)

    def strand_of(self, particle: int):
        """(strand, local vertex) of a particle index, or None when it is not a strand particle."""
        k = int(particle) - self.first
        if k < 0 or k >= self.strand_count * self.stride:
            return None
        return k // self.stride, k % self.stride

    def curve_widths(self, root_width=None, tip_fraction=0.2) -> np.ndarray:
        """Per curve vertex widths [m] tapering linearly from ``root_width`` (default 2 radius) at
        the root to ``tip_fraction`` of it at the tip, shape (strand_count * (segments + 1),)."""
        root = 2.0 * self.radius if root_width is None else np.full(self.strand_count, float(root_width))
        ramp = 1.0 - (1.0 - tip_fraction) * np.linspace(0.0, 1.0, self.segments + 1)
        return (root[:, None] * ramp[None, :]).reshape(-1)

    # ------------------------------------------------------------------ device data
    def bind(self, model):
        """Device arrays on ``model.device`` (made once per model; ``StrandForce``, ``StrandRoots``
        and ``sag_free`` share them): rest_length, bend_rest (wp.vec3, rest bending vectors in
        vertex frames [m]), per-strand parameters and the head-frame root data."""
        key = id(model)
        data = self._device_data.get(key)
        if data is not None and data["model"] is model:
            return data
        if model.particle_count < self.first + self.strand_count * self.stride:
            raise ValueError(f"Strands: the model has {model.particle_count} particles but the strands need "
                             f"{self.first + self.strand_count * self.stride}; finalize the builder the strands "
                             "were added to")
        d = model.device
        f32 = np.float32
        data = {"model": model}
        data["rest_length"] = wp.array(self.rest_length.astype(f32), dtype=float, device=d)
        for name in ("stretch_stiffness", "bend_stiffness", "stretch_damping", "bend_damping"):
            data[name] = wp.array(getattr(self, name).astype(f32), dtype=float, device=d)
        for name in ("ghost_local", "root_local", "normal_local"):
            data[name] = wp.array(getattr(self, name).astype(f32), dtype=wp.vec3, device=d)
        data["root_normal"] = wp.array(self.normal_world.astype(f32), dtype=wp.vec3, device=d)
        data["bend_rest"] = wp.zeros(self.strand_count * self.stride, dtype=wp.vec3, device=d)
        data["frame_t"] = wp.zeros(self.strand_count * self.stride, dtype=wp.vec3, device=d)  # force scratch
        data["frame_n"] = wp.zeros(self.strand_count * self.stride, dtype=wp.vec3, device=d)
        # the groomed shape is the bending rest state
        wp.launch(K.bend_rest_from_world, self.strand_count,
                  inputs=[model.particle_q, self.first, self.stride, data["root_normal"], data["bend_rest"], 1,
                          data["bend_rest"]], device=d)
        self._device_data = {key: data}
        return data


def add_strands(builder, roots=None, directions=None, segments: int = 16, *, polylines=None, length=0.3,
                mass=1.0e-3, stretch_rigidity=5.0, bend_rigidity=5.0e-4, stretch_damping=0.02,
                bend_damping=1.0e-3, radius=0.002, head=None, root_tolerance=None) -> Strands:
    """Add hair strands to ``builder``; returns a :class:`Strands` handle.

    Args:
      roots: (S, 3) root positions on the scalp [m] (with ``directions``).
      directions: (S, 3) growth directions (normalised here); strand s is the straight segment
        root + [0, length] direction.
      segments: segments per strand (>= 1).
      polylines: instead of roots/directions, (S, K, 3) or a list of (K_s, 3) groomed curves [m],
        root first, resampled to ``segments`` equal segments.
      length: strand length [m] (scalar or (S,)), with directions.
      mass: strand mass [kg], split evenly over its free vertices; stretch_rigidity EA [N] and
        bend_rigidity EI [N m^2] (the spring constants follow from the segment length h:
        k_stretch = EA / h, k_bend = EI / h^3, so the strand bends alike at any resolution);
        stretch_damping and bend_damping [N s/m] per spring; radius: collision radius [m] of every
        strand particle (all scalars or (S,) per strand).
      head: the head collider (``ws.Sphere``, ``ws.Capsule`` or solid ``ws.TriangleMesh``) the roots
        sit on; roots farther outside it than ``root_tolerance`` [m] (default: half a segment) and
        strand vertices deeper inside it than their radius are errors naming the strand. Roots
        are stored in the head's frame, so ``StrandRoots`` moves them with it.
    """
    segments = checks.count(segments, "add_strands segments", fix="a strand needs at least one segment, e.g. 16")
    if polylines is not None:
        if roots is not None or directions is not None:
            raise ValueError("add_strands: give either polylines or roots and directions, not both")
        if isinstance(polylines, np.ndarray) and polylines.ndim == 3:
            lines = list(polylines)
        else:
            lines = list(polylines)
        if not lines:
            raise ValueError("add_strands: polylines is empty; give at least one strand")
        curves = []
        for s, line in enumerate(lines):
            arr = checks.float_array(line, f"add_strands strand {s} polyline")
            if arr.ndim != 2 or arr.shape[1] != 3 or len(arr) < 2:
                raise ValueError(f"add_strands: strand {s} polyline has shape {arr.shape}; give (K >= 2, 3) points")
            bad = np.flatnonzero(~np.isfinite(arr).all(axis=1))
            if len(bad):
                raise ValueError(f"add_strands: strand {s} polyline point {int(bad[0])} is not finite: "
                                 f"{arr[bad[0]].tolist()}; give finite coordinates")
            curves.append(_resample(arr, segments, s))
        verts = np.stack(curves)
    else:
        if roots is None or directions is None:
            raise ValueError("add_strands needs roots and directions (S, 3), or polylines")
        roots = checks.vectors(roots, "add_strands roots", item="strand", unit="m")
        directions = checks.vectors(directions, "add_strands directions", item="strand",
                                    fix="give a finite growth direction per strand")
        checks.same_length(roots=roots, directions=directions)
        norms = np.linalg.norm(directions, axis=1)
        zero = np.flatnonzero(norms == 0.0)
        if len(zero):
            raise ValueError(f"add_strands: strand {int(zero[0])} has direction (0, 0, 0); give a non-zero growth "
                             "direction")
        dirs = directions / norms[:, None]
        lengths = _per_strand(length, "length", len(roots), "m", lo=0.0, lo_open=True)
        frac = np.linspace(0.0, 1.0, segments + 1)
        verts = roots[:, None, :] + (lengths[:, None] * frac[None, :])[:, :, None] * dirs[:, None, :]
    count = len(verts)
    seg_vec = np.diff(verts, axis=1)
    seg_len = np.linalg.norm(seg_vec, axis=2)
    short = np.argwhere(seg_len <= 1.0e-9)
    if len(short):
        s = int(short[0][0])
        raise ValueError(f"add_strands: strand {s} has a segment of length {seg_len[s].min():g} m; give a "
                         "longer strand or fewer segments")
    strands = Strands()
    strands.strand_count, strands.segments, strands.stride = count, segments, segments + 2
    strands.mass = _per_strand(mass, "mass", count, "kg", lo=0.0, lo_open=True)
    strands.radius = _per_strand(radius, "radius", count, "m", lo=0.0, lo_open=True)
    h = seg_len.mean(axis=1)
    strands.stretch_stiffness = _per_strand(stretch_rigidity, "stretch_rigidity", count, "N") / h
    strands.bend_stiffness = _per_strand(bend_rigidity, "bend_rigidity", count, "N m^2") / h**3
    for name in ("stretch_damping", "bend_damping"):
        setattr(strands, name, _per_strand(locals()[name], name, count, "N s/m"))
    tangent0 = seg_vec[:, 0] / seg_len[:, :1]
    ghosts = verts[:, 0] - tangent0 * seg_len[:, :1]
    helper = np.where(np.abs(tangent0[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 0.0, 1.0]]))
    normal = np.cross(tangent0, helper)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)

    if head is not None:
        tol = 0.5 * seg_len[:, 0] if root_tolerance is None else np.full(
            count, checks.nonnegative(root_tolerance, "add_strands root_tolerance", "m"))
        depth = head_signed_distance(head, verts[:, 0])
        out = np.flatnonzero(depth > tol)
        if len(out):
            s = int(out[0])
            raise ValueError(f"add_strands: strand {s} root {verts[s, 0].round(4).tolist()} is {depth[s]:.4g} m "
                             f"outside the head (tolerance {tol[s]:.3g} m); put every root on the scalp")
        inside = head_signed_distance(head, verts[:, 1:].reshape(-1, 3)).reshape(count, segments)
        deep = np.argwhere(inside < -strands.radius[:, None])
        if len(deep):
            s, v = int(deep[0][0]), int(deep[0][1])
            raise ValueError(f"add_strands: strand {s} vertex {v + 1} lies {-inside[s, v]:.4g} m inside the head "
                             f"(more than its radius {strands.radius[s]:g} m); point the strand away from the head")
        p, q = head.world_pose()
    else:
        p, q = np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0])
    inv = np.array([-q[0], -q[1], -q[2], q[3]])
    strands.ghost_local = _rotate(inv, ghosts - p)
    strands.root_local = _rotate(inv, verts[:, 0] - p)
    strands.normal_local = _rotate(inv, normal)
    strands.normal_world = normal
    strands.head = head

    strands.first = builder.particle_count
    rest = np.zeros((count, segments + 2))
    rest[:, 1:-1] = seg_len
    strands.rest_length = rest.reshape(-1)
    positions = np.concatenate([ghosts[:, None], verts], axis=1).reshape(-1, 3)
    masses = np.zeros((count, segments + 2))
    masses[:, 2:] = (strands.mass / segments)[:, None]
    n = len(positions)
    builder.particle_q.extend(map(tuple, positions.tolist()))
    builder.particle_qd.extend([(0.0, 0.0, 0.0)] * n)
    builder.particle_mass.extend(masses.reshape(-1).tolist())
    builder.particle_radius.extend(np.repeat(strands.radius, segments + 2).tolist())
    return strands
