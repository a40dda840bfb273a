"""Flocking and crowds: boids that fly or swim (:class:`Flock`) and agents that walk on terrain
(:class:`Crowd`), stepped by the Warp kernels in ``warpsim.kernels.agents``.

Example::

    import numpy as np, warpsim as ws
    from warpsim.agents import Flock, BoidParams

    rng = np.random.default_rng(0)
    flock = Flock(rng.uniform(0, 20, (500, 3)), rng.normal(0, 1, (500, 3)),
                  params=BoidParams(max_speed=5.0), bounds=((0, 0, 0), (20, 20, 20)), wrap=True)
    for _ in range(100):
        flock.step(1 / 30)
    print(ws.agents.polarization(flock.velocities.numpy()))

Each ``step(dt)`` rebuilds the neighbour grid (``wp.HashGrid``) on the host, outside any graph
capture, then launches the rule and integration kernels; it allocates nothing.

Agent states (:class:`AgentState`): FLYING, RESTING, WALKING, CLIMBING, FALLEN, and LANDING (a
tired flyer on its way down to rest).
"""

from __future__ import annotations

import enum
import math
from dataclasses import asdict, dataclass, fields

import numpy as np
import warp as wp

from .kernels import agents as K

__all__ = [
    "AgentState",
    "BoidParams",
    "Crowd",
    "Flock",
    "FoodSources",
    "Obstacles",
    "Terrain",
    "WalkerParams",
    "nearest_distances",
    "polarization",
    "radius_of_gyration",
    "same_group_fraction",
]


class AgentState(enum.IntEnum):
    """Per-agent state (``int`` array ``state``), also written to USD as the ``state`` primvar."""

    FLYING = 0
    RESTING = 1
    WALKING = 2
    CLIMBING = 3
    FALLEN = 4
    LANDING = 5


# --------------------------------------------------------------------------------------
# Parameters
# --------------------------------------------------------------------------------------
def _check_fields(obj, positive=(), nonnegative=(), unit_interval=(), name=None):
    name = name or type(obj).__name__
    for f in fields(obj):
        value = getattr(obj, f.name)
        if value is None or isinstance(value, (tuple, list)):
            continue
        try:
            value = float(value)
        except (TypeError, ValueError):
            raise ValueError(f"{name}.{f.name} must be a number, got {value!r}") from None
        if not math.isfinite(value):
            raise ValueError(f"{name}.{f.name} must be finite, got {value}")
    for key in positive:
        if getattr(obj, key) is not None and not getattr(obj, key) > 0.0:
            raise ValueError(f"{name}.{key} must be > 0, got {getattr(obj, key)}")
    for key in nonnegative:
        if getattr(obj, key) is not None and not getattr(obj, key) >= 0.0:
            raise ValueError(f"{name}.{key} must be >= 0, got {getattr(obj, key)}")
    for key in unit_interval:
        if not 0.0 <= getattr(obj, key) <= 1.0:
            raise ValueError(f"{name}.{key} must lie in [0, 1], got {getattr(obj, key)}")


def _rule_struct(values: dict) -> K.RuleParams:
    r = K.RuleParams()
    for key, value in values.items():
        setattr(r, key, value)
    return r


