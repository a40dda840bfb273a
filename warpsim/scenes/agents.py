"""Agent scenes: ``flock`` (two species of birds, food and resting), ``school`` (fish of three
species in a water volume), ``zombies`` (a horde that must get over a wall) and ``crowd``
(people crossing a plaza to destinations).

USD layout: the agents are a ``PointInstancer`` named ``agents`` (one prototype per species or
kind, oriented along the velocity: the prototype's +Z is the heading), with the per-agent
``state`` primvar (:class:`ws.AgentState`: 0 flying, 1 resting, 2 walking,
3 climbing, 4 fallen, 5 landing) and a per-agent ``displayColor`` from that state (or the
species while flying); terrain and obstacles are static meshes (spheres as ``Sphere`` prims);
food sources are ``Points`` whose widths follow the bites left.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
import warp as wp

from ..agents import (
    AgentState,
    BoidParams,
    Crowd,
    Flock,
    FoodSources,
    Obstacles,
    Terrain,
    WalkerParams,
)
from . import Scene, register_scene

STATE_COLORS = {
    AgentState.FLYING: (0.2, 0.4, 0.9),
    AgentState.RESTING: (0.2, 0.8, 0.3),
    AgentState.WALKING: (0.7, 0.7, 0.7),
    AgentState.CLIMBING: (0.95, 0.6, 0.1),
    AgentState.FALLEN: (0.9, 0.1, 0.1),
    AgentState.LANDING: (0.6, 0.3, 0.8),
}
_PALETTE = np.array([STATE_COLORS[s] for s in sorted(STATE_COLORS)], dtype=np.float32)


def _positive(p, *keys):
    for key in keys:
        if not p[key] > 0:
            raise ValueError(f"{key}={p[key]}: it must be > 0")


AGENT_BYTES = 500.0
"""Host bytes an agent takes while building (measured on the CPU: 316 a bird of flock, 293 a fish
of school, 357 a zombie, 200,000-300,000 of them)."""
TERRAIN_NODE_BYTES = 50.0
"""Bytes a node of a height-field terrain takes while building (measured: 40, flock size=2000)."""


def _check_agents(param, value, agents, per_value=1, others=0):
    """Refuse ``agents`` agents made by ``param`` = ``value`` (``per_value`` agents each, besides
    ``others`` made by other parameters) that cannot be built in memory: one line naming the
    parameter, the estimate and the value that fits."""
    from ..core.memory import check_build_memory

    check_build_memory(param, value, agents, "agents", AGENT_BYTES, lambda k: max(1, (k - others) // per_value))


class AgentScene(Scene):
    """Base of the agent scenes: ``self.agents`` is a Flock or Crowd stepped with ``dt``
    (the ``dt`` parameter) ``substeps`` times per frame."""

    agents: Any = None
    species_colors: Any = None  # colour while flying/walking per species (None: by state only)

    def advance(self, frame_dt, substeps):
        h = frame_dt / substeps
        for _ in range(substeps):
            self.agents.step(h)

    def declare_agents(self, writer, prototypes):
        writer.add_instancer("agents", prototypes, count_changes=False,
                             primvars={"state": "int[]", "displayColor": "color3f[]"})

    def declare_world(self, writer, terrain=None, obstacles=None, terrain_size=50.0):
        if terrain is not None:
            pts, tri = terrain.mesh(size=terrain_size)
            writer.add_static_mesh("terrain", pts, np.full(len(tri), 3), tri.reshape(-1), color=(0.45, 0.4, 0.3))
        if obstacles is not None:
            for k, (c, r) in enumerate(obstacles.spheres):
                writer.add_sphere(f"obstacle_sphere{k}", tuple(c), r, color=(0.4, 0.5, 0.4))
            for k, (n, off) in enumerate(obstacles.planes):
                writer.add_plane(f"obstacle_plane{k}", tuple(n), off, size=terrain_size)
            for k, (pts, tri) in enumerate(obstacles.meshes):
                writer.add_static_mesh(f"obstacle_mesh{k}", pts, np.full(len(tri), 3), tri.reshape(-1),
                                       color=(0.5, 0.45, 0.4))

    def agent_data(self):
        a = self.agents
        state = a.state.numpy()
        kinds = a.kinds.numpy()
        color = _PALETTE[np.clip(state, 0, len(_PALETTE) - 1)].copy()
        if self.species_colors is not None:
            moving = (state == AgentState.FLYING) | (state == AgentState.WALKING)
            color[moving] = np.asarray(self.species_colors, dtype=np.float32)[kinds[moving]]
        return {"positions": a.positions.numpy(), "orientations": a.orientations().numpy(),
                "velocities": a.velocities.numpy(), "protoIndices": kinds, "state": state, "displayColor": color}

    def frame_data(self):
        return {"agents": self.agent_data()}

    # checkpoints: every per-agent array and the clocks
    _ARRAYS = ("positions", "velocities", "heading", "state", "timer", "goals")

    def checkpoint(self):
        a = self.agents
        data = {name: getattr(a, name).numpy() for name in self._ARRAYS}
        for name in ("energy", "bite_timer", "bites", "food_amounts", "_step_counter"):
            if hasattr(a, name):
                data[name] = getattr(a, name).numpy()
        data["time"] = np.float64(a.time)
        data["step_count"] = np.int64(a.step_count)
        return data

    def restore(self, data):
        a = self.agents
        for name, value in data.items():
            if name in ("time", "step_count"):
                continue
            getattr(a, name).assign(wp.array(value, dtype=getattr(a, name).dtype, device=a.device))
        a.time = float(data["time"])
        a.step_count = int(data["step_count"])


# --------------------------------------------------------------------------------------
@register_scene("flock", "two species of birds (small flockers and drafting geese) over hills with food and "
                "rests", params={
                    "birds": (300, "small birds (species 0)"),
                    "geese": (40, "geese (species 1, fly in each other's upwash)"),
                    "food": (4, "food sources on the ground"),
                    "food_bites": (150, "bites per food source"),
                    "size": (60.0, "side of the (x, z)-periodic world [m]"),
                    "height": (25.0, "ceiling of the airspace [m]"),
                    "seed": (0, "random seed of the initial flock"),
                    "dt": (1.0 / 48.0, "time step [s]"),
                }, substeps=2)
class FlockScene(AgentScene):
    """Birds wrap around in x and z, have soft walls at the ground and ceiling, steer around a
    tree crown, rest on the hills when tired (energy drains in flight; initial energies are
    random so rests are staggered) and eat at food sources; geese seek the upwash behind and
    beside each other, which saves 30 % of their drain."""

    smoke_params: ClassVar[dict] = {"birds": 20, "geese": 4, "food": 1}

    species_colors = ((0.2, 0.4, 0.9), (0.95, 0.95, 0.9))

    def build(self, p):
        _positive(p, "size", "height", "dt")
        if p["birds"] < 0 or p["geese"] < 0 or p["birds"] + p["geese"] == 0:
            raise ValueError(f"birds={p['birds']}, geese={p['geese']}: need counts >= 0 and at least one bird")
        if p["food"] < 0 or p["food_bites"] < 0:
            raise ValueError("food and food_bites must be >= 0")
        from ..core.memory import check_build_memory

        many = "birds" if p["birds"] >= p["geese"] else "geese"
        _check_agents(many, p[many], p["birds"] + p["geese"], others=p["geese" if many == "birds" else "birds"])
        # the terrain: a height field of 1 m cells over the size x size world
        check_build_memory("size", p["size"], (p["size"] + 1.0) ** 2, "terrain nodes", TERRAIN_NODE_BYTES,
                           lambda k: f"{max(1.0, k ** 0.5 - 1.0):.0f}")
        rng = np.random.default_rng(p["seed"])
        half = 0.5 * p["size"]
        self.terrain = Terrain.from_function(
            lambda x, z: 1.5 + 1.5 * np.sin(x / 7.0) * np.cos(z / 9.0), (-half, -half), (half, half), 1.0)
        ground = self.terrain.height(np.zeros((1, 3)), self.device)[0]
        self.obstacles = Obstacles(spheres=[((0.3 * half, ground + 6.0, -0.3 * half), 3.0)])
        small = BoidParams(max_speed=9.0, min_speed=5.0, max_force=12.0, perception_radius=4.0,
                           separation_radius=1.0, separation_radius_other=2.0, fov_deg=280.0, min_height=0.5,
                           drain_rate=1.0 / 40.0, land_threshold=0.15, rest_time=8.0, food_sense_radius=12.0,
                           food_eat_radius=1.0, food_energy=0.05, bite_interval=1.0, avoid_distance=3.0)
        geese = BoidParams(max_speed=8.0, min_speed=5.0, max_force=6.0, perception_radius=6.0,
                           separation_radius=0.8, separation_radius_other=2.0, fov_deg=220.0, min_height=1.0,
                           cohesion_weight=0.3, alignment_weight=1.0, draft_weight=1.5, draft_saving=0.3,
                           draft_back=1.2, draft_side=1.0, draft_width=0.5, drain_rate=1.0 / 60.0, land_threshold=0.15,
                           rest_time=10.0, avoid_distance=4.0, body_radius=0.3)
        n0, n1 = p["birds"], p["geese"]
        n = n0 + n1
        species = np.r_[np.zeros(n0, int), np.ones(n1, int)]
        x = np.stack([rng.uniform(-half, half, n), rng.uniform(6.0, 0.8 * p["height"], n),
                      rng.uniform(-half, half, n)], axis=1)
        x[n0:] = [-0.5 * half, 12.0, 0.0] + rng.normal(0.0, 3.0, (n1, 3))
        heading = rng.normal(0.0, 1.0, (n, 3)) * [1.0, 0.1, 1.0]
        heading[n0:] = [1.0, 0.0, 0.2]
        v = 6.0 * heading / np.linalg.norm(heading, axis=1, keepdims=True)
        energy = rng.uniform(0.2, 1.0, n)
        food = None
        if p["food"] > 0:
            fxz = rng.uniform(-0.8 * half, 0.8 * half, (p["food"], 2))
            fy = self.terrain.height(fxz, self.device) + 0.5
            food = FoodSources(np.stack([fxz[:, 0], fy, fxz[:, 1]], axis=1), p["food_bites"])
        self.food = food
        self.agents = Flock(x, v, species, [small, geese], bounds=((-half, -5.0, -half), (half, p["height"], half)),
                            wrap=(True, False, True), margin=4.0, terrain=self.terrain, obstacles=self.obstacles,
                            food=food, energy=energy, device=self.device)

    def declare(self, writer):
        self.declare_agents(writer, [("cone", {"radius": 0.15, "height": 0.5, "axis": "Z"}),
                                     ("cone", {"radius": 0.35, "height": 1.2, "axis": "Z"})])
        self.declare_world(writer, self.terrain, self.obstacles)
        if self.food is not None:
            writer.add_points("food", radius=0.5, dynamic_widths=True, velocities=False, color=(0.9, 0.8, 0.1))

    def frame_data(self):
        data = {"agents": self.agent_data()}
        if self.food is not None:
            left = self.agents.food_amounts.numpy() / max(1, int(self.food.initial_amounts.max()))
            data["food"] = {"points": self.food.positions, "widths": 0.3 + 1.7 * left}
        return data


# --------------------------------------------------------------------------------------
@register_scene("school", "fish of three species schooling in a water volume around a rock and a reef",
                params={
                    "fish": (150, "fish per species"),
                    "size": ((30.0, 10.0, 30.0), "water volume x,y,z [m] (centred on x and z, from y = 0)"),
                    "seed": (0, "random seed"),
                    "dt": (1.0 / 48.0, "time step [s]"),
                }, substeps=2)
class SchoolScene(AgentScene):
    """Three species with different speeds and sizes; each aligns and coheres with its own
    species only and keeps a larger distance from the others, so the schools segregate. The
    tank has soft walls; a rock (sphere) and a reef (triangle mesh) are avoided."""

    smoke_params: ClassVar[dict] = {"fish": 8}

    species_colors = ((0.95, 0.55, 0.1), (0.3, 0.6, 0.95), (0.85, 0.85, 0.2))

    def build(self, p):
        _positive(p, "fish", "dt")
        _check_agents("fish", p["fish"], 3 * p["fish"], per_value=3)  # three species of `fish` each
        size = np.asarray(p["size"], dtype=np.float64)
        if (size <= 0).any():
            raise ValueError(f"size={p['size']}: every side must be > 0 [m]")
        rng = np.random.default_rng(p["seed"])
        lo = np.array([-0.5 * size[0], 0.0, -0.5 * size[2]])
        hi = lo + size
        reef = _box_mesh((0.25 * size[0], 0.0, 0.0), (0.12 * size[0], 0.25 * size[1], 0.3 * size[2]))
        self.obstacles = Obstacles(spheres=[((-0.2 * size[0], 0.0, 0.15 * size[2]), 0.3 * size[1])], meshes=[reef])
        common = {"fov_deg": 300.0, "separation_radius_other": 2.0, "min_distance": 0.25, "avoid_distance": 2.5,
                  "body_radius": 0.2, "boundary_weight": 2.0}
        params = [
            BoidParams(max_speed=4.0, min_speed=2.0, max_force=6.0, perception_radius=3.0, separation_radius=0.6,
                       **common),
            BoidParams(max_speed=3.0, min_speed=1.5, max_force=4.0, perception_radius=3.5, separation_radius=0.9,
                       **common),
            BoidParams(max_speed=5.0, min_speed=2.5, max_force=8.0, perception_radius=2.5, separation_radius=0.5,
                       **common),
        ]
        n = 3 * p["fish"]
        species = np.repeat(np.arange(3), p["fish"])
        x = lo + 2.0 + rng.uniform(0.0, 1.0, (n, 3)) * (size - 4.0)
        v = rng.normal(0.0, 1.0, (n, 3)) * [1.0, 0.2, 1.0]
        v = 2.0 * v / np.linalg.norm(v, axis=1, keepdims=True)
        self.agents = Flock(x, v, species, params, bounds=(lo, hi), margin=2.0, obstacles=self.obstacles,
                            device=self.device)
        self.box = (lo, hi)

    def declare(self, writer):
        self.declare_agents(writer, [("cone", {"radius": 0.12, "height": 0.45, "axis": "Z"}),
                                     ("cone", {"radius": 0.2, "height": 0.7, "axis": "Z"}),
                                     ("cone", {"radius": 0.08, "height": 0.35, "axis": "Z"})])
        self.declare_world(writer, Terrain.flat(0.0), self.obstacles, terrain_size=float(self.box[1][0] * 2))


def _box_mesh(center, half):
    """Closed triangle mesh of the box center +- half (outward normals)."""
    c = np.asarray(center, dtype=np.float64)
    h = np.asarray(half, dtype=np.float64)
    corners = np.array([[(1 if (i >> k) & 1 else -1) for k in range(3)] for i in range(8)], dtype=np.float64)
    quads = [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]]
    tri = np.array([[q[0], q[1], q[2]] for q in quads] + [[q[0], q[2], q[3]] for q in quads])
    return c + h * corners, tri


# --------------------------------------------------------------------------------------
def wall_terrain(length=40.0, width=20.0, wall_x=20.0, wall_height=3.0, wall_thickness=1.0, spacing=0.25):
    """Flat ground with a wall across z at x = wall_x: steep faces (one grid cell wide) and a
    flat top; a height field over x in [0, length], z in [-width / 2, width / 2]."""
    top = 0.5 * wall_thickness

    def h(x, z):
        d = np.abs(x - wall_x)
        return wall_height * np.clip((top + spacing - d) / spacing, 0.0, 1.0) + 0.0 * z

    return Terrain.from_function(h, (0.0, -0.5 * width), (length, 0.5 * width), spacing)


@register_scene("zombies", "a horde that walks to a wall, climbs it badly, falls, lies a while and gets up to "
                "reach the other side", params={
                    "zombies": (150, "horde size"),
                    "wall_height": (3.0, "wall height [m]"),
                    "climb_speed": (0.3, "climbing speed along the wall [m/s]"),
                    "fall_rate": (0.04, "falls per second of climbing [1/s]"),
                    "recovery_time": (60.0, "time a fallen zombie lies before getting up [s]"),
                    "walk_speed": (1.0, "walking speed [m/s]"),
                    "seed": (0, "random seed (start positions and falls)"),
                    "dt": (1.0 / 24.0, "time step [s]"),
                }, substeps=1, fps=24)
class ZombiesScene(AgentScene):
    """Zombies start on the near side (x < 12 m) of a 40 m x 20 m yard split by a wall at
    x = 20 m and want to reach x = 36 m. Ground flatter than 30 % is walked; the wall faces are
    climbed at ``climb_speed`` and a climbing zombie falls ``fall_rate`` times per second on
    average, drops under gravity, lies ``recovery_time`` and tries again. About 2,000 frames
    (80 s) show most of the horde over the wall with the default minute of recovery.
    ``over_wall_fraction()`` reports the share on the far side."""

    smoke_params: ClassVar[dict] = {"zombies": 8}

    def build(self, p):
        _positive(p, "zombies", "wall_height", "climb_speed", "walk_speed", "dt")
        _check_agents("zombies", p["zombies"], p["zombies"])
        if p["fall_rate"] < 0 or p["recovery_time"] < 0:
            raise ValueError("fall_rate and recovery_time must be >= 0")
        rng = np.random.default_rng(p["seed"])
        self.wall_x = 20.0
        self.terrain = wall_terrain(wall_x=self.wall_x, wall_height=p["wall_height"])
        n = p["zombies"]
        x = np.stack([rng.uniform(1.0, 12.0, n), np.zeros(n), rng.uniform(-9.0, 9.0, n)], axis=1)
        goals = np.stack([np.full(n, 36.0), np.zeros(n), x[:, 2]], axis=1)
        params = WalkerParams(max_speed=p["walk_speed"], max_force=2.0, perception_radius=1.5, personal_radius=0.8,
                              group_radius=0.8, personal_distance=0.45, min_distance=0.45, alignment_weight=0.0,
                              cohesion_weight=0.0, separation_weight=1.0, climb_speed=p["climb_speed"],
                              fall_rate=p["fall_rate"], recovery_time=p["recovery_time"], fall_speed=1.0,
                              arrive_radius=1.0)
        self.agents = Crowd(x, goals, groups=np.zeros(n, dtype=int), params=params, terrain=self.terrain,
                            bounds=((0.0, -10.0, -10.0), (40.0, 20.0, 10.0)), seed=p["seed"], device=self.device)

    def over_wall_fraction(self) -> float:
        """Share of the horde beyond the wall (x > wall_x + 1 m)."""
        return float((self.agents.positions.numpy()[:, 0] > self.wall_x + 1.0).mean())

    def declare(self, writer):
        self.declare_agents(writer, [("capsule", {"radius": 0.2, "height": 1.3, "axis": "Y"})])
        self.declare_world(writer, self.terrain)
        writer.add_attribute("agents", "warpsim:overWallFraction", "double")

    def frame_data(self):
        data = self.agent_data()
        data["positions"] = data["positions"] + [0.0, 0.85, 0.0]  # capsule centre above the feet
        data["warpsim:overWallFraction"] = self.over_wall_fraction()
        return {"agents": data}


# --------------------------------------------------------------------------------------
@register_scene("crowd", "people in small groups crossing a plaza with planters to destinations on the other "
                "side, keeping away from strangers", params={
                    "people": (200, "number of people"),
                    "plaza": (30.0, "side of the square plaza [m]"),
                    "seed": (0, "random seed (groups, starts and destinations)"),
                    "dt": (1.0 / 24.0, "time step [s]"),
                }, substeps=1, fps=24)
class CrowdScene(AgentScene):
    """People walk in groups of one to four from one edge of the plaza to a destination near
    the opposite edge, steer around four planters (spheres), keep ``personal_radius`` from
    strangers and stay close to their group. ``arrived_fraction()`` reports how many are
    within 1 m of their destination."""

    smoke_params: ClassVar[dict] = {"people": 10, "plaza": 12.0}

    species_colors = ((0.7, 0.7, 0.7),)

    def build(self, p):
        _positive(p, "people", "plaza", "dt")
        _check_agents("people", p["people"], p["people"])
        rng = np.random.default_rng(p["seed"])
        half = 0.5 * p["plaza"]
        n = p["people"]
        sizes = []
        total = 0
        while total < n:  # a running total: summing the list each time took minutes for 300,000 people
            sizes.append(int(rng.integers(1, 5)))
            total += sizes[-1]
        sizes[-1] -= total - n
        groups = np.repeat(np.arange(len(sizes)), sizes)
        side = rng.integers(0, 4, len(sizes))[groups]  # start edge per group
        along = rng.uniform(-0.8 * half, 0.8 * half, len(sizes))[groups] + rng.normal(0.0, 0.5, n)
        dest_along = rng.uniform(-0.8 * half, 0.8 * half, len(sizes))[groups] + rng.normal(0.0, 0.5, n)
        depth = rng.uniform(0.0, 0.15 * half, len(sizes))[groups] + rng.uniform(0.0, 1.0, n)
        start = np.zeros((n, 3))
        goal = np.zeros((n, 3))
        edge = half - 1.0 - depth
        dirs = np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])[side]
        perp = np.stack([-dirs[:, 1], dirs[:, 0]], axis=1)
        start[:, [0, 2]] = -dirs * edge[:, None] + perp * along[:, None]
        goal[:, [0, 2]] = dirs * (half - 2.0) + perp * dest_along[:, None]
        planters = [((sx * 0.35 * p["plaza"] * 0.5, 0.0, sz * 0.35 * p["plaza"] * 0.5), 1.2)
                    for sx in (-1, 1) for sz in (-1, 1)]
        self.obstacles = Obstacles(spheres=planters)
        self.terrain = Terrain.flat(0.0)
        params = WalkerParams(max_speed=1.3, max_force=3.0, perception_radius=2.0, personal_radius=1.2,
                              group_radius=0.6, personal_distance=0.6, min_distance=0.45, separation_weight=0.6,
                              alignment_weight=0.2, cohesion_weight=0.2, goal_weight=1.5, avoid_distance=1.0, body_radius=0.3, arrive_radius=0.6,
                              max_slope=0.3)
        self.agents = Crowd(start, goal, groups=groups, params=params, terrain=self.terrain, obstacles=self.obstacles,
                            bounds=((-half, -1.0, -half), (half, 5.0, half)), seed=p["seed"], device=self.device)
        self.plaza = p["plaza"]

    def arrived_fraction(self, within=1.0) -> float:
        """Share of people within ``within`` [m] of their destination."""
        return float((self.agents.distance_to_goals() < within).mean())

    def declare(self, writer):
        self.declare_agents(writer, [("capsule", {"radius": 0.22, "height": 1.3, "axis": "Y"})])
        self.declare_world(writer, self.terrain, self.obstacles, terrain_size=self.plaza)
        writer.add_points("destinations", radius=0.1, velocities=False, color=(0.9, 0.9, 0.2))

    def frame_data(self):
        data = self.agent_data()
        data["positions"] = data["positions"] + [0.0, 0.87, 0.0]
        return {"agents": data, "destinations": {"points": self.agents.goals.numpy()}}
