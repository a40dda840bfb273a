"""Batched worlds of a flock scene (``flock``): N flocks as one :class:`warpsim.Flock`.

A flock world is cheap to build and its interesting variations (the ``seed`` of the initial
flock and food, ``food_bites``) are not affine in the parameters, so each world's initial agents
come from the scene's own build (on the CPU, arrays only) and are uploaded together once. Worlds
never interact: the neighbour grid is keyed by world (``Flock.agent_world``: each world's agents
sit in grid cells of their own, raised by ``world_stride`` along y, and neighbours of another
world are skipped) and each world has its own block of food sources (``integrate_flyers``
searches ``agent_world * food_count ..``). Terrain, obstacles, bird parameters, counts and the
box must be equal in every world (ValueError naming the key otherwise).

The interface matches :class:`warpsim.worlds.batch.WorldBatch` (``advance``, ``end_frame``,
``world_slices``, ``world_frame_data``, ``model.particle_world``...), so ``run_batch``, the
metrics and the USD output treat a flock batch like any other (agents weigh 1 kg each in the
centre-of-mass and energy metrics).
"""
from __future__ import annotations

import copy

import numpy as np
import warp as wp

from ..agents import Flock, FoodSources
from .batch import end_frame, is_agent_scene
from .plan import StructuralError

__all__ = ["AgentWorldBatch", "is_agent_scene"]


class _Model:
    """What the metrics read: one kilogram per agent, world of each agent."""


class _State:
    def __init__(self, flock):
        self.flock = flock

    @property
    def positions(self):
        return self.flock.positions

    @property
    def velocities(self):
        return self.flock.velocities


class _Sim:
    def __init__(self, flock, model):
        self.flock, self.model = flock, model
        self.state = _State(flock)
        self.colliders = ()


def _shared(flock):
    """The parts every world of a batch must share, as comparable NumPy values."""
    space = flock.space
    out = {"agents": flock.agent_count, "rules": repr(flock.rule_values), "params": repr(flock.params),
           "space": (tuple(space.lower), tuple(space.upper), space.wrap_x, space.wrap_y, space.wrap_z, space.margin),
           "obstacles": repr(getattr(flock.obstacles, "spheres", None)),
           "food": 0 if flock.food is None else len(flock.food.positions)}
    terrain = flock.terrain
    if terrain is not None:
        out["terrain"] = np.asarray(terrain.mesh(size=8.0)[0])
    return out