@dataclass
class BoidParams:
    """Behaviour of one species of flyers or swimmers. Lengths [m], speeds [m/s], steering
    accelerations [m/s^2] (unit mass), times [s], energy in arbitrary units.

    Reynolds rules: within ``perception_radius`` and the field of view ``fov_deg`` (a cone of
    that full angle around the heading) an agent steers away from neighbours closer than
    ``separation_radius`` (``separation_radius_other`` for other species), matches the mean
    velocity of, and moves to the centre of, its own species. ``min_distance`` (and
    ``min_distance_other``) is a hard minimum distance enforced by a position correction (0: off).
    The steering sum is limited to ``max_force``; speed stays in [min_speed, max_speed].

    Energy drains at ``drain_rate`` per second of flight (0: never tires); at
    ``land_threshold`` the agent lands, rests ``rest_time`` and takes off again. Food within
    ``food_sense_radius`` attracts hungry agents (energy below ``energy_max``); within
    ``food_eat_radius`` they take a bite (``food_energy``) every ``bite_interval``. Drafting: the
    upwash slot ``draft_back`` behind and ``draft_side`` beside a neighbour of the same species
    saves up to ``draft_saving`` of the drain (Gaussian of width ``draft_width``), and
    ``draft_weight`` steers agents into the nearest slot within ``draft_time``.
    """

    max_speed: float = 8.0
    min_speed: float = 2.0
    max_force: float = 10.0
    perception_radius: float = 3.0
    separation_radius: float = 1.0
    separation_radius_other: float | None = None
    fov_deg: float = 270.0
    min_distance: float = 0.0
    min_distance_other: float | None = None
    separation_weight: float = 1.5
    alignment_weight: float = 1.0
    cohesion_weight: float = 1.0
    goal_weight: float = 0.0
    avoid_distance: float = 2.0
    avoid_weight: float = 2.0
    body_radius: float = 0.1
    boundary_weight: float = 1.0
    min_height: float = 0.0
    energy_max: float = 1.0
    drain_rate: float = 0.0
    land_threshold: float = 0.2
    rest_time: float = 5.0
    descent_speed: float = 1.5
    takeoff_speed: float = 2.0
    food_sense_radius: float = 0.0
    food_eat_radius: float = 0.5
    food_weight: float = 1.0
    food_energy: float = 0.25
    bite_interval: float = 0.5
    draft_weight: float = 0.0
    draft_saving: float = 0.0
    draft_back: float = 0.8
    draft_side: float = 0.6
    draft_width: float = 0.3
    draft_time: float = 1.0

    def validate(self, name="BoidParams"):
        _check_fields(self, name=name,
                      positive=("max_speed", "max_force", "perception_radius", "energy_max", "rest_time",
                                "descent_speed", "draft_width", "draft_time", "avoid_distance"),
                      nonnegative=("min_speed", "separation_radius", "separation_radius_other", "min_distance",
                                   "min_distance_other", "body_radius", "min_height", "drain_rate",
                                   "land_threshold", "takeoff_speed", "food_sense_radius", "food_eat_radius",
                                   "food_energy", "bite_interval", "draft_back", "draft_side",
                                   "separation_weight", "alignment_weight", "cohesion_weight", "goal_weight",
                                   "avoid_weight", "boundary_weight", "food_weight", "draft_weight"),
                      unit_interval=("draft_saving",))
        if self.min_speed > self.max_speed:
            raise ValueError(f"{name}.min_speed = {self.min_speed} exceeds max_speed = {self.max_speed}")
        if not 0.0 < self.fov_deg <= 360.0:
            raise ValueError(f"{name}.fov_deg must lie in (0, 360] degrees, got {self.fov_deg}")
        if self.land_threshold >= self.energy_max and self.drain_rate > 0.0:
            raise ValueError(f"{name}.land_threshold = {self.land_threshold} must be below energy_max = "
                             f"{self.energy_max}")
        return self

    def rule_values(self) -> dict:
        """The neighbour-rule parameters (fields of ``kernels.agents.RuleParams``)."""
        sep_other = self.separation_radius if self.separation_radius_other is None else self.separation_radius_other
        md_other = self.min_distance if self.min_distance_other is None else self.min_distance_other
        return _rule_values(self.perception_radius, self.separation_radius, sep_other, self.min_distance, md_other,
                            self.fov_deg, self.max_speed, self.max_force,
                            draft=int(self.draft_weight > 0.0 or self.draft_saving > 0.0),
                            draft_back=self.draft_back, draft_side=self.draft_side,
                            draft_width=self.draft_width, draft_time=self.draft_time)

    def flight_struct(self) -> K.FlightParams:
        f = K.FlightParams()
        f.min_speed = self.min_speed
        f.w_separation = self.separation_weight
        f.w_alignment = self.alignment_weight
        f.w_cohesion = self.cohesion_weight
        f.w_draft = self.draft_weight
        f.w_avoid = self.avoid_weight
        f.w_food = self.food_weight
        f.w_goal = self.goal_weight
        f.w_boundary = self.boundary_weight
        for key in ("avoid_distance", "body_radius", "min_height", "energy_max", "drain_rate", "draft_saving",
                    "land_threshold", "rest_time", "descent_speed", "takeoff_speed", "food_sense_radius",
                    "food_eat_radius", "food_energy", "bite_interval"):
            setattr(f, key, float(getattr(self, key)))
        return f


def _rule_values(perception, sep, sep_other, md, md_other, fov_deg, max_speed, max_force, draft=0,
                 draft_back=0.0, draft_side=0.0, draft_width=1.0, draft_time=1.0) -> dict:
    fov_cos = -1.0 if fov_deg >= 360.0 else math.cos(math.radians(0.5 * fov_deg))
    return {
        "perception_radius": float(perception), "separation_radius": float(sep),
        "separation_radius_other": float(sep_other), "min_distance": float(md), "min_distance_other": float(md_other),
        "query_radius": float(max(perception, sep, sep_other, md, md_other)), "fov_cos": float(fov_cos),
        "max_speed": float(max_speed), "max_force": float(max_force), "draft": int(draft),
        "draft_back": float(draft_back), "draft_side": float(draft_side), "draft_width": float(draft_width),
        "draft_time": float(draft_time),
    }


@dataclass
class WalkerParams:
    """Behaviour of ground agents (people, zombies). Lengths [m], speeds [m/s], steering
    accelerations [m/s^2], times [s].

    Agents walk at up to ``max_speed`` towards their goal (slowing inside ``slow_radius``,
    stopping inside ``arrive_radius``), keep ``personal_radius`` from strangers (other groups)
    and ``group_radius`` from their own group by steering, and never come closer than
    ``personal_distance`` / ``min_distance`` (position correction); they align with and cohere
    to their own group within ``perception_radius``. A move steeper than ``max_slope`` (rise
    over run; 0.3 = 30 %) is a climb at ``climb_speed`` along the surface, during which an
    agent falls ``fall_rate`` times per second on average; a fallen agent is a particle under
    ``gravity`` pushed off the slope at ``fall_speed``, slides where the ground is steeper than
    ``max_slope``, lies ``recovery_time`` where it is not, then walks on.
    """

    max_speed: float = 1.4
    max_force: float = 3.0
    perception_radius: float = 2.0
    personal_radius: float = 1.2
    group_radius: float = 0.6
    personal_distance: float = 0.6
    min_distance: float = 0.4
    fov_deg: float = 360.0
    separation_weight: float = 1.5
    alignment_weight: float = 0.2
    cohesion_weight: float = 0.3
    goal_weight: float = 1.0
    avoid_distance: float = 1.0
    avoid_weight: float = 2.0
    body_radius: float = 0.25
    boundary_weight: float = 1.0
    arrive_radius: float = 0.5
    slow_radius: float = 2.0
    max_slope: float = 0.3
    climb_speed: float = 0.3
    fall_rate: float = 0.1
    fall_speed: float = 1.0
    recovery_time: float = 60.0
    gravity: tuple = (0.0, -9.81, 0.0)

    def validate(self, name="WalkerParams"):
        _check_fields(self, name=name,
                      positive=("max_speed", "max_force", "perception_radius", "avoid_distance", "slow_radius",
                                "max_slope", "climb_speed"),
                      nonnegative=("personal_radius", "group_radius", "personal_distance", "min_distance",
                                   "separation_weight", "alignment_weight", "cohesion_weight", "goal_weight",
                                   "avoid_weight", "body_radius", "boundary_weight", "arrive_radius", "fall_rate",
                                   "fall_speed", "recovery_time"))
        if not 0.0 < self.fov_deg <= 360.0:
            raise ValueError(f"{name}.fov_deg must lie in (0, 360] degrees, got {self.fov_deg}")
        g = np.asarray(self.gravity, dtype=np.float64)
        if g.shape != (3,) or not np.isfinite(g).all():
            raise ValueError(f"{name}.gravity must be 3 finite numbers [m/s^2], got {self.gravity!r}")
        return self

    def rule_values(self) -> dict:
        return _rule_values(self.perception_radius, self.group_radius, self.personal_radius, self.min_distance,
                            self.personal_distance, self.fov_deg, self.max_speed, self.max_force)

    def walk_struct(self) -> K.WalkParams:
        w = K.WalkParams()
        w.w_separation = self.separation_weight
        w.w_alignment = self.alignment_weight
        w.w_cohesion = self.cohesion_weight
        w.w_avoid = self.avoid_weight
        w.w_goal = self.goal_weight
        w.w_boundary = self.boundary_weight
        for key in ("avoid_distance", "body_radius", "arrive_radius", "slow_radius", "max_slope", "climb_speed",
                    "fall_rate", "fall_speed", "recovery_time"):
            setattr(w, key, float(getattr(self, key)))
        w.gravity = wp.vec3(*[float(c) for c in self.gravity])
        return w


