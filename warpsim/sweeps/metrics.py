"""Per-world metrics, accumulated on the device once per frame (frame 0 included), and picking.

Built-in metrics (one value per world):
  center_x, center_y, center_z   final centre of mass [m] (pinned particles weigh nothing)
  peak_center_y                  highest centre-of-mass height over the frames [m]
  peak_speed                     highest particle speed over the frames [m/s]
  kinetic_energy                 kinetic energy at the last frame [J]
  blown_up, blown_frame          1 if the world blew up (then frozen at its last good frame) or is unstable,
                                 the frame it was frozen from (else the frame it was flagged unstable)
  energy_gain                    the largest energy gain beyond the work of its driving forces, relative to
                                 its energy scale (``warpsim.core.energy.EnergyBalance.gains``): the balanced
                                 energy's gain, or the plain energy's growth where that tripped the check;
                                 0 for a world that only lost energy, inf for a non-finite energy; up to
                                 the frame the world was flagged (later frames do not change it) or frozen.
                                 The same figure as ``Simulator.energy_gain`` and the blow-up message of
                                 the world run alone, in one-process, ``--devices`` and Ray sweeps alike.
                                 Empty for solvers outside the energy balance (agents: boids, crowds;
                                 position-based and grid fluids cannot be swept)
  unstable                       1 exactly when energy_gain passed ``warpsim.core.energy.MARGIN`` (or is
                                 inf): a step above the stability limit (or a force that adds energy), even
                                 where walls stop the velocities; a world frozen by a NaN or the speed bound
                                 is blown up, and unstable too when its gain passed the margin before; empty
                                 where energy_gain is
Tracked particles (``track={"spout": 12}``, indices within one world): NAME_x, NAME_y, NAME_z (final
position [m]) and NAME_peak_y. A user metric :class:`UserMetric` sums a ``@wp.func`` of
(x [m], v [m/s], m [kg]) -> float over a world's particles: NAME (last frame) and NAME_peak.

Picking (``select``): ``rank`` orders by a metric (``-METRIC`` or ``METRIC:desc`` for largest
first), ``where`` filters with comparisons ``METRIC<VALUE`` (``<, <=, >, >=, ==, !=``), parsed
here, never evaluated as code.
"""
from __future__ import annotations

import math
import re

import numpy as np
import warp as wp

from ..kernels import worlds as KW

BUILTIN = ("center_x", "center_y", "center_z", "peak_center_y", "peak_speed", "kinetic_energy", "blown_up",
           "blown_frame", "energy_gain", "unstable")

__all__ = ["BUILTIN", "UserMetric", "WorldMetrics", "aligned", "format_cell", "parse_rank", "parse_where",
           "print_picked", "select"]


class UserMetric:
    """A per-world metric: ``func`` is a ``@wp.func`` (x: wp.vec3, v: wp.vec3, m: float) -> float
    summed over every particle of a world each frame; the table gets NAME (last frame) and
    NAME_peak (largest over the frames)."""

    def __init__(self, name, func):
        if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", str(name)):
            raise ValueError(f"metric name {name!r} must be an identifier (letters, digits, '_')")
        taken = [n for n in (str(name), f"{name}_peak") if n in BUILTIN]
        if taken:
            raise ValueError(f"metric name {name!r} would replace the built-in column {taken[0]!r}; choose another "
                             f"name (built-in: {', '.join(BUILTIN)})")
        if not isinstance(func, wp.Function):
            raise ValueError(  # noqa: TRY004 (bad input is a ValueError throughout warpsim)
f"metric {name!r} needs a @wp.func of (wp.vec3, wp.vec3, float) -> float")
        self.name, self.func = str(name), func
        self.kernel = KW.user_metric_kernel(func)


