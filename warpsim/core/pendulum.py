"""The angle-form pendulum q'' = -(g / l) sin q, stepped by any of the five integrators."""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from . import checks
from .integrators import make_integrator
from ..kernels import forces as KF
from ..kernels import integrate as KI
from .simulator import check_dt
from .solver import SolverBase, check_change
from .system import PendulumSystem


def exact_period(amplitude: float, length: float = 1.0, gravity: float = 9.81) -> float:
    """Exact period [s] of a pendulum released at rest from ``amplitude`` [rad]:
    T = 4 sqrt(l / g) K(sin(amplitude / 2)), K the complete elliptic integral of the first kind
    (computed with the arithmetic-geometric mean)."""
    amplitude = checks.finite(amplitude, "exact_period amplitude", "rad")
    length = checks.positive(length, "exact_period length", "m")
    gravity = checks.positive(gravity, "exact_period gravity", "m/s^2")
    if not abs(amplitude) < math.pi:
        raise ValueError(f"exact_period amplitude {amplitude} must be below pi in magnitude (released at rest "
                         "upside down, a pendulum never swings)")
    k = math.sin(abs(amplitude) / 2.0)
    a, b = 1.0, math.sqrt(1.0 - k * k)
    for _ in range(40):
        a, b = 0.5 * (a + b), math.sqrt(a * b)
    return 4.0 * math.sqrt(length / gravity) * math.pi / (2.0 * a)