# --------------------------------------------------------------------------------------
# World: terrain, obstacles, food
# --------------------------------------------------------------------------------------
def _points(value, what, width=3):
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be an array of shape (n, {width}) [m]") from None
    if a.ndim == 1 and a.size == width:
        a = a[None]
    if a.ndim != 2 or a.shape[1] != width:
        raise ValueError(f"{what} must have shape (n, {width}), got {a.shape}")
    bad = np.flatnonzero(~np.isfinite(a).all(axis=1))
    if len(bad):
        raise ValueError(f"{what}[{bad[0]}] is not finite: {a[bad[0]]}; give finite values")
    return a


def _mesh_arrays(points, faces, what):
    pts = _points(points, f"{what} points")
    try:
        tri = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    except ValueError:
        raise ValueError(f"{what} faces must be triangles: an int array of shape (m, 3)") from None
    if len(tri) == 0:
        raise ValueError(f"{what} has no triangles")
    if tri.min() < 0 or tri.max() >= len(pts):
        bad = int(np.flatnonzero((tri < 0).any(axis=1) | (tri >= len(pts)).any(axis=1))[0])
        raise ValueError(f"{what} triangle {bad} indexes a vertex outside [0, {len(pts)}): {tri[bad].tolist()}")
    return pts, tri


class Terrain:
    """Ground for agents: y = h(x, z), flat, a height field or a triangle mesh (followed as a
    height field: the highest surface under the agent; model walls with steep but finite
    faces). Build with :meth:`flat`, :meth:`from_heights`, :meth:`from_function` or
    :meth:`from_mesh`."""

    def __init__(self, kind, height=0.0, heights=None, origin=(0.0, 0.0), spacing=1.0, points=None, faces=None):
        self.kind = kind
        self.flat_height = float(height)
        self.heights = heights
        self.origin = (float(origin[0]), float(origin[1]))
        self.spacing = float(spacing)
        self.points = points
        self.faces = faces
        self._cache = {}

    @classmethod
    def flat(cls, height=0.0):
        """The plane y = height [m]."""
        h = float(height)
        if not math.isfinite(h):
            raise ValueError(f"terrain height must be finite, got {height}")
        return cls(0, height=h)

    @classmethod
    def from_heights(cls, heights, spacing, origin=(0.0, 0.0)):
        """Height field: ``heights[i, k]`` [m] at x = origin[0] + i spacing, z = origin[1] +
        k spacing; bilinear in between, clamped outside."""
        h = np.asarray(heights, dtype=np.float64)
        if h.ndim != 2 or h.shape[0] < 2 or h.shape[1] < 2:
            raise ValueError(f"terrain heights must be a 2-D array of at least 2 x 2 samples, got shape {h.shape}")
        if not np.isfinite(h).all():
            i, k = np.argwhere(~np.isfinite(h))[0]
            raise ValueError(f"terrain heights[{i}, {k}] is not finite")
        if not (math.isfinite(float(spacing)) and float(spacing) > 0.0):
            raise ValueError(f"terrain spacing must be > 0 [m], got {spacing}")
        o = _points(origin, "terrain origin (x, z)", width=2)[0]
        return cls(1, height=float(h.min()), heights=h, origin=o, spacing=spacing)

    @classmethod
    def from_function(cls, fn, lower, upper, spacing):
        """Height field sampling ``fn(x, z)`` (NumPy, vectorised) on [lower, upper] (x, z pairs) [m]."""
        lo = _points(lower, "terrain lower (x, z)", width=2)[0]
        hi = _points(upper, "terrain upper (x, z)", width=2)[0]
        if not (hi > lo).all():
            raise ValueError(f"terrain upper {hi} must exceed lower {lo} in x and z")
        if not (math.isfinite(float(spacing)) and float(spacing) > 0.0):
            raise ValueError(f"terrain spacing must be > 0 [m], got {spacing}")
        n = np.maximum(np.ceil((hi - lo) / spacing).astype(int) + 1, 2)
        xs = lo[0] + spacing * np.arange(n[0])
        zs = lo[1] + spacing * np.arange(n[1])
        X, Z = np.meshgrid(xs, zs, indexing="ij")
        return cls.from_heights(np.broadcast_to(fn(X, Z), X.shape), spacing, lo)

    @classmethod
    def from_mesh(cls, points, faces):
        """A triangle mesh (points (v, 3) [m], triangles (m, 3)) followed from above."""
        pts, tri = _mesh_arrays(points, faces, "terrain mesh")
        return cls(2, height=float(pts[:, 1].min()), points=pts, faces=tri)

    # ----------------------------------------------------------------------------------
    def bind(self, device):
        """The kernel struct on ``device`` (built once per device)."""
        key = str(device)
        if key in self._cache:
            return self._cache[key][0]
        t = K.TerrainData()
        t.kind = self.kind
        t.height = self.flat_height
        t.origin_x, t.origin_z = self.origin
        t.spacing = self.spacing
        keep = []
        if self.kind == 1:
            t.heights = wp.array(self.heights.astype(np.float32), dtype=float, device=device)
            t.nx, t.nz = self.heights.shape
            keep.append(t.heights)
        else:
            t.heights = wp.zeros((1, 1), dtype=float, device=device)
            t.nx = t.nz = 1
        if self.kind == 2:
            mesh = wp.Mesh(points=wp.array(self.points.astype(np.float32), dtype=wp.vec3, device=device),
                           indices=wp.array(self.faces.reshape(-1).astype(np.int32), dtype=int, device=device))
            t.mesh = mesh.id
            t.top = float(self.points[:, 1].max() + 1.0)
            t.bottom = float(self.points[:, 1].min() - 1.0)
            keep.append(mesh)
        else:
            t.mesh = 0
            t.top = t.bottom = 0.0
        self._cache[key] = (t, keep)
        return t

    def sample(self, points, device=None):
        """(h, dh/dx, dh/dz) at points (n, 3) or (n, 2) (x, z) as a NumPy (n, 3) array."""
        device = wp.get_device(device)
        p = np.asarray(points, dtype=np.float64)
        if p.ndim == 2 and p.shape[1] == 2:
            p = np.stack([p[:, 0], np.zeros(len(p)), p[:, 1]], axis=1)
        p = _points(p, "terrain sample points")
        out = wp.zeros(len(p), dtype=wp.vec3, device=device)
        wp.launch(K.sample_terrain, len(p), inputs=[self.bind(device), wp.array(p.astype(np.float32), dtype=wp.vec3,
                                                                                 device=device), out], device=device)
        return out.numpy().astype(np.float64)

    def height(self, points, device=None):
        """Ground height h [m] at points (n, 3) or (n, 2)."""
        return self.sample(points, device)[:, 0]

    def bounds(self):
        """((x_min, z_min), (x_max, z_max)) of a height field or mesh, None for a flat plane."""
        if self.kind == 1:
            o = np.array(self.origin)
            return o, o + self.spacing * (np.array(self.heights.shape) - 1)
        if self.kind == 2:
            return self.points[:, [0, 2]].min(axis=0), self.points[:, [0, 2]].max(axis=0)
        return None

    def mesh(self, size=50.0):
        """(points (v, 3), triangles (m, 3)) for drawing; a flat plane is a square of side ``size``."""
        if self.kind == 2:
            return self.points, self.faces
        if self.kind == 1:
            nx, nz = self.heights.shape
            xs = self.origin[0] + self.spacing * np.arange(nx)
            zs = self.origin[1] + self.spacing * np.arange(nz)
            X, Z = np.meshgrid(xs, zs, indexing="ij")
            pts = np.stack([X, self.heights, Z], axis=-1).reshape(-1, 3)
        else:
            h = 0.5 * size
            pts = np.array([[-h, self.flat_height, -h], [h, self.flat_height, -h], [-h, self.flat_height, h], [h, self.flat_height, h]])
            nx = nz = 2
        idx = np.arange(nx * nz).reshape(nx, nz)
        a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[:-1, 1:], idx[1:, 1:]
        # counter-clockwise seen from above (+Y): normals point up
        tri = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)])
        return pts, tri


