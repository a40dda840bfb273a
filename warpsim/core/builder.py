"""ModelBuilder: collects particles and springs on the host, validates them, and finalizes a Model."""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np
import warp as wp

from . import checks
from .model import Model, spring_adjacency


_COINCIDENT = 1.0e-6  # particles closer than this fraction of a spring's rest length count as coincident


def _check_coincident(index, i, j, distance, rest_length):
    if rest_length > 0.0 and distance <= _COINCIDENT * rest_length:
        raise ValueError(f"spring {index} joins particles {i} and {j} at the same position (distance {distance:g} m) "
                         f"with rest length {rest_length:g} m: a spring between coincident particles has no "
                         "direction and exerts no force; move one particle apart or give rest_length=0")


class ModelBuilder:
    """Builds particle systems with damped springs.

    Example::

        builder = ws.ModelBuilder()
        a = builder.add_particle((0, 1, 0), mass=0.0)      # pinned
        b = builder.add_particle((0, 0, 0), mass=1.0)
        builder.add_spring(a, b, stiffness=100.0, damping=1.0)
        model = builder.finalize(device="cpu")
    """

    def __init__(self):
        self.particle_q: list[tuple] = []
        self.particle_qd: list[tuple] = []
        self.particle_mass: list[float] = []
        self.particle_radius: list[float] = []
        self.spring_indices: list[tuple[int, int]] = []
        self.spring_rest_length: list[float] = []
        self.spring_stiffness: list[float] = []
        self.spring_damping: list[float] = []
        self.spring_break_strain: list[float] = []  # inf: never breaks by strain (shorter lists pad with inf)
        self.spring_break_force: list[float] = []  # inf: never breaks by force

    @property
    def particle_count(self) -> int:
        return len(self.particle_q)

    @property
    def spring_count(self) -> int:
        return len(self.spring_indices)

    def add_particle(self, pos, vel=(0.0, 0.0, 0.0), mass: float = 1.0, radius: float = 0.0) -> int:
        """Add a particle at ``pos`` [m] with velocity ``vel`` [m/s], ``mass`` [kg] (0 = pinned or
        kinematic: forces never move it) and collision ``radius`` [m]. Returns its index."""
        index = self.particle_count
        pos = checks.vec3(pos, f"particle {index} position")
        vel = checks.vec3(vel, f"particle {index} velocity")
        mass = checks.number(mass, f"particle {index} mass", "kg", "give a number >= 0 (0 pins it)")
        if not math.isfinite(mass) or mass < 0.0:
            raise ValueError(f"particle {index} has mass {mass}; mass must be finite and >= 0 (0 pins it)")
        radius = checks.number(radius, f"particle {index} radius", "m", "give a number >= 0")
        if not math.isfinite(radius) or radius < 0.0:
            raise ValueError(f"particle {index} has radius {radius}; radius must be finite and >= 0")
        self.particle_q.append(pos)
        self.particle_qd.append(vel)
        self.particle_mass.append(mass)
        self.particle_radius.append(radius)
        return index

    def add_particles(self, positions, velocities=None, masses=1.0, radii=0.0) -> np.ndarray:
        """Add many particles at once; ``positions`` (N, 3). Returns their indices, shape (N,)."""
        first = self.particle_count
        positions = checks.vectors(positions, "add_particles positions", item=f"row (particle {first} +)")
        n = len(positions)
        if velocities is None:
            velocities = np.zeros((n, 3))
        else:
            velocities = checks.vectors(velocities, "add_particles velocities", item=f"row (particle {first} +)")
            checks.same_length(positions=positions, velocities=velocities)
        masses = checks.numbers_array(masses, "add_particles masses", n, lo=0.0,
                                      item=f"row (particle {first} +)", unit="kg")
        radii = checks.numbers_array(radii, "add_particles radii", n, lo=0.0, item=f"row (particle {first} +)",
                                     unit="m")
        self.particle_q.extend(map(tuple, positions.tolist()))  # (checked above as add_particle checks one)
        self.particle_qd.extend(map(tuple, velocities.tolist()))
        self.particle_mass.extend(masses.tolist())
        self.particle_radius.extend(radii.tolist())
        return np.arange(first, first + n, dtype=np.int64)

    def add_spring(self, i: int, j: int, stiffness: float, damping: float = 0.0, rest_length: float | None = None,
                   *, break_strain: float | None = None, break_force: float | None = None) -> int:
        """Join particles ``i`` and ``j`` with a damped spring: stiffness [N/m], damping [N s/m],
        rest length [m] (default: their current distance). Returns the spring index.

        ``break_strain`` (tensile strain (l - L) / L, > 0) and/or ``break_force`` (tension [N], > 0)
        make the spring breakable: once a step ends past either threshold it stops acting for good
        (``warpsim.core.fracture``). None (default): it never breaks."""
        index = self.spring_count
        n = self.particle_count
        for name, p in (("i", i), ("j", j)):
            if isinstance(p, (bool, np.bool_)) or not isinstance(p, (int, np.integer)):
                raise ValueError(f"spring {index}: particle {name}={checks.show(p)} is not an integer index; "
                                 "pass the index add_particle returned")
            if p < 0 or p >= n:
                raise ValueError(f"spring {index}: particle {name}={p!r} is out of range [0, {n}); add the particle first")
        if i == j:
            raise ValueError(f"spring {index} joins particle {i} to itself; join two different particles")
        for name, value in (("stiffness", stiffness), ("damping", damping)):
            v = checks.number(value, f"spring {index} {name}", fix="give a number >= 0")
            if not math.isfinite(v) or v < 0.0:
                raise ValueError(f"spring {index} has {name} {value}; it must be finite and >= 0")
        distance = float(np.linalg.norm(np.subtract(self.particle_q[i], self.particle_q[j])))
        if rest_length is None:
            rest_length = distance
        else:
            rest_length = checks.number(rest_length, f"spring {index} rest length", "m", "give a number >= 0")
            if not math.isfinite(rest_length) or rest_length < 0.0:
                raise ValueError(f"spring {index} has rest length {rest_length}; it must be finite and >= 0")
            _check_coincident(index, i, j, distance, rest_length)
        strain, force = _break_thresholds(index, break_strain, break_force, float(rest_length))
        self._pad_break_thresholds()
        self.spring_break_strain.append(strain)
        self.spring_break_force.append(force)
        self.spring_indices.append((int(i), int(j)))
        self.spring_rest_length.append(float(rest_length))
        self.spring_stiffness.append(float(stiffness))
        self.spring_damping.append(float(damping))
        return index

    def add_springs(self, indices, stiffness, damping=0.0, rest_length=None) -> np.ndarray:
        """Add many unbreakable springs at once: ``indices`` (M, 2) particle pairs; ``stiffness`` [N/m],
        ``damping`` [N s/m] and ``rest_length`` [m] scalars or shape (M,) (rest length default:
        the current distances). Checked as ``add_spring`` checks one. Returns the indices (M,)."""
        first = self.spring_count
        ij = np.asarray(indices)
        if ij.ndim != 2 or ij.shape[1] != 2 or not np.issubdtype(ij.dtype, np.integer):
            raise ValueError(f"add_springs indices have shape {ij.shape} and dtype {ij.dtype}; give (M, 2) integer "
                             "particle pairs")
        m, n = len(ij), self.particle_count
        bad = np.flatnonzero((ij < 0).any(1) | (ij >= n).any(1))
        if len(bad):
            raise ValueError(f"spring {first + int(bad[0])}: particles {ij[bad[0]].tolist()} are out of range [0, {n}); "
                             "add the particles first")
        bad = np.flatnonzero(ij[:, 0] == ij[:, 1])
        if len(bad):
            raise ValueError(f"spring {first + int(bad[0])} joins particle {int(ij[bad[0], 0])} to itself; join two "
                             "different particles")
        values = {}
        for name, value in (("stiffness", stiffness), ("damping", damping),
                            ("rest length", pair_distances(self.particle_q, ij) if rest_length is None else
                             rest_length)):
            v = np.broadcast_to(np.asarray(value, dtype=np.float64), (m,))
            bad = np.flatnonzero(~np.isfinite(v) | (v < 0.0))
            if len(bad):
                raise ValueError(f"spring {first + int(bad[0])} has {name} {v[bad[0]]}; it must be finite and >= 0")
            values[name] = v
        self.spring_indices.extend(map(tuple, ij.tolist()))
        self.spring_rest_length.extend(values["rest length"].tolist())
        self.spring_stiffness.extend(values["stiffness"].tolist())
        self.spring_damping.extend(values["damping"].tolist())
        return np.arange(first, first + m)

    def _check_coincident_springs(self):
        """ValueError for a spring with rest length > 0 whose particles sit at one position (it
        would push along no direction: no force at all), e.g. after particle_q was edited."""
        if not self.spring_count:
            return
        q = np.asarray(self.particle_q, dtype=np.float64).reshape(-1, 3)
        ij = np.asarray(self.spring_indices, dtype=np.int64).reshape(-1, 2)
        rest = np.asarray(self.spring_rest_length, dtype=np.float64)
        dist = np.linalg.norm(q[ij[:, 0]] - q[ij[:, 1]], axis=1)
        bad = np.flatnonzero((dist <= _COINCIDENT * np.maximum(rest, 1e-300)) & (rest > 0.0))
        if len(bad):
            s = int(bad[0])
            _check_coincident(s, int(ij[s, 0]), int(ij[s, 1]), float(dist[s]), float(rest[s]))

    def _pad_break_thresholds(self):
        """Springs appended to the lists directly (e.g. by the cloth builder) never break."""
        for values in (self.spring_break_strain, self.spring_break_force):
            values.extend([math.inf] * (self.spring_count - len(values)))

    def set_spring_breaking(self, springs, break_strain: float | None = None,
                            break_force: float | None = None) -> None:
        """Give existing springs (indices, e.g. ``body.spring_range("edge")``) the break thresholds
        of :meth:`add_spring` (None: that threshold is removed)."""
        self._pad_break_thresholds()
        idx = check_spring_indices(springs, self.spring_count, "set_spring_breaking")
        for s in idx:
            strain, force = _break_thresholds(int(s), break_strain, break_force, self.spring_rest_length[s])
            self.spring_break_strain[s] = strain
            self.spring_break_force[s] = force

    def finalize(self, device=None) -> Model:
        """Copy everything to ``device`` (None: Warp's preferred device) and return the Model."""
        self._check_coincident_springs()
        model = Model(device)
        d = model.device
        n = self.particle_count
        mass = np.array(self.particle_mass, dtype=np.float32).reshape(n)
        inv_mass = np.zeros_like(mass)
        inv_mass[mass > 0.0] = 1.0 / mass[mass > 0.0]
        model.particle_count = n
        model.particle_q = wp.array(np.array(self.particle_q, dtype=np.float32).reshape(n, 3), dtype=wp.vec3, device=d)
        model.particle_qd = wp.array(np.array(self.particle_qd, dtype=np.float32).reshape(n, 3), dtype=wp.vec3, device=d)
        # as given (float64): batched worlds shift these and cast once, as a scene built there would
        model.particle_q_host = np.array(self.particle_q, dtype=np.float64).reshape(n, 3)
        model.particle_qd_host = np.array(self.particle_qd, dtype=np.float64).reshape(n, 3)
        model.particle_mass = wp.array(mass, dtype=float, device=d)
        model.particle_inv_mass = wp.array(inv_mass, dtype=float, device=d)
        model.particle_radius = wp.array(np.array(self.particle_radius, dtype=np.float32).reshape(n), dtype=float, device=d)
        m = self.spring_count
        model.spring_count = m
        model.spring_indices = wp.array(np.array(self.spring_indices, dtype=np.int32).reshape(2 * m), dtype=int, device=d)
        model.spring_rest_length = wp.array(np.array(self.spring_rest_length, dtype=np.float32), dtype=float, device=d)
        model.spring_stiffness = wp.array(np.array(self.spring_stiffness, dtype=np.float32), dtype=float, device=d)
        model.spring_damping = wp.array(np.array(self.spring_damping, dtype=np.float32), dtype=float, device=d)
        self._pad_break_thresholds()
        strain = np.array(self.spring_break_strain[:m], dtype=np.float32)
        force = np.array(self.spring_break_force[:m], dtype=np.float32)
        model.spring_break_strain = wp.array(strain, dtype=float, device=d)
        model.spring_break_force = wp.array(force, dtype=float, device=d)
        model.spring_broken = wp.zeros(m, dtype=int, device=d)
        model.breakable_spring_count = int(np.count_nonzero(np.isfinite(strain) | np.isfinite(force)))
        offsets, springs = spring_adjacency(np.array(self.spring_indices, dtype=np.int64).reshape(2 * m), n)
        model.particle_spring_offsets = wp.array(offsets, dtype=int, device=d)
        model.particle_springs = wp.array(springs, dtype=int, device=d)
        return model


