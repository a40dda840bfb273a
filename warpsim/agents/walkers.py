"""Walkers: :class:`Crowd`, agents that walk on terrain with slope limits, fall and get back up."""

from __future__ import annotations

import numpy as np
import warp as wp

from ..kernels import agents as K
from .params import AgentState, WalkerParams
from ..core.simulator import check_dt
from .swarm import AgentSwarm, int_labels
from .world import Terrain, as_points


class Crowd(AgentSwarm):
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
        grp = int_labels(groups, n, "groups") if groups is not None else np.arange(n)
        terrain = Terrain.flat(0.0) if terrain is None else terrain
        if not isinstance(terrain, Terrain):
            raise ValueError(f"terrain must be a warpsim.Terrain, got {type(terrain).__name__}")
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
        return as_points(a, what).copy()

    def step(self, dt: float) -> None:
        """Advance the crowd by ``dt`` [s]."""
        dt = check_dt(dt)
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