class Obstacles:
    """Obstacles agents steer around and never enter.

    spheres: [(center (3,), radius)] [m]; planes: [(normal (3,), offset)] half-spaces n . x >=
    offset are free (normals are normalised); meshes: [(points (v, 3), triangles (m, 3))]
    (closed meshes: the inside is solid)."""

    def __init__(self, spheres=(), planes=(), meshes=()):
        self.spheres = []
        for k, s in enumerate(spheres):
            try:
                c, r = s
            except (TypeError, ValueError):
                raise ValueError(f"obstacle sphere {k} must be (center, radius), got {s!r}") from None
            c = _points(c, f"obstacle sphere {k} center")[0]
            if not (math.isfinite(float(r)) and float(r) > 0.0):
                raise ValueError(f"obstacle sphere {k} radius must be > 0 [m], got {r}")
            self.spheres.append((c, float(r)))
        self.planes = []
        for k, pl in enumerate(planes):
            try:
                n, off = pl
            except (TypeError, ValueError):
                raise ValueError(f"obstacle plane {k} must be (normal, offset), got {pl!r}") from None
            n = _points(n, f"obstacle plane {k} normal")[0]
            if np.linalg.norm(n) == 0.0 or not math.isfinite(float(off)):
                raise ValueError(f"obstacle plane {k} needs a non-zero normal and a finite offset, got {pl!r}")
            self.planes.append((n / np.linalg.norm(n), float(off)))
        self.meshes = []
        for k, m in enumerate(meshes):
            try:
                pts, tri = m
            except (TypeError, ValueError):
                raise ValueError(f"obstacle mesh {k} must be (points, triangles), got {type(m).__name__}") from None
            self.meshes.append(_mesh_arrays(pts, tri, f"obstacle mesh {k}"))
        self._cache = {}

    @property
    def count(self):
        return len(self.spheres) + len(self.planes) + len(self.meshes)

    def bind(self, device):
        """The kernel struct on ``device`` (built once per device)."""
        key = str(device)
        if key in self._cache:
            return self._cache[key][0]
        o = K.Obstacles()
        sph = np.array([[*c, r] for c, r in self.spheres] or [[0.0, 0.0, 0.0, 0.0]], dtype=np.float32)
        pln = np.array([[*n, off] for n, off in self.planes] or [[0.0, 1.0, 0.0, 0.0]], dtype=np.float32)
        o.spheres = wp.array(sph, dtype=wp.vec4, device=device)
        o.planes = wp.array(pln, dtype=wp.vec4, device=device)
        keep = [o.spheres, o.planes]
        ids = []
        for pts, tri in self.meshes:
            mesh = wp.Mesh(points=wp.array(pts.astype(np.float32), dtype=wp.vec3, device=device),
                           indices=wp.array(tri.reshape(-1).astype(np.int32), dtype=int, device=device))
            keep.append(mesh)
            ids.append(mesh.id)
        o.meshes = wp.array(ids or [0], dtype=wp.uint64, device=device)
        keep.append(o.meshes)
        o.sphere_count = len(self.spheres)
        o.plane_count = len(self.planes)
        o.count = self.count
        self._cache[key] = (o, keep)
        return o

    def distance(self, points, max_dist=1.0e6, device=None):
        """Smallest signed distance [m] from each point (n, 3) to the obstacles (NumPy (n,))."""
        device = wp.get_device(device)
        p = _points(points, "obstacle distance points")
        out = wp.zeros(len(p), dtype=float, device=device)
        wp.launch(K.eval_obstacle_distance, len(p), inputs=[self.bind(device), wp.array(
            p.astype(np.float32), dtype=wp.vec3, device=device), float(max_dist), out], device=device)
        return out.numpy().astype(np.float64)