def pair_distances(points, pairs) -> np.ndarray:
    """|points[i] - points[j]| [m] of each pair (M, 2), rounded as ``add_spring`` rounds one
    (``np.linalg.norm`` of the difference: its dot product, here one per pair through
    ``np.matmul`` of a row and a column, which calls the same dot)."""
    ij = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    q = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    d = q[ij[:, 0]] - q[ij[:, 1]]
    return np.sqrt(np.matmul(d[:, None, :], d[:, :, None]).reshape(-1))


def _break_thresholds(index: int, break_strain, break_force, rest_length: float) -> tuple:
    """(strain, force) thresholds of spring ``index`` as floats (inf = none); ValueError naming the
    spring for a value that is not a finite number > 0, or a strain threshold on a spring of rest
    length 0."""
    out = []
    for name, value, unit in (("break_strain", break_strain, ""), ("break_force", break_force, " N")):
        if value is None:
            out.append(math.inf)
            continue
        try:
            v = float(value)
        except (TypeError, ValueError):
            raise ValueError(f"spring {index} has {name} {value!r}; give a number > 0 or None (never breaks)") from None
        if not math.isfinite(v) or v <= 0.0:
            raise ValueError(f"spring {index} has {name} {value}{unit}; it must be a finite number > 0 "
                             "(or None: never breaks)")
        out.append(v)
    if math.isfinite(out[0]) and rest_length <= 0.0:
        raise ValueError(f"spring {index} has rest length 0, so break_strain={break_strain} is undefined; "
                         "give break_force instead")
    return out[0], out[1]