class WorldMetrics:
    """Device accumulators for one :class:`warpsim.worlds.batch.WorldBatch` (allocated once;
    ``update`` launches kernels only, so it can sit in a captured graph). ``frame_dt`` [s]: the
    frame length, for the energy balance (``energy_gain`` and ``unstable``; None: not tested, the
    cells stay empty); ``step_dt`` [s]: the step the frames take, one for all worlds or one per world
    (semi-implicit Euler's synchronised velocity; None: ``frame_dt``)."""

    def __init__(self, batch, track=None, user=(), frame_dt=None, step_dt=None):
        self.batch = batch
        n, d = batch.world_count, batch.device
        P = batch.model.world_particle_count
        self.track = dict(track or {})
        for name, index in self.track.items():
            if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", str(name)):
                raise ValueError(f"tracked particle name {name!r} must be an identifier")
            if not 0 <= int(index) < P:
                raise ValueError(f"tracked particle {name}={index} is out of range [0, {P}) for one world")
        self.user = list(user)
        columns = list(BUILTIN) + [f"{n}{s}" for n in self.track for s in ("_x", "_y", "_z", "_peak_y")]
        for metric in self.user:
            if not isinstance(metric, UserMetric):
                raise TypeError(f"metrics must be UserMetric objects, got {metric!r}; e.g. "
                                "UserMetric('height', my_func)")
            for column in (metric.name, f"{metric.name}_peak"):
                if column in columns:
                    raise ValueError(f"metric {metric.name!r} gives column {column!r}, which another metric or "
                                     "tracked particle already fills; give each metric its own name")
                columns.append(column)
        inf = float("inf")
        self.moment = wp.zeros(n, dtype=wp.vec3, device=d)
        self.mass = wp.zeros(n, dtype=float, device=d)
        self.kinetic = wp.zeros(n, dtype=float, device=d)
        self.peak_speed = wp.zeros(n, dtype=float, device=d)
        self.center = wp.zeros(n, dtype=wp.vec3, device=d)
        self.peak_center = wp.full(n, wp.vec3(-inf, -inf, -inf), dtype=wp.vec3, device=d)
        self.final_kinetic = wp.zeros(n, dtype=float, device=d)
        t = max(len(self.track), 1)
        self.tracked = wp.array(np.array(list(self.track.values()) or [0], dtype=np.int32), dtype=int, device=d)
        self.tracked_final = wp.zeros(n * t, dtype=wp.vec3, device=d)
        self.tracked_peak = wp.full(n * t, wp.vec3(-inf, -inf, -inf), dtype=wp.vec3, device=d)
        self.user_value = [wp.zeros(n, dtype=float, device=d) for _ in self.user]
        self.user_final = [wp.zeros(n, dtype=float, device=d) for _ in self.user]
        self.user_peak = [wp.full(n, -inf, dtype=float, device=d) for _ in self.user]
        self.frame_dt = None if frame_dt is None else float(frame_dt)
        self.step_dt = self.frame_dt if step_dt is None else np.asarray(step_dt, dtype=np.float64)
        # agents (boids, crowds) propel themselves: no mechanical energy balance for them
        mechanical = hasattr(batch.sim, "forces") and hasattr(batch.sim, "integrator")
        self.energy = self._energy_balance() if frame_dt is not None and mechanical else None
        self._energy_started = False

    def update(self):
        """Fold the current state into the metrics (call after every frame, and for frame 0)."""
        b = self.batch
        st, m, d, n = b.sim.state, b.model, b.device, b.world_count
        self.moment.zero_()
        self.mass.zero_()
        self.kinetic.zero_()
        wp.launch(KW.accumulate_world_sums, m.particle_count,
                  inputs=[st.positions, st.velocities, m.particle_mass, m.particle_world, b.world_bad, self.moment,
                          self.mass, self.kinetic, self.peak_speed], device=d)
        wp.launch(KW.finish_world_frame, n, inputs=[b.world_bad, self.moment, self.mass, self.kinetic, self.center,
                                                    self.peak_center, self.final_kinetic], device=d)
        if self.track:
            wp.launch(KW.track_particles, (n, len(self.track)),
                      inputs=[st.positions, self.tracked, m.world_particle_count, b.world_bad, self.tracked_final,
                              self.tracked_peak], device=d)
        for metric, value, final, peak in zip(self.user, self.user_value, self.user_final, self.user_peak):
            value.zero_()
            wp.launch(metric.kernel, m.particle_count,
                      inputs=[st.positions, st.velocities, m.particle_mass, m.particle_world, b.world_bad, value],
                      device=d)
            wp.launch(KW.keep_metric, n, inputs=[b.world_bad, value, final, peak], device=d)
        if self.energy is not None:
            clock = getattr(b.sim, "_time", None)
            if not self._energy_started:
                self.energy.start(st, self.step_dt, time=clock)
                self.energy.set_limits(self.step_dt, [lim.dt for lim in b.world_limits()])
                self._energy_started = True
            else:
                self.energy.update(st, self.step_dt, self.frame_dt, time=clock, world_bad=b.world_bad)

    def _energy_balance(self):
        """The batch's per-world energy balance (its springs from the stand-in on the shared path)."""
        from ..core.energy import EnergyBalance, gravity_of
        from ..core.stability import synchronised_energy

        b = self.batch
        if b.stepper is not None:  # the shared step keeps gravity itself
            gravity = np.asarray(b.stepper.world_gravity.numpy(), dtype=np.float64)
        else:
            gravity = gravity_of(b.sim.forces, b.world_count)
        shared = None if b.stepper is None else b.stepper.springs  # read in place: no tiled copy of every world's
        return EnergyBalance(b.model, b.sim.forces, b.sim.colliders, gravity,  # springs (8 GB at 10^5 teapots)
                             synchronise=synchronised_energy(b.sim.integrator),
                             springs=b.model if shared is not None else b._springs_model(), shared=shared,
                             per_world=True)

    def names(self):
        out = list(BUILTIN)
        for name in self.track:
            out += [f"{name}_x", f"{name}_y", f"{name}_z", f"{name}_peak_y"]
        for metric in self.user:
            out += [metric.name, f"{metric.name}_peak"]
        return out

    def rows(self):
        """One dict of metric values per world (reads back from the device)."""
        b = self.batch
        n = b.world_count
        center = self.center.numpy()
        peak = self.peak_center.numpy()
        speed = self.peak_speed.numpy()
        ke = self.final_kinetic.numpy()
        bad = b.world_bad.numpy()
        blown = b.world_blown_frame.numpy()
        judged = self.energy is not None
        unstable = self.energy.unstable_frame.numpy() if judged else np.full(n, -1)
        gains = self.energy.gains() if judged and self._energy_started else np.zeros(n)
        rows = []
        t = len(self.track)
        tf = self.tracked_final.numpy().reshape(n, -1, 3)
        tp = self.tracked_peak.numpy().reshape(n, -1, 3)
        users = [(mt.name, f.numpy(), p.numpy()) for mt, f, p in zip(self.user, self.user_final, self.user_peak)]
        for w in range(n):
            row = {"center_x": float(center[w, 0]), "center_y": float(center[w, 1]), "center_z": float(center[w, 2]),
                   "peak_center_y": float(peak[w, 1]), "peak_speed": float(speed[w]),
                   "kinetic_energy": float(ke[w]), "blown_up": int(bad[w] or unstable[w] >= 0),
                   "blown_frame": int(blown[w] if blown[w] >= 0 else unstable[w]),
                   "energy_gain": float(gains[w]) if judged else None,  # None: an empty cell
                   "unstable": int(unstable[w] >= 0) if judged else None}
            for k, name in enumerate(self.track):
                if k < t:
                    row.update({f"{name}_x": float(tf[w, k, 0]), f"{name}_y": float(tf[w, k, 1]),
                                f"{name}_z": float(tf[w, k, 2]), f"{name}_peak_y": float(tp[w, k, 1])})
            for name, final, pk in users:
                row[name] = float(final[w])
                row[f"{name}_peak"] = float(pk[w])
            rows.append(row)
        return rows


