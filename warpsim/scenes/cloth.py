"""Cloth scenes: ``cloth`` (a sheet pinned at two corners swinging down onto a sphere) and
``drape`` (a sheet falling onto a sphere and the floor). The cloth is a UsdGeom.Mesh with fixed
topology and points / velocities per frame. ``integrator=vbd`` steps the sheet by ``ws.VBD`` with its
self contact, the sphere and the floor inside the descent (``ws.VBDContact``)."""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from ..cloth.builder import add_cloth_grid
from ..cloth.solver import ClothImplicitEuler, ClothSemiImplicitEuler, ClothSimulator
from ..bodies.colliders import Plane, Sphere
from ..bodies.vbd import VBD
from ..bodies.vbd_contact import VBDContact, cut_guess_line
from ..core import Gravity, ModelBuilder, Simulator, Wind, checks
from . import SimulatorScene, register_scene
from .live import drop_graphs, set_contact, set_springs

CLOTH_INTEGRATORS = ("implicit_euler", "semi_implicit_euler", "vbd")

COMMON = {
    "resolution": (32, "cells per side of the square sheet"),
    "size": (1.0, "side of the sheet [m]"),
    "density": (0.3, "area density [kg/m^2] (implicit_euler: below 0.001, 1/300 of the default, raise "
                     "newton_iterations: the energy balance measured its gain at 0.0001 as 0.25 with 3)", None, 1.0e-3),
    "structural": (400.0, "structural spring stiffness [N/m]"),
    "shear": (100.0, "shear spring stiffness [N/m]"),
    "bend": (20.0, "bend spring stiffness [N/m]"),
    "damping": (0.02, "spring damping [N s/m] (bend springs get a quarter)"),
    "friction": (0.4, "Coulomb friction against the sphere and the floor"),
    "thickness": (0.01, "cloth thickness offset for collisions [m]"),
    "sphere_radius": (0.3, "sphere radius [m]"),
    "integrator": ("implicit_euler", ("implicit_euler (Baraff-Witkin), semi_implicit_euler, or vbd (ws.VBD: vertex block "
                                      "descent with the sheet's self contact, the sphere and the floor inside the descent "
                                      "and a step bound that keeps every edge out of every triangle)"), CLOTH_INTEGRATORS),
    "vbd_iterations": (10, "vbd only: colour sweeps per step"),
    "vbd_contact_stiffness": (1000.0, "vbd only: k_c of the contact energy k_c/2 (thickness - d)^2 [N/m]"),
    "self_contact": (True, "vbd only: the sheet against itself (pairs sharing a particle never)"),
    "explicit_substeps": (40, "semi_implicit_euler only: steps per frame sub-step (~40 for stability)"),
    "cg_tol": (1.0e-4, "implicit_euler: CG tolerance relative to |b|"),
    "newton_iterations": (3, "implicit_euler: most Newton iterations a step, until no velocity changes by more "
                             "than newton_tol (1 = Baraff-Witkin's linearised step, which gains energy where the cloth "
                             "lands and folds: 0.18x of the scale in cloth, 2 and 3 none)"),
    "newton_tol": (1.0e-3, "implicit_euler: Newton stops when no velocity changes by more than this [m/s]"),
    "wind": (0.0, "gusting wind speed along +z [m/s]; air drag 2 x particle mass [kg/s] while it blows"),
}


