"""Flocking and crowds: boids that fly or swim (:class:`Flock`) and agents that walk on terrain
(:class:`Crowd`), stepped by the Warp kernels in ``warpsim.kernels.agents``.

Modules: ``flyers`` (Flock), ``walkers`` (Crowd), ``world`` (Terrain, Obstacles, FoodSources),
``params`` (AgentState, BoidParams, WalkerParams), ``swarm`` (the arrays, neighbour grid and rules
launch both share), ``metrics`` (polarization, ...), ``reference`` (the NumPy boids oracle).

Example::

    import numpy as np, warpsim as ws

    rng = np.random.default_rng(0)
    flock = ws.Flock(rng.uniform(0, 20, (500, 3)), rng.normal(0, 1, (500, 3)),
                     params=ws.BoidParams(max_speed=5.0), bounds=((0, 0, 0), (20, 20, 20)), wrap=True)
    for _ in range(100):
        flock.step(1 / 30)
    print(ws.agents.polarization(flock.velocities.numpy()))

Each ``step(dt)`` rebuilds the neighbour grid (``wp.HashGrid``) on the host, outside any graph
capture, then launches the rule and integration kernels; it allocates nothing.

Agent states (:class:`AgentState`): FLYING, RESTING, WALKING, CLIMBING, FALLEN, and LANDING (a
tired flyer on its way down to rest).
"""

from .flyers import Flock
from .metrics import nearest_distances, polarization, radius_of_gyration, same_group_fraction
from .params import AgentState, BoidParams, WalkerParams, params_dict
from .walkers import Crowd
from .world import FoodSources, Obstacles, Terrain

__all__ = [
    "AgentState", "BoidParams", "Crowd", "Flock", "FoodSources", "Obstacles", "Terrain", "WalkerParams",
    "nearest_distances", "params_dict", "polarization", "radius_of_gyration", "same_group_fraction",
]