_COMPARE = re.compile(r"^\s*([A-Za-z_][A-Za-z0-9_]*)\s*(<=|>=|==|!=|<|>)\s*(\S+)\s*$")
_OPS = {"<": np.less, "<=": np.less_equal, ">": np.greater, ">=": np.greater_equal, "==": np.equal,
        "!=": np.not_equal}


def parse_where(text, names):
    """(metric, operator, value) from ``METRIC<VALUE``; ValueError naming the problem."""
    from ..core.names import close_matches

    match = _COMPARE.match(str(text))
    if not match:
        raise ValueError(f"--where {text!r} is malformed; write METRIC<VALUE (operators < <= > >= == !=), "
                         "e.g. --where peak_speed<3")
    name, op, value = match.groups()
    if name not in names:
        raise ValueError(f"--where {text!r}: unknown metric {name!r}.{close_matches(name, names)} "
                         f"Metrics: {', '.join(names)}")
    try:
        number = float(value)
    except ValueError:
        raise ValueError(f"--where {text!r}: {value!r} is not a number") from None
    if math.isnan(number):
        raise ValueError(f"--where {text!r}: compare with a number, not nan")
    return name, op, number


def parse_rank(text, names):
    """(metric, descending) from ``METRIC``, ``-METRIC`` or ``METRIC:desc`` / ``METRIC:asc``."""
    from ..core.names import close_matches

    text = str(text).strip()
    descending = False
    if text.startswith("-"):
        text, descending = text[1:], True
    if ":" in text:
        text, order = text.split(":", 1)
        if order not in ("asc", "desc"):
            raise ValueError(f"--rank {text}:{order}: the order must be asc or desc")
        descending = order == "desc"
    if text not in names:
        raise ValueError(f"--rank {text!r}: unknown metric.{close_matches(text, names)} Metrics: {', '.join(names)}")
    return text, descending