class FoodSources:
    """Food at ``positions`` (n, 3) [m] holding ``amounts`` (n,) bites each (ints >= 0)."""

    def __init__(self, positions, amounts):
        self.positions = _points(positions, "food positions")
        a = np.asarray(amounts)
        if a.ndim == 0:
            a = np.full(len(self.positions), a)
        if a.shape != (len(self.positions),):
            raise ValueError(f"food amounts must have shape ({len(self.positions)},), got {a.shape}")
        if not np.all(np.equal(np.mod(a, 1), 0)) or (a < 0).any():
            bad = int(np.flatnonzero((np.mod(a, 1) != 0) | (a < 0))[0])
            raise ValueError(f"food source {bad} has amount {a[bad]}; amounts are whole bites >= 0")
        self.initial_amounts = a.astype(np.int64)


def _food_struct(food, device):
    f = K.Food()
    if food is None:
        f.positions = wp.zeros(1, dtype=wp.vec3, device=device)
        f.amounts = wp.zeros(1, dtype=int, device=device)
        f.count = 0
    else:
        f.positions = wp.array(food.positions.astype(np.float32), dtype=wp.vec3, device=device)
        f.amounts = wp.array(food.initial_amounts.astype(np.int32), dtype=int, device=device)
        f.count = len(food.positions)
    return f