class Pendulum(SolverBase):
    """A batch of independent pendulums (one per entry of ``angle``); a
    ``warpsim.core.solver.Solver`` whose ``state`` is the pendulum itself.

    Args:
        angle: initial angle(s) from the downward vertical [rad], shape () or (N,).
        angular_velocity: initial angular velocity [rad/s], broadcast to (N,).
        length: rod length(s) [m]; mass: bob mass(es) [kg] (energy only); gravity: g [m/s^2].
        integrator: any integrator name or instance (see ws.INTEGRATORS).
    """

    def __init__(self, angle, angular_velocity=0.0, length=1.0, mass=1.0, gravity=9.81, integrator="rk4",
                 device=None):
        angle = np.atleast_1d(checks.float_array(angle, "Pendulum angle"))
        n = len(angle)
        omega = np.broadcast_to(checks.float_array(angular_velocity, "Pendulum angular_velocity"), (n,))
        length = np.broadcast_to(checks.float_array(length, "Pendulum length"), (n,))
        mass = np.broadcast_to(checks.float_array(mass, "Pendulum mass"), (n,))
        gravity = checks.number(gravity, "Pendulum gravity", "m/s^2")
        for name, values in (("angle", angle), ("angular_velocity", omega)):
            if not np.all(np.isfinite(values)):
                raise ValueError(f"pendulum {int(np.flatnonzero(~np.isfinite(values))[0])} has a non-finite {name}")
        if np.any(~(length > 0.0)):
            raise ValueError(f"pendulum {int(np.flatnonzero(~(length > 0.0))[0])} has length <= 0; lengths must be > 0 [m]")
        if np.any(~(mass > 0.0)):
            raise ValueError(f"pendulum {int(np.flatnonzero(~(mass > 0.0))[0])} has mass <= 0; masses must be > 0 [kg]")
        if not (math.isfinite(gravity) and gravity > 0.0):
            raise ValueError(f"gravity = {gravity}; it must be > 0 [m/s^2]")
        self.device = wp.get_device(device)
        self.gravity = float(gravity)
        self.system = PendulumSystem(length, self.gravity, self.device)
        self.integrator = make_integrator(integrator)
        self.integrator.prepare(self.system)
        d = self.device
        self.angle = wp.array(angle.astype(np.float32), dtype=float, device=d)
        """Angles [rad], shape (N,)."""
        self.angular_velocity = wp.array(omega.astype(np.float32), dtype=float, device=d)
        """Angular velocities [rad/s], shape (N,)."""
        self.length = wp.array(length.astype(np.float32), dtype=float, device=d)
        self.mass = wp.array(mass.astype(np.float32), dtype=float, device=d)
        self._time = wp.zeros(1, dtype=float, device=d)
        self._kinetic = wp.zeros(n, dtype=float, device=d)
        self._potential = wp.zeros(n, dtype=float, device=d)
        self.time = 0.0
        self.count = n

    def stability(self):
        """The largest stable step (``ws.StabilityLimit``) of the stiffest pendulum, linearised
        about the bottom: omega = sqrt(g / l), undamped, in this integrator's stability region."""
        from .stability import pendulum_limit

        return pendulum_limit(self.system.g_over_l.numpy(), self.integrator)

    def stable_dt(self) -> float:
        """Largest stable step [s] (2 / omega for semi-implicit Euler, 2.83 / omega for RK4, 0.0
        for explicit Euler and RK2, inf for implicit Euler; omega = sqrt(g / l))."""
        return self.stability().dt

    @property
    def state(self):
        """The pendulum itself: ``angle`` [rad] and ``angular_velocity`` [rad/s], shape (N,)."""
        return self

    def notify_changed(self, what: str) -> None:
        """Announce an outside edit (``warpsim.core.solver.CHANGES``); "parameters": g / l is taken
        again from ``length`` (edited in place) and ``gravity``."""
        if check_change(what, "Pendulum") != "parameters":
            return
        length = self.length.numpy()
        if np.any(~(length > 0.0)):
            raise ValueError(f"pendulum {int(np.flatnonzero(~(length > 0.0))[0])} has length <= 0; lengths must be "
                             "> 0 [m]")
        self.system.g_over_l.assign(self.gravity / length)

    def checkpoint(self) -> dict:
        """Everything needed to continue bit for bit (host copies): angles, angular velocities,
        the device clock and ``time``."""
        return {"angle": self.angle.numpy(), "angular_velocity": self.angular_velocity.numpy(),
                "device_time": self._time.numpy(), "time": np.float64(self.time)}

    def restore(self, data) -> None:
        """Inverse of :meth:`checkpoint` (the same number of pendulums)."""
        for name, arr in (("angle", self.angle), ("angular_velocity", self.angular_velocity),
                          ("device_time", self._time)):
            values = np.asarray(data[name], dtype=np.float32).reshape(-1)
            if values.shape != (arr.shape[0],):
                raise ValueError(f"Pendulum restore: {name} has {values.size} values for {arr.shape[0]}; "
                                 "restore a checkpoint of the same pendulums")
            arr.assign(values)
        self.time = float(data["time"])

    def step(self, dt: float) -> None:
        dt = check_dt(dt)
        self.integrator.step(self.system, self.angle, self.angular_velocity, self._time, dt)
        wp.launch(KI.advance_time, 1, inputs=[self._time, dt], device=self.device)
        self.time += dt

    def energy(self) -> tuple[np.ndarray, np.ndarray]:
        """(kinetic, potential) energy [J] per pendulum as NumPy arrays of shape (N,);
        potential is zero at the bottom."""
        wp.launch(KF.eval_pendulum_energy, self.count,
                  inputs=[self.angle, self.angular_velocity, self.mass, self.length, self.gravity, self._kinetic,
                          self._potential], device=self.device)
        return self._kinetic.numpy().astype(np.float64), self._potential.numpy().astype(np.float64)

    def run(self, steps: int, dt: float) -> dict:
        """Take ``steps`` steps of ``dt``; returns a dict of NumPy arrays with one row per frame
        (initial state included): time (S+1,), angle, angular_velocity, kinetic, potential,
        total (S+1, N)."""
        rows = {k: [] for k in ("time", "angle", "angular_velocity", "kinetic", "potential")}

        def record():
            ke, pe = self.energy()
            rows["time"].append(self.time)
            rows["angle"].append(self.angle.numpy().astype(np.float64))
            rows["angular_velocity"].append(self.angular_velocity.numpy().astype(np.float64))
            rows["kinetic"].append(ke)
            rows["potential"].append(pe)

        record()
        for _ in range(int(steps)):
            self.step(dt)
            record()
        out = {k: np.array(v) for k, v in rows.items()}
        out["total"] = out["kinetic"] + out["potential"]
        return out