def select(rows, *, rank=None, top=None, where=()):
    """Rows passing every ``where`` (parsed triples), ordered by ``rank`` ((metric, descending) or
    None: world order), at most ``top``. Worlds that blew up sort last."""
    keep = []
    for row in rows:
        ok = True
        for name, op, value in where:
            v = row.get(name)
            if v is None or v == "" or not bool(_OPS[op](float(v), value)):  # an empty cell passes no test
                ok = False
                break
        if ok:
            keep.append(row)
    if rank is not None:
        name, descending = rank

        def key(row):
            v = row.get(name)
            v = float("nan") if v is None or v == "" else float(v)  # empty cells sort last
            bad = bool(row.get("blown_up")) or not math.isfinite(v)
            return (bad, -v if descending and not bad else v if not bad else 0.0, row["world"])

        keep.sort(key=key)
    if top is not None:
        keep = keep[: int(top)]
    return keep


def format_cell(value) -> str:
    """A table value as the picked-worlds listing prints it: floats to 6 significant digits,
    vectors as comma-separated numbers, None (a column a solver does not have) as an empty cell."""
    if value is None:
        return ""
    if isinstance(value, float):
        return f"{value:.6g}"
    if isinstance(value, (tuple, list)):
        return ",".join(f"{v:g}" for v in value)
    return str(value)


def print_picked(picked, total, params, *, rank=None, where=(), extra=(), out):
    """Print the picked worlds (``warpsim sweep`` and ``warpsim query`` alike): ``picked N of TOTAL
    worlds:``, a header, then one line per row of ``picked`` with its world, the parameters
    ``params`` and the columns it was picked by (``rank``, ``where`` as :func:`select` takes them,
    then ``extra``, e.g. the region answers), each once."""
    shown = list(params) + [m for m in ([rank[0]] if rank else []) + [w[0] for w in where] + list(extra)
                            if m not in params]
    shown = list(dict.fromkeys(shown))
    print(f"picked {len(picked)} of {total} worlds:", file=out)
    for line in aligned([["world", *shown]] + [[str(r["world"]), *(format_cell(r.get(k, "")) for k in shown)]
                                               for r in picked]):
        print("  " + line, file=out)


def aligned(rows) -> list:
    """``rows`` (lists of cell texts, the header first) as lines of columns two spaces apart, each
    column as wide as its widest cell: numbers right-aligned (their digits line up), other text
    left-aligned; no trailing spaces."""
    widths = [max(len(row[k]) for row in rows if k < len(row)) for k in range(max(map(len, rows), default=0))]

    def number(text):
        try:
            float(text.split(",")[0])
        except ValueError:
            return False
        return True

    numeric = [all(number(row[k]) for row in rows[1:] if k < len(row) and row[k]) for k in range(len(widths))]
    return ["  ".join(cell.rjust(widths[k]) if numeric[k] else cell.ljust(widths[k]) for k, cell in enumerate(row))
            .rstrip() for row in rows]