class ClothScene(SimulatorScene):
    """Shared part: one grid cloth, a sphere and the floor, driven by a ClothSimulator."""

    smoke_params: ClassVar[dict] = {"resolution": 4}
    sphere_center = (0.0, 0.0, 0.0)
    substeps_auto = True  # semi_implicit_euler: sub-step inside the springs' limit

    def make_cloth(self, builder, p):
        raise NotImplementedError

    def build(self, p):
        for key in ("resolution", "explicit_substeps", "newton_iterations"):
            if p[key] < 1:
                raise ValueError(f"{key}={p[key]}: it must be >= 1")
        for key in ("size", "density", "sphere_radius"):
            if not p[key] > 0.0:
                raise ValueError(f"{key}={p[key]}: it must be > 0")
        from ..core.memory import check_build_memory

        # the sheet's particles and springs (measured: 2,003 bytes a particle while building), before building
        check_build_memory("resolution", p["resolution"], (p["resolution"] + 1) ** 2, "particles", 2500.0,
                           lambda n: max(1, int(n ** 0.5) - 1))
        b = ModelBuilder()
        self.cloth = self.make_cloth(b, p)
        model = b.finalize(self.device)
        if p["integrator"] == "vbd":
            self._build_vbd(p, model)
            return
        if p["integrator"] == "implicit_euler":
            integrator = ClothImplicitEuler(cg_tol=p["cg_tol"], newton_iterations=p["newton_iterations"],
                                            newton_tol=p["newton_tol"])
        else:
            integrator = ClothSemiImplicitEuler()
        self.sphere = Sphere(self.sphere_center, p["sphere_radius"], restitution=0.0, friction=p["friction"],
                             thickness=p["thickness"])
        self.floor = Plane((0.0, 1.0, 0.0), 0.0, restitution=0.0, friction=p["friction"], mode="project")
        mass = model.particle_mass.numpy()
        self.wind_coefficient = 2.0 * float(mass[mass > 0].mean()) if (mass > 0).any() else 0.0  # [kg/s]
        self.wind = Wind((0.0, 0.0, 1.0), speed=p["wind"], coefficient=self.wind_coefficient if p["wind"] else 0.0)
        self.sim = ClothSimulator(model, integrator, forces=[Gravity(), self.wind],
                                  colliders=[self.sphere, self.floor])
        self.steps_per_substep = 1 if p["integrator"] == "implicit_euler" else p["explicit_substeps"]

    def _build_vbd(self, p, model) -> None:
        """``integrator=vbd``: a ws.Simulator stepped by ws.VBD whose contact holds the sheet's triangles (self
        contact), the sphere and the floor (no collider after the step)."""
        if p["vbd_iterations"] < 1:
            raise ValueError(f"vbd_iterations={p['vbd_iterations']}: it must be >= 1 (colour sweeps a step)")
        self.vbd_contact = VBDContact(self.cloth.triangles, thickness=p["thickness"],
                                      stiffness=p["vbd_contact_stiffness"], friction=p["friction"],
                                      self_contact=p["self_contact"], planes=[((0.0, 1.0, 0.0), 0.0)],
                                      spheres=[(self.sphere_center, p["sphere_radius"])])
        mass = model.particle_mass.numpy()
        self.wind_coefficient = 2.0 * float(mass[mass > 0].mean()) if (mass > 0).any() else 0.0  # [kg/s]
        self.wind = Wind((0.0, 0.0, 1.0), speed=p["wind"], coefficient=self.wind_coefficient if p["wind"] else 0.0)
        self.sim = Simulator(model, integrator=VBD(int(p["vbd_iterations"]), contact=self.vbd_contact),
                             forces=[Gravity(), self.wind], colliders=[])
        self.steps_per_substep = 1

    def scene_warning(self, frame_dt, substeps):
        """``integrator=vbd``: one line when the sheet's fall (from its highest particle to the floor, sqrt(2 g
        height)) takes an initial guess longer than the bound lets a vertex move before the next contact search
        (``VBDContact`` max_displacement, the thickness; ``guess_length``): the bound cuts the guess and slows the
        fall (measured: the drape's sheet at one step of 1/60 s a frame fell at 1.20 m/s at 0.15 s, free fall
        1.47; at 4 and 9 steps a frame 1.4713 and 1.4704), naming the steps a frame that fit it."""
        contact = getattr(self, "vbd_contact", None)
        if contact is None:
            return None
        g = max(float(np.linalg.norm(f.g)) for f in self.sim.forces if isinstance(f, Gravity))  # [m/s^2]
        height = max(float(self.sim.model.particle_q.numpy()[:, 1].max()), 0.0)  # above the floor at y = 0 [m]
        return cut_guess_line(f"{self.name}: with integrator=vbd the sheet", height, (2.0 * g * height) ** 0.5, g,
                              frame_dt, self.frame_steps(frame_dt, substeps), contact.max_displacement, "the thickness")

    def springs(self, p):
        k = p["damping"]
        return {"structural": (p["structural"], k), "shear": (p["shear"], k), "bend": (p["bend"], 0.25 * k)}

    live_params = ("friction", "structural", "shear", "bend", "damping", "wind")

    def apply_param(self, key, value):
        if key == "wind":
            self.wind.speed = float(value)
            self.wind.coefficient = self.wind_coefficient if value else 0.0
        elif key == "friction":
            set_contact(self.sim.colliders, friction=value)
            if getattr(self, "vbd_contact", None) is not None:  # integrator=vbd: the contact inside the descent
                self.vbd_contact.friction = float(checks.nonnegative(value, "friction", fix="e.g. 0.4"))
        elif key == "damping":
            for kind, (start, count) in self.cloth.springs.items():
                set_springs(self.sim.model, "damping", value * (0.25 if kind == "bend" else 1.0), start, count)
        else:
            start, count = self.cloth.springs[key]
            set_springs(self.sim.model, "stiffness", value, start, count)
        drop_graphs(self.sim)  # friction is a launch argument baked into the captured frame

    def drag_map(self):
        return {"cloth": None}  # the cloth's particles are the model's, in order

    def declare(self, writer):
        c = self.cloth
        writer.add_mesh("cloth", c.face_vertex_counts, c.face_vertex_indices, color=(0.2, 0.45, 0.8),
                        double_sided=True)
        writer.add_sphere("sphere", self.sphere_center, self.params["sphere_radius"], color=(0.7, 0.7, 0.7))
        writer.add_plane("floor", size=3.0 * self.params["size"])

    def frame_arrays(self):
        from ..usd.frame_arrays import Particles

        return {"cloth": {"points": Particles("positions"), "velocities": Particles("velocities")}}

    def advance(self, frame_dt, substeps):
        self.sim.frame(frame_dt, self.frame_steps(frame_dt, substeps))
        self.sim.check_frame(frame_dt)

    def frame_steps(self, frame_dt, substeps):
        steps = "auto" if substeps == "auto" else substeps * self.steps_per_substep
        return self.steps_for(frame_dt, steps)


