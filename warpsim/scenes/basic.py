"""The foundation's scenes: ``bounce`` (the seed's ball), ``pendulum`` and ``springs``."""
from __future__ import annotations

import numpy as np

import warpsim as ws

from . import Scene, SimulatorScene, register_scene
from .live import set_contact, set_gravity, set_springs

INTEGRATOR = ("semi_implicit_euler", "time integrator", tuple(sorted(ws.INTEGRATORS)))


@register_scene("bounce", "the seed's ball: 1 kg dropped at rest from 4 cm onto a floor, dt = 0.04 s", params={
    "height": (0.04, "release height [m]"),
    "velocity": ((0.0, 0.0, 0.0), "initial velocity [m/s]"),
    "mass": (1.0, "ball mass [kg]"),
    "gravity": (9.81, "gravitational acceleration [m/s^2] (downward)"),
    "restitution": (0.5, "floor restitution in [0, 1]"),
    "friction": (0.0, "floor Coulomb friction coefficient"),
    "collision": ("reflect", "floor contact: reflect (at the time of impact: never gains energy), seed (the "
                  "lecture's mirror h' = e h, v' = -e v: gains energy at large steps), project",
                  ("reflect", "seed", "project")),
    "dt": (0.04, "time step [s]"),
    "integrator": INTEGRATOR,
    "display_radius": (0.004, "drawn radius [m]; the ball collides as a point, as in the seed"),
})
class Bounce(SimulatorScene):
    """A point mass falling onto the plane y = 0; frame 1 of the defaults has v_y = -0.3924 m/s
    and y = 0.024304 m, and frame 2 reaches the floor. ``collision="seed"`` reproduces the
    lecture's frame table (frame 2: y = e h with h = 0.007088 m below the floor, v_y = 0.3924 m/s);
    the default ``"reflect"`` ends that step on the floor and never rebounds above the release
    height (``kernels/collide.py``)."""

    def build(self, p):
        if p["mass"] <= 0:
            raise ValueError(f"mass={p['mass']}: the ball needs a mass > 0 [kg]")
        if p["height"] < 0:
            raise ValueError(f"height={p['height']:g}: the ball would start below the floor (y = 0); give height >= 0 [m]")
        if p["dt"] <= 0:
            raise ValueError(f"dt={p['dt']:g}: the time step must be > 0 [s]")
        b = ws.ModelBuilder()
        b.add_particle((0.0, p["height"], 0.0), vel=p["velocity"], mass=p["mass"])
        self.sim = ws.Simulator(b.finalize(self.device), integrator=p["integrator"],
                                forces=[ws.Gravity((0.0, -p["gravity"], 0.0))],
                                colliders=[ws.Plane((0.0, 1.0, 0.0), 0.0, restitution=p["restitution"],
                                                    friction=p["friction"], mode=p["collision"])])

    live_params = ("restitution", "friction", "gravity")

    def apply_param(self, key, value):
        if key == "gravity":
            set_gravity(self.sim.forces, value)
        else:
            set_contact(self.sim.colliders, **{key: value})

    def declare(self, writer):
        self.declare_state(writer, "ball", radius=self.params["display_radius"], color=(0.9, 0.3, 0.1))
        writer.add_plane("floor", size=max(0.2, 5 * self.params["height"]))


@register_scene("pendulum", "angle-form pendulum q'' = -(g/l) sin q; pick the integrator, energy per frame", params={
    "angle": (1.0, "release angle from the downward vertical [rad]"),
    "angular_velocity": (0.0, "initial angular velocity [rad/s]"),
    "length": (1.0, "rod length [m]"),
    "mass": (1.0, "bob mass [kg] (energies)"),
    "gravity": (9.81, "gravitational acceleration [m/s^2]"),
    "dt": (1.0 / 120.0, "time step [s]"),
    "integrator": ("rk4", "time integrator", INTEGRATOR[2]),
    "bob_radius": (0.05, "drawn bob radius [m]"),
}, substeps=2)
class PendulumScene(Scene):
    """The bob is a Points prim (pivot at (0, length, 0)) with ``warpsim:angle`` [rad],
    ``warpsim:kineticEnergy``, ``warpsim:potentialEnergy`` and ``warpsim:totalEnergy`` [J] sampled
    every frame; the rod is a linear BasisCurves."""

    ENERGY = ("warpsim:kineticEnergy", "warpsim:potentialEnergy", "warpsim:totalEnergy")

    def build(self, p):
        self.pendulum = ws.Pendulum(p["angle"], p["angular_velocity"], length=p["length"], mass=p["mass"],
                                    gravity=p["gravity"], integrator=p["integrator"], device=self.device)
        self.pivot = np.array([0.0, p["length"], 0.0])

    def declare(self, writer):
        writer.add_points("bob", radius=self.params["bob_radius"], color=(0.9, 0.7, 0.1))
        writer.add_attribute("bob", "warpsim:angle", "double", unit="rad")
        for name in self.ENERGY:
            writer.add_attribute("bob", name, "double")
        writer.add_curves("rod", curve_vertex_counts=[2], width=0.01, color=(0.3, 0.3, 0.3))
        writer.add_sphere("pivot", tuple(self.pivot), 0.02)

    def stability(self):
        return self.pendulum.stability()

    def auto_steps(self, frame_dt, minimum):
        return self.pendulum.stability().substeps_for(frame_dt, minimum=int(minimum))

    def advance(self, frame_dt, substeps):
        substeps = self.frame_steps(frame_dt, substeps)  # automatic timing: inside the pendulum's limit
        for _ in range(substeps):
            self.pendulum.step(frame_dt / substeps)
        q = self.pendulum.angle.numpy()
        w = self.pendulum.angular_velocity.numpy()
        if not (np.isfinite(q).all() and np.isfinite(w).all()):
            raise ws.SimulationError(f"pendulum angle became {q[0]} rad (angular velocity {w[0]} rad/s) at "
                                     f"t = {self.pendulum.time:.6g} s. Remedy: use a smaller dt or "
                                     "integrator='rk4'.", step=0, time=self.pendulum.time, particle=0)

    def frame_data(self):
        q = float(self.pendulum.angle.numpy()[0])
        w = float(self.pendulum.angular_velocity.numpy()[0])
        length = self.params["length"]
        bob = self.pivot + length * np.array([np.sin(q), -np.cos(q), 0.0])
        vel = length * w * np.array([np.cos(q), np.sin(q), 0.0])
        ke, pe = self.pendulum.energy()
        energy = dict(zip(self.ENERGY, (float(ke[0]), float(pe[0]), float(ke[0] + pe[0]))))
        return {"bob": {"points": bob[None], "velocities": vel[None], "warpsim:angle": q, **energy},
                "rod": {"points": np.stack([self.pivot, bob])}}

    def checkpoint(self):
        return self.pendulum.checkpoint()

    def restore(self, data):
        self.pendulum.restore(data)


