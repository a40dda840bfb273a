"""Agent states and the rule parameters of flyers (:class:`BoidParams`) and walkers
(:class:`WalkerParams`), validated on the host and packed into the kernels' structs."""

from __future__ import annotations

import enum
import math
from dataclasses import asdict, dataclass, fields

import numpy as np
import warp as wp

from ..kernels import agents as K


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


def rule_struct(values: dict) -> K.RuleParams:
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


def params_dict(params) -> dict:
    """A BoidParams / WalkerParams as a plain dict (for logs and USD metadata)."""
    return asdict(params)