# --------------------------------------------------------------------------------------
# Common machinery
# --------------------------------------------------------------------------------------
class _Agents:
    """Arrays, neighbour grid and the rules kernel shared by Flock and Crowd."""

    def _setup(self, positions, velocities, kinds, groups, rules: list, bounds, wrap, margin, obstacles, terrain,
               goals, device):
        self.device = wp.get_device(device)
        x = positions
        n = len(x)
        self.agent_count = n
        if velocities is None:
            velocities = np.zeros((n, 3))
        vel = _points(velocities, "velocities")
        if vel.shape != x.shape:
            raise ValueError(f"velocities has shape {vel.shape} but positions has {x.shape}")
        self.space, self.box = self._space(bounds, wrap, margin, rules)
        if self.box is not None:
            lo, hi, w = self.box
            x = x.copy()
            for ax in range(3):
                if w[ax]:
                    x[:, ax] = lo[ax] + np.mod(x[:, ax] - lo[ax], hi[ax] - lo[ax])
        if obstacles is None:
            obstacles = Obstacles()
        if not isinstance(obstacles, Obstacles):
            raise ValueError(f"obstacles must be a warpsim.agents.Obstacles, got {type(obstacles).__name__}")
        if terrain is not None and not isinstance(terrain, Terrain):
            raise ValueError(f"terrain must be a warpsim.agents.Terrain, got {type(terrain).__name__}")
        self.obstacles, self.terrain = obstacles, terrain
        if goals is None:
            goals = x
        g = _points(goals, "goals")
        if len(g) == 1:
            g = np.repeat(g, n, axis=0)
        if g.shape != x.shape:
            raise ValueError(f"goals must have shape {x.shape} (one per agent) or (3,), got {g.shape}")

        d = self.device
        f3 = np.float32
        self.positions = wp.array(x.astype(f3), dtype=wp.vec3, device=d)
        """Agent positions [m], shape (agent_count,)."""
        self.velocities = wp.array(vel.astype(f3), dtype=wp.vec3, device=d)
        """Agent velocities [m/s], shape (agent_count,)."""
        speed = np.linalg.norm(vel, axis=1, keepdims=True)
        head = np.where(speed > 1e-9, vel / np.maximum(speed, 1e-12), [[0.0, 0.0, 1.0]])
        self.heading = wp.array(head.astype(f3), dtype=wp.vec3, device=d)
        """Unit heading (last non-zero velocity direction), shape (agent_count,)."""
        self.kinds = wp.array(kinds.astype(np.int32), dtype=int, device=d)
        self.groups = wp.array(groups.astype(np.int32), dtype=int, device=d)
        self.goals = wp.array(g.astype(f3), dtype=wp.vec3, device=d)
        """Goal position of each agent [m], shape (agent_count,)."""
        self.timer = wp.zeros(n, dtype=float, device=d)
        """Remaining rest / recovery time [s] (RESTING, lying FALLEN agents), shape (agent_count,)."""
        self.rules = wp.array([_rule_struct(r) for r in rules], dtype=K.RuleParams, device=d)
        self.rule_values = rules
        self.separation = wp.zeros(n, dtype=wp.vec3, device=d)
        """Separation steering of the last step [m/s^2] (also alignment, cohesion, draft)."""
        self.alignment = wp.zeros(n, dtype=wp.vec3, device=d)
        self.cohesion = wp.zeros(n, dtype=wp.vec3, device=d)
        self.draft = wp.zeros(n, dtype=wp.vec3, device=d)
        self.benefit = wp.zeros(n, dtype=float, device=d)
        """Upwash benefit in [0, 1] of the last step."""
        self.push = wp.zeros(n, dtype=wp.vec3, device=d)
        self.neighbour_counts = wp.zeros(n, dtype=int, device=d)
        self._orientations = wp.zeros(n, dtype=wp.quat, device=d)
        self._obstacles = obstacles.bind(d)
        self._terrain = (terrain or Terrain.flat(-1.0e30)).bind(d)
        self.cell_size = max(r["query_radius"] for r in rules)
        if self.box is not None:
            cells = np.ceil((self.box[1] - self.box[0]) / self.cell_size).astype(int)
            dims = np.clip(cells, 4, 128)
        else:
            dims = np.full(3, int(np.clip(np.ceil((2 * n) ** (1 / 3)), 4, 128)))
        self.grid = wp.HashGrid(int(dims[0]), int(dims[1]), int(dims[2]), device=d)
        self.grid.reserve(n)
        self.time = 0.0
        """Simulated time [s]."""
        self.step_count = 0

    @staticmethod
    def _space(bounds, wrap, margin, rules):
        s = K.Space()
        if isinstance(wrap, (bool, np.bool_, int)):
            wrap = (bool(wrap),) * 3
        try:
            w = tuple(bool(c) for c in wrap)
        except TypeError:
            raise ValueError(f"wrap must be a bool or 3 bools (x, y, z), got {wrap!r}") from None
        if len(w) != 3:
            raise ValueError(f"wrap must be a bool or 3 bools (x, y, z), got {wrap!r}")
        if bounds is None:
            if any(w):
                raise ValueError("wrap needs bounds=(lower, upper): the periodic box [m]")
            s.lower = wp.vec3(0.0)
            s.upper = wp.vec3(1.0)
            s.bounded = 0
            s.wrap_x = s.wrap_y = s.wrap_z = 0
            s.margin = 1.0
            return s, None
        try:
            lo, hi = bounds
        except (TypeError, ValueError):
            raise ValueError(f"bounds must be (lower, upper) with 3 coordinates each, got {bounds!r}") from None
        lo = _points(lo, "bounds lower")[0]
        hi = _points(hi, "bounds upper")[0]
        if not (hi > lo).all():
            raise ValueError(f"bounds upper {hi.tolist()} must exceed lower {lo.tolist()} on every axis")
        margin = float(margin)
        if not (math.isfinite(margin) and margin > 0.0):
            raise ValueError(f"margin must be > 0 [m], got {margin}")
        rq = max(r["query_radius"] for r in rules)
        for ax in range(3):
            if w[ax] and not rq < 0.5 * (hi[ax] - lo[ax]):
                raise ValueError(f"wrap on axis {'xyz'[ax]}: the box ({hi[ax] - lo[ax]:g} m) must be more than twice "
                                 f"the largest perception/separation radius ({rq:g} m); enlarge bounds or shrink radii")
        s.lower = wp.vec3(*lo.astype(np.float32))
        s.upper = wp.vec3(*hi.astype(np.float32))
        s.wrap_x, s.wrap_y, s.wrap_z = (int(c) for c in w)
        s.bounded = 1
        s.margin = margin
        return s, (lo, hi, w)

    def eval_rules(self, lookahead=0.0):
        """Rebuild the neighbour grid and evaluate the neighbour rules into ``separation``,
        ``alignment``, ``cohesion``, ``draft``, ``benefit``, ``push`` (hard distances predicted
        ``lookahead`` [s] ahead; the step passes dt) and ``neighbour_counts``."""
        self.grid.build(self.positions, self.cell_size)
        wp.launch(K.eval_neighbour_rules, self.agent_count,
                  inputs=[self.grid.id, self.positions, self.velocities, self.kinds, self.groups, self.state,
                          self.rules, self.space, float(lookahead)],
                  outputs=[self.separation, self.alignment, self.cohesion, self.draft, self.benefit, self.push,
                           self.neighbour_counts], device=self.device)

    def orientations(self) -> wp.array:
        """Quaternions (x, y, z, w) turning +Z to each agent's heading (+Y up), shape (agent_count,)."""
        wp.launch(K.eval_orientations, self.agent_count, inputs=[self.heading, self.state, int(self._upright)],
                  outputs=[self._orientations], device=self.device)
        return self._orientations

    def state_counts(self) -> dict:
        """{AgentState name: number of agents in it} (reads back from the device)."""
        s = self.state.numpy()
        return {st.name: int((s == st).sum()) for st in AgentState}


def _check_dt(dt):
    try:
        value = float(dt)
    except (TypeError, ValueError):
        raise ValueError(f"dt must be a number > 0 [s], got {dt!r}") from None
    if not (math.isfinite(value) and value > 0.0):
        raise ValueError(f"dt must be > 0 and finite [s], got {dt}")
    return value


def _int_labels(values, n, what, default=0):
    if values is None:
        return np.full(n, default, dtype=np.int64)
    a = np.asarray(values)
    if a.ndim == 0:
        a = np.full(n, a)
    if a.shape != (n,) or not np.issubdtype(a.dtype, np.integer):
        raise ValueError(f"{what} must be {n} integers (one per agent), got shape {a.shape} of {a.dtype}")
    if (a < 0).any():
        bad = int(np.flatnonzero(a < 0)[0])
        raise ValueError(f"{what}[{bad}] = {a[bad]} must be >= 0")
    return a.astype(np.int64)


