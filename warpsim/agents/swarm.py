"""The machinery flyers and walkers share: device arrays, the neighbour grid (``wp.HashGrid``) and
the rules kernel launch (:class:`AgentSwarm`), and input checks."""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from ..core.solver import SolverBase
from ..kernels import agents as K
from ..kernels import worlds as KW
from .params import AgentState, rule_struct
from .world import Obstacles, Terrain, as_points


# --------------------------------------------------------------------------------------
# Common machinery
# --------------------------------------------------------------------------------------
class AgentSwarm(SolverBase):
    """Arrays, neighbour grid and the rules kernel shared by Flock and Crowd (each a
    ``warpsim.core.solver.Solver``: ``step(dt)``, ``frame``, ``state``, ``notify_changed``)."""

    state: wp.array
    """Each agent's AgentState as an int, shape (agent_count,) (set by Flock / Crowd)."""
    _upright: bool

    def _setup(self, positions, velocities, kinds, groups, rules: list, bounds, wrap, margin, obstacles, terrain,
               goals, device):
        self.device = wp.get_device(device)
        x = positions
        n = len(x)
        self.agent_count = n
        if velocities is None:
            velocities = np.zeros((n, 3))
        vel = as_points(velocities, "velocities")
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
            raise ValueError(f"obstacles must be a warpsim.Obstacles, got {type(obstacles).__name__}")
        if terrain is not None and not isinstance(terrain, Terrain):
            raise ValueError(f"terrain must be a warpsim.Terrain, got {type(terrain).__name__}")
        self.obstacles, self.terrain = obstacles, terrain
        if goals is None:
            goals = x
        g = as_points(goals, "goals")
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
        self.rules = wp.array([rule_struct(r) for r in rules], dtype=K.RuleParams, device=d)
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
        self.agent_world = wp.zeros(n, dtype=int, device=d)
        """World of each agent (batched worlds, ``warpsim.worlds``; 0 otherwise), shape (agent_count,)."""
        self.world_stride = 0.0
        """Grid offset [m] between worlds (0: one world; see ``eval_neighbour_rules``)."""
        self.world_side = 1
        """Worlds per side of the cube of world offsets in the grid."""
        self._grid_points = None
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
        lo = as_points(lo, "bounds lower")[0]
        hi = as_points(hi, "bounds upper")[0]
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
        points = self.positions
        if self.world_stride > 0.0:  # batched worlds: each world's agents in cells of their own
            if self._grid_points is None:
                self._grid_points = wp.zeros_like(self.positions)
            wp.launch(KW.key_world_points, self.agent_count,
                      inputs=[self.positions, self.agent_world, self.world_stride, self.world_side,
                              self._grid_points], device=self.device)
            points = self._grid_points
        self.grid.build(points, self.cell_size)
        wp.launch(K.eval_neighbour_rules, self.agent_count,
                  inputs=[self.grid.id, self.positions, self.velocities, self.kinds, self.groups, self.state,
                          self.rules, self.space, float(lookahead), self.agent_world, float(self.world_stride),
                          int(self.world_side)],
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


def int_labels(values, n, what, default=0):
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
