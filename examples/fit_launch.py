"""Fit a launch velocity by differentiating the simulation: the lecture's ball lands on a target
after one bounce.

The ball of the lecture (1 kg, starts at (0, 0.04, 0) m, gravity -9.81 m/s^2, a floor at y = 0
with restitution 0.5, semi-implicit Euler at dt = 0.01 s) is launched with velocity v0. A
differentiable ``ws.Simulator`` records the flight on a ``wp.Tape``. The landing point is where
the path crosses the floor the second time, interpolated inside the step of that contact
(between the state before the step and the integrated, not yet reflected, position), so it
moves smoothly with v0 as long as the first bounce stays in the same step. The loss is
|landing - target|^2 and its gradient with respect to the horizontal launch velocity
(``rollout.states[0].velocities.grad``, from seeding the tape with dL/d(those two positions))
drives SciPy's L-BFGS; the vertical launch speed is given (``--vy``). The first contact is
differentiated through the reflection itself (x' = x + (1 + e) h n, v_n' = -e v_n). The script
prints the iterations, the velocity found, the miss distance [mm] and the landing time.

Why the vertical speed (or the landing time) is not fitted too: the lecture's reflection
reverses the velocity of the end of the step, which gravity has already sped up for the part of
the step after the impact, so a bounce leaves up to (1 + e) g dt too fast. Within the set of launches whose first
bounce falls in one step the landing time then *decreases* as the impact comes later, and jumps
up by about 3 dt when the bounce moves to the next step: a sawtooth whose exact gradient points
against the trend, so L-BFGS drives the vertical speed to whatever bound it has. The landing
point is linear in the horizontal launch speed at a given vertical one: no such trap.

    python examples/fit_launch.py --target 1.5 0.0 0.4
"""

import argparse

import numpy as np
import warp as wp
from scipy.optimize import minimize

import warpsim as ws


class Example:
    def __init__(self, target=(1.5, 0.0, 0.4), duration=2.0, dt=0.01, restitution=0.5, device=None):
        builder = ws.ModelBuilder()
        builder.add_particle((0.0, 0.04, 0.0), mass=1.0)
        self.sim = ws.Simulator(builder.finalize(device), "semi_implicit_euler", [ws.Gravity((0.0, -9.81, 0.0))],
                                [ws.Plane((0.0, 1.0, 0.0), 0.0, restitution=restitution)], differentiable=True)
        self.steps = round(duration / dt)
        self.dt = dt
        self.target = np.asarray(target, dtype=np.float64)
        self.rollout = self.sim.rollout
        self.rollout.reserve(self.steps)
        self.evaluations = 0

    def flight(self, v0):
        """Simulate ``duration`` from launch velocity v0 [m/s] (recorded on the tape); returns the
        steps whose integrated position went below the floor (the contacts)."""
        self.rollout.reset(velocities=np.reshape(v0, (1, 3)))
        for _ in range(self.steps):
            self.sim.step(self.dt)
        below = [k for k in range(1, self.steps + 1) if self.rollout.integrated(k)[0].numpy()[0, 1] < 0.0]
        return below

    def landing(self, v0):
        """(landing point [m], landing time [s], step k of the second contact, its two endpoints,
        the fraction s of step k at which the path crosses the floor) for launch v0."""
        contacts = self.flight(v0)
        if len(contacts) < 2:
            raise ValueError(f"launch velocity {v0} does not bounce twice within {self.steps * self.dt} s; "
                             "start from a steeper guess or a longer duration")
        k = contacts[1]
        a = self.rollout.states[k - 1].positions.numpy()[0].astype(np.float64)
        b = self.rollout.integrated(k)[0].numpy()[0].astype(np.float64)
        s = a[1] / (a[1] - b[1])  # fraction of the step at which y crosses 0
        return a + s * (b - a), (k - 1 + s) * self.dt, k, a, b, s

    def loss_and_gradient(self, v0):
        """|landing - target|^2 [m^2] and its gradient with respect to v0 [m^2 / (m/s)]:
        dL/d(the two endpoints of the crossing step) by hand, then the tape down to v0."""
        point, _, k, a, b, s = self.landing(v0)
        e = 2.0 * (point - self.target)
        dl_ds = e @ (b - a)
        ds_da, ds_db = -b[1] / (a[1] - b[1]) ** 2, a[1] / (a[1] - b[1]) ** 2
        g_a = (1.0 - s) * e + np.array([0.0, dl_ds * ds_da, 0.0])
        g_b = s * e + np.array([0.0, dl_ds * ds_db, 0.0])
        d_ = self.sim.device
        self.rollout.tape.backward(grads={
            self.rollout.states[k - 1].positions: wp.array([g_a], dtype=wp.vec3, device=d_),
            self.rollout.integrated(k)[0]: wp.array([g_b], dtype=wp.vec3, device=d_),
        })
        self.evaluations += 1
        loss = float(np.sum((point - self.target) ** 2))
        return loss, self.rollout.states[0].velocities.grad.numpy()[0].astype(np.float64)

    def fit(self, vy, guess=(1.0, 0.0), iterations=100):
        """The horizontal launch velocity (vx, vz) [m/s] for vertical speed vy [m/s]."""

        def loss_and_gradient(u):
            loss, grad = self.loss_and_gradient(np.array([u[0], vy, u[1]]))
            return loss, grad[[0, 2]]

        result = minimize(loss_and_gradient, np.asarray(guess, dtype=np.float64), jac=True, method="L-BFGS-B",
                          options={"maxiter": iterations, "ftol": 1e-14, "gtol": 1e-9})
        v0 = np.array([result.x[0], vy, result.x[1]])
        point, t, k, *_ = self.landing(v0)
        return result, v0, point, t, k


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--target", type=float, nargs=3, default=(1.5, 0.0, 0.4), help="landing point [m]")
    parser.add_argument("--duration", type=float, default=2.0, help="simulated time [s] (two bounces fit in)")
    parser.add_argument("--dt", type=float, default=0.01)
    parser.add_argument("--vy", type=float, default=3.0, help="vertical launch speed [m/s]")
    parser.add_argument("--guess", type=float, nargs=2, default=(1.0, 0.0), help="initial (vx, vz) [m/s]")
    parser.add_argument("--quick", action="store_true", help="a shorter flight (tests)")
    parser.add_argument("--device", default=None)
    args = parser.parse_args(argv)
    wp.config.quiet = True
    if args.quick:
        args.vy, args.duration = 2.0, 1.2
    example = Example(tuple(args.target), args.duration, args.dt, device=args.device)
    result, v0, point, t, k = example.fit(args.vy, args.guess)
    miss = float(np.linalg.norm(point - example.target))
    print(f"L-BFGS: {result.nit} iterations, {example.evaluations} simulations + gradients")
    print(f"launch velocity v0 = ({v0[0]:.5f}, {v0[1]:.5f}, {v0[2]:.5f}) m/s")
    print(f"second touch-down in step {k}, t = {t:.5f} s, at ({point[0]:.5f}, {point[1]:.5f}, {point[2]:.5f}) m: "
          f"{1000.0 * miss:.4f} mm from the target, after 1 bounce")
    return 0 if miss < 1.0e-3 else 1


if __name__ == "__main__":
    raise SystemExit(main())