# --------------------------------------------------------------------------------------
# Flock
# --------------------------------------------------------------------------------------
class Flock(_Agents):
    """Boids that fly or swim in 3-D.

    Args:
        positions: (n, 3) [m]; velocities: (n, 3) [m/s] (default zero).
        species: (n,) ints in [0, len(params)) (default 0): each species has its own
            :class:`BoidParams`; alignment and cohesion act within a species, separation between all.
        params: a BoidParams or a list of one per species.
        bounds: (lower, upper) box [m]; wrapped axes are periodic, the others have soft walls
            ``margin`` [m] deep and a hard clamp. None: unbounded.
        wrap: bool or 3 bools (x, y, z).
        terrain: a :class:`Terrain` to rest on (needed when a species drains energy); flyers
            stay ``min_height`` above it.
        obstacles: :class:`Obstacles`; food: :class:`FoodSources`; goals: (n, 3) or (3,) [m]
            (used by species with ``goal_weight`` > 0); energy: (n,) initial energy (default
            each species' ``energy_max``); state: (n,) initial :class:`AgentState` (FLYING or
            RESTING; default FLYING).
    """

    _upright = False

    def __init__(self, positions, velocities=None, species=None, params=None, *, bounds=None, wrap=False,
                 margin=2.0, terrain=None, obstacles=None, food=None, goals=None, energy=None, state=None,
                 device=None):
        x = _points(positions, "positions")
        n = len(x)
        if n == 0:
            raise ValueError("positions is empty: a flock needs at least one agent")
        params = [BoidParams()] if params is None else params
        if isinstance(params, BoidParams):
            params = [params]
        params = list(params)
        for k, p in enumerate(params):
            if not isinstance(p, BoidParams):
                raise ValueError(f"params[{k}] is a {type(p).__name__}, not a BoidParams")
            p.validate(f"params[{k}]" if len(params) > 1 else "BoidParams")
        sp = _int_labels(species, n, "species")
        if sp.max() >= len(params):
            bad = int(np.flatnonzero(sp >= len(params))[0])
            raise ValueError(f"species[{bad}] = {sp[bad]} but only {len(params)} BoidParams were given "
                             "(one per species)")
        if terrain is None and any(p.drain_rate > 0.0 for p in params):
            raise ValueError("BoidParams.drain_rate > 0 makes agents land to rest: give terrain= (e.g. "
                             "Terrain.flat(0.0))")
        if food is not None and not isinstance(food, FoodSources):
            raise ValueError(f"food must be a warpsim.agents.FoodSources, got {type(food).__name__}")
        self.params = params
        self._setup(x, velocities, sp, sp, [p.rule_values() for p in params], bounds, wrap, margin, obstacles,
                    terrain, goals, device)
        d = self.device
        self.species = self.kinds
        """Species of each agent, shape (agent_count,)."""
        self.flight = wp.array([p.flight_struct() for p in params], dtype=K.FlightParams, device=d)
        emax = np.array([p.energy_max for p in params])[sp]
        e = emax if energy is None else np.asarray(energy, dtype=np.float64)
        if e.shape != (n,) or not np.isfinite(e).all() or (e < 0).any():
            raise ValueError(f"energy must be {n} finite values >= 0, got shape {e.shape}")
        self.energy = wp.array(e.astype(np.float32), dtype=float, device=d)
        """Energy of each agent, shape (agent_count,)."""
        st = _int_labels(state, n, "state", default=int(AgentState.FLYING))
        if not np.isin(st, (AgentState.FLYING, AgentState.RESTING)).all():
            bad = int(np.flatnonzero(~np.isin(st, (AgentState.FLYING, AgentState.RESTING)))[0])
            raise ValueError(f"state[{bad}] = {st[bad]}: flock agents start FLYING (0) or RESTING (1)")
        self.state = wp.array(st.astype(np.int32), dtype=int, device=d)
        """AgentState of each agent, shape (agent_count,)."""
        rest = np.array([p.rest_time for p in params])[sp]
        self.timer.assign((np.where(st == AgentState.RESTING, rest, 0.0)).astype(np.float32))
        self.bite_timer = wp.zeros(n, dtype=float, device=d)
        self.bites = wp.zeros(n, dtype=int, device=d)
        """Bites each agent has eaten, shape (agent_count,)."""
        self.food = food
        self._food = _food_struct(food, d)
        self.food_amounts = self._food.amounts
        """Bites left at each food source, shape (food count,)."""

    def step(self, dt: float) -> None:
        """Advance the flock by ``dt`` [s]."""
        dt = _check_dt(dt)
        self.eval_rules(dt)
        wp.launch(K.integrate_flyers, self.agent_count,
                  inputs=[self.rules, self.flight, self.space, self._obstacles, self._terrain, self._food, self.kinds,
                          self.separation, self.alignment, self.cohesion, self.draft, self.benefit, self.push,
                          self.goals, dt],
                  outputs=[self.positions, self.velocities, self.state, self.energy, self.timer, self.bite_timer,
                           self.bites, self.heading], device=self.device)
        self.time += dt
        self.step_count += 1