def check_spring_indices(springs, count: int, what: str) -> np.ndarray:
    """Validate spring indices (a range, sequence or array); returns them as int64."""
    idx = np.asarray(list(springs) if isinstance(springs, range) else springs).reshape(-1)
    if idx.size and idx.dtype.kind not in "iu":
        raise ValueError(f"{what}: spring indices must be integers, got dtype {idx.dtype}")
    idx = idx.astype(np.int64)
    bad = idx[(idx < 0) | (idx >= count)]
    if len(bad):
        raise ValueError(f"{what}: spring index {int(bad[0])} is out of range [0, {count}); add the spring first")
    return idx


def check_indices(indices: Sequence[int], count: int, what: str) -> np.ndarray:
    """Validate particle indices for a force or collider; returns them as int32."""
    if isinstance(indices, (str, bytes)) or indices is None:
        raise ValueError(f"{what}: particle indices must be a sequence of integers, got {checks.show(indices)}")
    raw = np.asarray(indices)
    if raw.dtype.kind not in "iu" and not (raw.dtype.kind == "f" and np.all(np.isfinite(raw))
                                          and np.all(raw == np.round(raw))) and raw.size:
        raise ValueError(f"{what}: particle indices must be integers, got {checks.show(indices)}; pass the indices "
                         "add_particle returned")
    idx = raw.astype(np.int64).reshape(-1)
    bad = idx[(idx < 0) | (idx >= count)]
    if len(bad):
        raise ValueError(f"{what}: particle index {int(bad[0])} is out of range [0, {count})")
    return idx.astype(np.int32)