@register_scene("cloth", "a sheet pinned at two corners swings down onto a sphere (--set integrator=...)",
                params=COMMON)
class PinnedCloth(ClothScene):
    """The sheet starts horizontal at 1.2 m, pinned at the two corners of its edge z = -0.6 m, and
    swings about that edge into a sphere below it."""

    sphere_center = (0.0, 0.6, -0.3)

    def make_cloth(self, builder, p):
        s = p["size"]
        return add_cloth_grid(builder, p["resolution"], s, (-0.5 * s, 1.2, -0.6), u_axis=(1, 0, 0), v_axis=(0, 0, 1),
                              density=p["density"], pin=["corner_00", "corner_10"], radius=0.0,
                              **self.springs(p))


@register_scene("drape", "a sheet falls onto a sphere and drapes over it down to the floor",
                params=dict(COMMON, size=(1.6, "side of the sheet [m]"), sphere_radius=(0.35, "sphere radius [m]")))
class Drape(ClothScene):
    """The sheet starts horizontal at 1 m, centred over a sphere resting on the floor."""

    sphere_center = (0.0, 0.35, 0.0)

    def build(self, p):
        self.sphere_center = (0.0, p["sphere_radius"], 0.0)
        super().build(p)

    def make_cloth(self, builder, p):
        return add_cloth_grid(builder, p["resolution"], p["size"], (0.0, 1.0, 0.0), centered=True,
                              density=p["density"], **self.springs(p))