@register_scene("springs", "masses on damped springs hanging from pinned particles: a chain or a lattice", params={
    "shape": ("chain", "chain (swinging rope) or lattice (a square sheet pinned at two corners)",
              ("chain", "lattice")),
    "count": (10, "masses in the chain, or per side of the lattice"),
    "spacing": (0.1, "rest distance between neighbours [m]"),
    "mass": (0.05, "mass of each particle [kg]"),
    "stiffness": (400.0, "spring stiffness [N/m]"),
    "damping": (0.05, "spring damping [N s/m]"),
    "gravity": (9.81, "gravitational acceleration [m/s^2]"),
    "dt": (1.0 / 480.0, "time step [s]"),
    "integrator": INTEGRATOR,
}, substeps=8)
class Springs(SimulatorScene):
    """A horizontal chain pinned at one end (or a horizontal sheet pinned at two corners) released
    under gravity; masses are Points, springs a linear BasisCurves."""

    substeps_auto = True  # stiffness and mass sliders reach past dt's limit: sub-step inside it

    def build(self, p):
        n, s = p["count"], p["spacing"]
        if n < 2:
            raise ValueError(f"count={n}: the springs scene needs count >= 2")
        if s <= 0 or p["mass"] <= 0:
            raise ValueError("spacing and mass must be > 0")
        from ..core.memory import check_build_memory

        # measured while building: 408 bytes a particle of the chain, about 2,000 of the lattice (more springs)
        if p["shape"] == "chain":
            check_build_memory("count", n, n, "particles", 500.0, lambda k: max(2, k))
        else:
            check_build_memory("count", n, n * n, "particles", 2500.0, lambda k: max(2, int(k ** 0.5)))
        b = ws.ModelBuilder()
        top = 1.0 + (n - 1) * s
        if p["shape"] == "chain":
            for i in range(n):
                b.add_particle((i * s, top, 0.0), mass=0.0 if i == 0 else p["mass"], radius=0.01)
            for i in range(n - 1):
                b.add_spring(i, i + 1, p["stiffness"], p["damping"])
        else:
            for j in range(n):
                for i in range(n):
                    pinned = j == 0 and i in (0, n - 1)
                    b.add_particle((i * s, top, j * s), mass=0.0 if pinned else p["mass"], radius=0.01)
            for j in range(n):
                for i in range(n):
                    k = j * n + i
                    if i + 1 < n:
                        b.add_spring(k, k + 1, p["stiffness"], p["damping"])
                    if j + 1 < n:
                        b.add_spring(k, k + n, p["stiffness"], p["damping"])
                    if i + 1 < n and j + 1 < n:  # shear
                        b.add_spring(k, k + n + 1, p["stiffness"], p["damping"])
                        b.add_spring(k + 1, k + n, p["stiffness"], p["damping"])
        self.model = b.finalize(self.device)
        self.sim = ws.Simulator(self.model, integrator=p["integrator"], forces=[ws.Gravity((0.0, -p["gravity"], 0.0))])

    live_params = ("stiffness", "damping", "gravity")

    def apply_param(self, key, value):
        if key == "gravity":
            set_gravity(self.sim.forces, value)
        else:
            set_springs(self.model, key, value)

    def declare(self, writer):
        self.declare_state(writer, "masses", radius=0.015, color=(0.2, 0.5, 0.9))
        writer.add_curves("springs", self.model.spring_indices.numpy(), width=0.005, color=(0.8, 0.8, 0.8))

    def frame_arrays(self):
        from ..usd.frame_arrays import Particles

        data = super().frame_arrays()
        data["springs"] = {"points": Particles("positions")}
        return data
