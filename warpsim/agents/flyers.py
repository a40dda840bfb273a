"""Flyers: :class:`Flock`, boids that fly or swim in 3-D, with species, food, resting and landing."""

from __future__ import annotations

import numpy as np
import warp as wp

from ..kernels import agents as K
from .params import AgentState, BoidParams
from ..core.simulator import check_dt
from .swarm import AgentSwarm, int_labels
from .world import FoodSources, food_struct, as_points


# --------------------------------------------------------------------------------------
# Flock
# --------------------------------------------------------------------------------------
class Flock(AgentSwarm):
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
        x = as_points(positions, "positions")
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
        sp = int_labels(species, n, "species")
        if sp.max() >= len(params):
            bad = int(np.flatnonzero(sp >= len(params))[0])
            raise ValueError(f"species[{bad}] = {sp[bad]} but only {len(params)} BoidParams were given "
                             "(one per species)")
        if terrain is None and any(p.drain_rate > 0.0 for p in params):
            raise ValueError("BoidParams.drain_rate > 0 makes agents land to rest: give terrain= (e.g. "
                             "Terrain.flat(0.0))")
        if food is not None and not isinstance(food, FoodSources):
            raise ValueError(f"food must be a warpsim.FoodSources, got {type(food).__name__}")
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
        st = int_labels(state, n, "state", default=int(AgentState.FLYING))
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
        self._food = food_struct(food, d)
        self.food_amounts = self._food.amounts
        """Bites left at each food source, shape (food count,)."""
        # bites are granted in agent order (requests sorted by source with a stable sort), not by
        # atomics racing on the amounts: the same agents eat on every run and device
        food_total = self.food_amounts.shape[0]
        self._bite_request = wp.zeros(n, dtype=int, device=d)
        self._bite_keys = wp.zeros(2 * n, dtype=int, device=d)
        self._bite_ids = wp.zeros(2 * n, dtype=int, device=d)
        self._requests = wp.zeros(food_total, dtype=int, device=d)
        self._first_request = wp.zeros(food_total, dtype=int, device=d)

    def step(self, dt: float) -> None:
        """Advance the flock by ``dt`` [s]."""
        dt = check_dt(dt)
        self.eval_rules(dt)
        wp.launch(K.integrate_flyers, self.agent_count,
                  inputs=[self.rules, self.flight, self.space, self._obstacles, self._terrain, self._food, self.kinds,
                          self.separation, self.alignment, self.cohesion, self.draft, self.benefit, self.push,
                          self.goals, dt, self.agent_world],
                  outputs=[self.positions, self.velocities, self.state, self.energy, self.timer, self.bite_timer,
                           self.bites, self.heading, self._bite_request], device=self.device)
        if self._food.count > 0:
            self._grant_bites()
        self.time += dt
        self.step_count += 1


    def _grant_bites(self) -> None:
        d, n = self.device, self.agent_count
        self._requests.zero_()
        wp.launch(K.key_bite_requests, n, inputs=[self._bite_request, self._requests.shape[0]],
                  outputs=[self._requests, self._bite_keys, self._bite_ids], device=d)
        wp.utils.radix_sort_pairs(self._bite_keys, self._bite_ids, n)
        wp.utils.array_scan(self._requests, self._first_request, inclusive=False)
        wp.launch(K.grant_bites, n,
                  inputs=[self.flight, self.kinds, self._bite_keys, self._bite_ids, self._bite_request,
                          self._first_request, self.food_amounts],
                  outputs=[self.energy, self.bite_timer, self.bites, self.state], device=d)
        wp.launch(K.consume_food, self._requests.shape[0], inputs=[self._requests], outputs=[self.food_amounts],
                  device=d)


# --------------------------------------------------------------------------------------
# Crowd
# --------------------------------------------------------------------------------------