class AgentWorldBatch:
    """N worlds of an agent scene driven by a :class:`warpsim.Flock` (``scene.agents``)."""

    def __init__(self, cls, world_params, device=None):
        if len(world_params) < 1:
            raise ValueError("a batch needs at least one world")
        self.cls = cls
        self.device = wp.get_device(device)
        self.params = [cls.resolve_params(p) for p in world_params]
        base = self.params[0]
        self.varied = [k for k in cls.params if any(p[k] != base[k] for p in self.params)]
        self.scene = cls(base, device="cpu")
        if not isinstance(getattr(self.scene, "agents", None), Flock):
            raise StructuralError(f"scene {cls.name!r} is not a flock; batched agent worlds support flocks")
        scenes = [self.scene]
        for p in self.params[1:]:
            try:
                scenes.append(cls(p, device="cpu"))
            except ValueError as exc:
                raise ValueError(f"a world with {', '.join(f'{k}={p[k]}' for k in self.varied)}: {exc}") from None
        ref = _shared(self.scene.agents)
        for k, s in enumerate(scenes[1:], 1):
            mine = _shared(s.agents)
            for part, value in ref.items():
                same = np.array_equal(value, mine[part]) if isinstance(value, np.ndarray) else value == mine[part]
                if not same:
                    keys = [key for key in self.varied if self.params[k][key] != base[key]]
                    raise StructuralError(f"{' or '.join(keys) or 'a parameter'} changes the flock's {part}; worlds "
                                          "of one batch share it: set it with --set")
        self.foods = [getattr(s, "food", None) for s in scenes]
        self.flock = self._concatenate([s.agents for s in scenes])
        n, a = self.world_count, self.scene.agents.agent_count
        d = self.device
        m = _Model()
        m.world_count, m.world_particle_count, m.world_spring_count = n, a, 0
        m.particle_count, m.spring_count = n * a, 0
        m.particle_world = self.flock.agent_world
        m.particle_mass = wp.ones(n * a, dtype=float, device=d)
        m.particle_inv_mass = wp.ones(n * a, dtype=float, device=d)  # freezing writes here; agents have no mass
        self.model = m
        self.sim = _Sim(self.flock, m)
        self.world_bad = wp.zeros(n, dtype=int, device=d)
        self.world_blown_frame = wp.full(n, -1, dtype=int, device=d)
        self.frame_counter = wp.zeros(1, dtype=int, device=d)
        self.q_good = wp.clone(self.flock.positions)
        self.max_speed = 1.0e3

    @property
    def world_count(self) -> int:
        return len(self.params)

    def _concatenate(self, flocks):
        f0 = flocks[0]
        lo, hi, wrap = f0.box
        def cat(name):
            return np.concatenate([getattr(f, name).numpy() for f in flocks])

        food = None
        if f0.food is not None:
            food = FoodSources(np.concatenate([f.food.positions for f in flocks]),
                               np.concatenate([f.food.initial_amounts for f in flocks]))
        batch = Flock(cat("positions"), cat("velocities"), cat("kinds"), f0.params, bounds=(lo, hi), wrap=wrap,
                      margin=f0.space.margin, terrain=f0.terrain, obstacles=f0.obstacles, food=food,
                      energy=cat("energy"), state=cat("state"), device=self.device)
        batch.timer.assign(cat("timer"))
        batch.heading.assign(cat("heading"))
        n, a = len(flocks), f0.agent_count
        batch.agent_world = wp.array(np.repeat(np.arange(n, dtype=np.int32), a), dtype=int, device=self.device)
        extent = float(np.max(hi - lo)) if lo is not None else 1.0e3
        batch.world_stride = 4.0 * (extent + 4.0 * batch.cell_size) if n > 1 else 0.0
        batch.world_side = max(1, int(np.ceil(n ** (1.0 / 3.0) - 1e-9)))
        if f0.food is not None:
            batch._food.count = len(f0.food.positions)  # one block of sources per world
        return batch

    # ------------------------------------------------------------------ stepping (WorldBatch's interface)
    def can_capture(self) -> bool:
        return False  # the neighbour grid is rebuilt every step (a HashGrid build on the host side)

    def end_frame(self) -> None:
        end_frame(self)

    def advance(self, frame_dt, substeps) -> None:
        h = frame_dt / substeps
        for _ in range(substeps):
            self.flock.step(h)
        self.end_frame()

    def world_slices(self):
        n, a = self.world_count, self.model.world_particle_count
        self._frame = {name: getattr(self.flock, name).numpy() for name in ("state", "kinds")}
        self._frame["orientations"] = self.flock.orientations().numpy()
        self._frame["food_amounts"] = self.flock.food_amounts.numpy()
        return (self.flock.positions.numpy().reshape(n, a, 3), self.flock.velocities.numpy().reshape(n, a, 3))

    def world_frame_data(self, x, v, world):
        """The scene's frame data for ``world``, whose slices are ``x``, ``v`` (from ``world_slices``)."""
        a = self.model.world_particle_count
        w = int(world)
        s = slice(w * a, (w + 1) * a)
        view = copy.copy(self.scene.agents)
        view.positions = wp.array(np.ascontiguousarray(x), dtype=wp.vec3, device="cpu")
        view.velocities = wp.array(np.ascontiguousarray(v), dtype=wp.vec3, device="cpu")
        view.state = wp.array(self._frame["state"][s], dtype=int, device="cpu")
        view.kinds = wp.array(self._frame["kinds"][s], dtype=int, device="cpu")
        quats = wp.array(self._frame["orientations"][s], dtype=wp.quat, device="cpu")
        view.orientations = lambda: quats
        food = self.foods[w]
        if food is not None:
            f = len(food.positions)
            view.food_amounts = wp.array(self._frame["food_amounts"][w * f:(w + 1) * f], dtype=int, device="cpu")
        scene = copy.copy(self.scene)
        scene.agents = view
        if hasattr(scene, "food"):
            scene.food = food
        return scene.frame_data()