# --------------------------------------------------------------------------------------
# Crowd
# --------------------------------------------------------------------------------------
class Crowd(_Agents):
    """Agents that walk on terrain towards goals (people, zombies).

    Args:
        positions: (n, 3) [m] (y is replaced by the ground height) or (n, 2) (x, z).
        goals: (n, 3) / (n, 2) or one (3,) goal for all [m].
        groups: (n,) ints; agents of one group are not strangers to each other (default: one
            group per agent, everyone a stranger).
        params: :class:`WalkerParams`.
        terrain: :class:`Terrain` (default flat y = 0).
        obstacles, bounds, wrap, margin: as for :class:`Flock`.
        seed: random stream for falls (deterministic for a given seed).
    """

    _upright = True

    def __init__(self, positions, goals, groups=None, params=None, *, terrain=None, obstacles=None, bounds=None,
                 wrap=False, margin=1.0, seed=0, device=None):
        x = self._xz_or_xyz(positions, "positions")
        n = len(x)
        if n == 0:
            raise ValueError("positions is empty: a crowd needs at least one agent")
        g = self._xz_or_xyz(goals, "goals")
        params = WalkerParams() if params is None else params
        if not isinstance(params, WalkerParams):
            raise ValueError(f"params must be a WalkerParams, got {type(params).__name__}")
        params.validate()
        self.params = params
        grp = _int_labels(groups, n, "groups") if groups is not None else np.arange(n)
        terrain = Terrain.flat(0.0) if terrain is None else terrain
        if not isinstance(terrain, Terrain):
            raise ValueError(f"terrain must be a warpsim.agents.Terrain, got {type(terrain).__name__}")
        device = wp.get_device(device)
        x[:, 1] = terrain.height(x, device)
        g[:, 1] = terrain.height(g, device) if len(g) else g[:, 1]
        self._setup(x, None, np.zeros(n, dtype=np.int64), grp, [params.rule_values()], bounds, wrap, margin,
                    obstacles, terrain, g, device)
        d = self.device
        self.group_ids = self.groups
        """Group of each agent, shape (agent_count,)."""
        self.state = wp.full(n, int(AgentState.WALKING), dtype=int, device=d)
        """AgentState of each agent (WALKING, CLIMBING or FALLEN), shape (agent_count,)."""
        self._walk = params.walk_struct()
        self.seed = int(seed)
        self._step_counter = wp.zeros(1, dtype=int, device=d)

    @staticmethod
    def _xz_or_xyz(value, what):
        a = np.asarray(value, dtype=np.float64)
        if a.ndim == 1 and a.size in (2, 3):
            a = a[None]
        if a.ndim == 2 and a.shape[1] == 2:
            a = np.stack([a[:, 0], np.zeros(len(a)), a[:, 1]], axis=1)
        return _points(a, what).copy()

    def step(self, dt: float) -> None:
        """Advance the crowd by ``dt`` [s]."""
        dt = _check_dt(dt)
        self.eval_rules(dt)
        wp.launch(K.integrate_walkers, self.agent_count,
                  inputs=[self.rules, self._walk, self.space, self._obstacles, self._terrain, self.kinds,
                          self.separation, self.alignment, self.cohesion, self.push, self.goals, self.seed,
                          self._step_counter, dt],
                  outputs=[self.positions, self.velocities, self.state, self.timer, self.heading], device=self.device)
        wp.launch(K.advance_counter, 1, inputs=[self._step_counter], device=self.device)
        self.time += dt
        self.step_count += 1

    def distance_to_goals(self) -> np.ndarray:
        """Horizontal distance [m] from each agent to its goal (NumPy, reads back)."""
        d = self.goals.numpy() - self.positions.numpy()
        return np.hypot(d[:, 0], d[:, 2])


# --------------------------------------------------------------------------------------
# Metrics (host, NumPy)
# --------------------------------------------------------------------------------------
def polarization(velocities) -> float:
    """Order parameter phi = |sum of unit headings| / n in [0, 1] (= |sum v| / (n v0) at a
    common speed v0); about 0.92 / sqrt(n) for random headings in 3-D."""
    v = np.asarray(velocities, dtype=np.float64).reshape(-1, 3)
    s = np.linalg.norm(v, axis=1)
    u = v[s > 0] / s[s > 0, None]
    return float(np.linalg.norm(u.sum(axis=0)) / max(len(v), 1))


def radius_of_gyration(positions) -> float:
    """sqrt(mean |x - mean(x)|^2) [m]."""
    x = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    return float(np.sqrt(((x - x.mean(axis=0)) ** 2).sum(axis=1).mean()))


def _pair_deltas(x, rows, box):
    d = x[None, :, :] - x[rows, None, :]
    if box is not None:
        lo, hi, wrap = box
        L = np.asarray(hi) - np.asarray(lo)
        for ax in range(3):
            if wrap[ax]:
                d[..., ax] -= L[ax] * np.round(d[..., ax] / L[ax])
    return d


def nearest_distances(positions, box=None, mask=None, chunk=512) -> np.ndarray:
    """Distance [m] from each agent to its nearest other agent (minimum image for a periodic
    ``box`` = (lower, upper, wrap flags), e.g. ``flock.box``); ``mask(i_rows, j)`` (bool (r, n))
    restricts the pairs. O(n^2) in chunks."""
    x = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    n = len(x)
    out = np.full(n, np.inf)
    for start in range(0, n, chunk):
        rows = np.arange(start, min(start + chunk, n))
        dist = np.linalg.norm(_pair_deltas(x, rows, box), axis=2)
        dist[np.arange(len(rows)), rows] = np.inf
        if mask is not None:
            dist = np.where(mask(rows), dist, np.inf)
        out[rows] = dist.min(axis=1)
    return out


def same_group_fraction(positions, groups, k=5, box=None) -> float:
    """Mean share of each agent's k nearest neighbours that belong to its own group (species):
    segregation index, compared with the share expected for a random mixture."""
    x = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    g = np.asarray(groups)
    n = len(x)
    total = 0.0
    for start in range(0, n, 512):
        rows = np.arange(start, min(start + 512, n))
        dist = np.linalg.norm(_pair_deltas(x, rows, box), axis=2)
        dist[np.arange(len(rows)), rows] = np.inf
        nn = np.argsort(dist, axis=1)[:, :k]
        total += (g[nn] == g[rows, None]).sum()
    return float(total / (n * k))


def params_dict(params) -> dict:
    """A BoidParams / WalkerParams as a plain dict (for logs and USD metadata)."""
    return asdict(params)
