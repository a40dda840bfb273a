"""The ``hair`` scene: a head with a groom of strands that keeps its shape from frame 0
(sag-free initialization), is still for a while, then turns and nods; the strands swing, collide
with the head and the floor, and can be grabbed in the viewer.

Prims: ``hair`` (BasisCurves, root to tip, widths tapering to the tip), ``head`` (a Mesh moving
with the head), ``floor``, and ``hair_vertices`` (Points of the free strand vertices, purpose
``guide``: what the viewer's mouse grabs).
"""

from __future__ import annotations

import math
from typing import ClassVar

import numpy as np

import warpsim as ws

from ..bodies.colliders import ParticleCollisions, quat_multiply, quat_rotate
from ..strands import StrandForce, StrandImplicitEuler, StrandRoots, add_strands, sag_free, strand_stable_dt
from ..strands.frame import HairFrame, PosedSphere
from ..strands.preflight import (FRAME_SECONDS_LIMIT, check_hair_params, estimate_basis, format_seconds,
                                 frame_seconds)
from ..usd.sink import display_hints
from . import SimulatorScene, register_scene
from .live import set_contact

MOTIONS = ("still", "turn", "nod", "turn_nod")
STYLES = ("straight", "wavy", "curly")
SOLVERS = ("implicit", "explicit")

HEAD_CENTER = (0.0, 0.55, 0.0)
HEAD_RADIUS = 0.1


def _axis_quat(axis, angle):
    a = np.asarray(axis, np.float64)
    return np.concatenate([a * math.sin(0.5 * angle), [math.cos(0.5 * angle)]])


def head_motion(kind, still, center, radius):
    """``motion`` callable for the head collider: identity until ``still`` [s], then a smooth start
    into turning (yaw 0.6 rad at 0.4 Hz) and/or nodding (pitch 0.3 rad at 0.6 Hz) about the neck,
    a pivot ``radius`` below ``center``."""
    pivot = np.asarray(center, np.float64) - np.array([0.0, radius, 0.0])

    def motion(t):
        tau = t - still
        if kind == "still" or tau <= 0.0:
            return np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0])
        ramp = min(tau / 0.5, 1.0)
        ramp = ramp * ramp * (3.0 - 2.0 * ramp)
        q = np.array([0.0, 0.0, 0.0, 1.0])
        if kind in ("turn", "turn_nod"):
            q = quat_multiply(q, _axis_quat((0.0, 1.0, 0.0), ramp * 0.6 * math.sin(2.0 * math.pi * 0.4 * tau)))
        if kind in ("nod", "turn_nod"):
            q = quat_multiply(q, _axis_quat((1.0, 0.0, 0.0), ramp * 0.3 * math.sin(2.0 * math.pi * 0.6 * tau)))
        return pivot - quat_rotate(q, pivot), q

    return motion


def scalp_roots(count, center, radius):
    """``count`` root positions on the scalp (a Fibonacci lattice of the sphere above 0.2 radius
    over the centre, the face (front, below 0.7 radius) left bare) and their outward normals."""
    lattice = max(64, 8 * count)
    k = np.arange(lattice) + 0.5
    y = 1.0 - 2.0 * k / lattice
    r = np.sqrt(1.0 - y * y)
    phi = math.pi * (3.0 - math.sqrt(5.0)) * k
    n = np.stack([r * np.cos(phi), y, r * np.sin(phi)], axis=1)
    keep = (n[:, 1] > 0.2) & ~((n[:, 2] > 0.3) & (n[:, 1] < 0.7))
    n = n[keep]
    if len(n) < count:
        raise ValueError(f"strands={count}: the scalp lattice has only {len(n)} roots")
    n = n[np.linspace(0, len(n) - 1, count).round().astype(int)]
    return np.asarray(center) + radius * n, n


def groom(roots, normals, center, radius, length, style, lift, wavelength=0.05, samples=160):
    """Polylines (S, samples, 3) [m]: from each root along the meridian over the head at ``lift``
    above the scalp down to its equator, then straight down; ``wavy`` adds a sideways wave
    (amplitude 8 mm, wavelength ``wavelength`` [m]) growing in over the first 3 cm, ``curly`` a
    helix about the path (radius 8 mm, one turn per ``wavelength``, away from the head first),
    growing in the same way."""
    c = np.asarray(center, np.float64)
    s = np.linspace(0.0, 1.0, samples)[None, :] * np.asarray(length, np.float64).reshape(-1, 1)  # (S, K)
    horizontal = normals * np.array([1.0, 0.0, 1.0])
    hn = np.linalg.norm(horizontal, axis=1, keepdims=True)
    horizontal = np.where(hn > 1e-6, horizontal / np.maximum(hn, 1e-12), np.array([[0.0, 0.0, -1.0]]))
    theta0 = np.arccos(np.clip(normals[:, 1], -1.0, 1.0))[:, None]  # from +y
    rho = radius + lift * np.clip(s / 0.02, 0.0, 1.0)  # leaves the scalp over 2 cm
    over = np.maximum(0.5 * math.pi - theta0, 0.0) * (radius + lift)  # arc length over the head
    theta = theta0 + np.minimum(s, over) / (radius + lift)
    up = np.array([0.0, 1.0, 0.0])
    pts = c + rho[..., None] * (np.sin(theta)[..., None] * horizontal[:, None, :] + np.cos(theta)[..., None] * up)
    below = np.maximum(s - over, 0.0)
    pts = pts - below[..., None] * up
    if style in ("wavy", "curly"):
        side = np.cross(up, horizontal)
        grow = 0.008 * np.clip(s / 0.03, 0.0, 1.0)
        angle = 2.0 * math.pi * s / wavelength
        pts = pts + (grow * np.sin(angle))[..., None] * side[:, None, :]
        if style == "curly":
            pts = pts + (grow * (1.0 - np.cos(angle)))[..., None] * horizontal[:, None, :]
    return pts


PARAMS = {
    "strands": (2000, "number of strands"),
    "segments": (16, "segments per strand"),
    "length": (0.25, "strand length [m]"),
    "style": ("straight", "groom: straight, wavy (a sideways wave of 8 mm) or curly (a helix of 8 mm radius); "
                          "a wave or curl spans >= 8 segments and 0.1 m",
              STYLES),
    "motion": ("turn_nod", "head motion after the still time: still, turn, nod or turn_nod", MOTIONS),
    "still": (1.0, "seconds the head stays still before it moves [s]"),
    "sag_free": (True, "solve the rest state so the groom is an equilibrium at frame 0"),
    "mass": (1.0e-3, "mass of a strand [kg] (a guide strand standing for many hairs)"),
    "stretch_rigidity": (5.0, "stretch rigidity EA of a strand [N]"),
    "bend_rigidity": (5.0e-4, "bending rigidity EI of a strand [N m^2]"),
    "damping": (0.02, "stretch damping [N s/m] (bending damping is a twentieth)"),
    "air_drag": (2.0e-4, "linear air drag on every strand vertex [kg/s]"),
    "friction": (0.3, "Coulomb friction of hair on the head and the floor"),
    "strand_friction": (0.0, "> 0: strand-strand collisions with this friction (ParticleCollisions)"),
    "radius": (0.002, "collision radius of a strand vertex [m]"),
    "solver": ("implicit", "strand step: implicit (backward Euler, a direct solve per strand) or explicit "
                           "(semi-implicit Euler at half the measured stable step)", SOLVERS),
    "graph": (True, "on CUDA: capture a frame's strand steps as one CUDA graph and replay it (the head's poses "
                    "are read from the device)"),
    "steps": (4, "implicit solver: strand steps per 1/60 s frame (backward Euler damps a mode of omega "
                 "by about exp(-omega^2 h t / 2))"),
}


@register_scene("hair", "a head with a groom of strands that holds its shape (sag-free), then turns and nods",
                params=PARAMS, fps=60.0, substeps=1)
class Hair(SimulatorScene):
    """Hair on a spherical head of radius 0.1 m at 0.55 m over the floor. ``solver=implicit``
    (default): ``StrandImplicitEuler``, ``steps`` strand steps per 1/60 s frame, or more when
    ``Simulator.stable_dt()`` is finite (``safety`` times it; every groom style is unrestricted).
    ``solver=explicit``: semi-implicit Euler, the frame sub-step split into steps of at most
    ``safety`` times the strands' stable step measured on the groom at frame 0
    (``strand_stable_dt(hair, model)``)."""

    smoke_params: ClassVar[dict] = {"strands": 12, "segments": 4}
    safety = 0.5

    def build(self, p):
        if p["solver"] not in SOLVERS:
            raise ValueError(f"solver={p['solver']!r}: give one of {', '.join(SOLVERS)}")
        for key in ("strands", "segments", "steps"):
            if p[key] < 1:
                raise ValueError(f"{key}={p[key]}: it must be >= 1")
        for key in ("length", "mass", "stretch_rigidity", "bend_rigidity", "radius"):
            if not p[key] > 0.0:
                raise ValueError(f"{key}={p[key]}: it must be > 0")
        for key in ("damping", "air_drag", "friction", "strand_friction", "still"):
            if not p[key] >= 0.0:
                raise ValueError(f"{key}={p[key]}: it must be >= 0")
        # every size (strands, segments, steps, the dense stability check, sag-free's minimum) refused
        # with the figure before anything is allocated
        check_hair_params(p, self.device)
        self.head = PosedSphere(HEAD_CENTER, HEAD_RADIUS, restitution=0.0, friction=p["friction"], mode="project",
                           motion=head_motion(p["motion"], p["still"], HEAD_CENTER, HEAD_RADIUS))
        roots, normals = scalp_roots(p["strands"], HEAD_CENTER, HEAD_RADIUS)
        # a wave or curl of at least 8 segments and 0.1 m (resolved by the segments; the implicit step
        # takes the bending frames' coupling, so sharper ones stay stable too: 0.05 m at 32 segments
        # measured stiffness ratios 0.89-1.13)
        wavelength = max(0.1, 8.0 * p["length"] / p["segments"])
        lines = groom(roots, normals, HEAD_CENTER, HEAD_RADIUS, p["length"], p["style"], lift=2.0 * p["radius"] + 1e-3,
                      wavelength=wavelength)
        b = ws.ModelBuilder()
        self.hair = add_strands(b, segments=p["segments"], polylines=lines, mass=p["mass"],
                                stretch_rigidity=p["stretch_rigidity"], bend_rigidity=p["bend_rigidity"],
                                stretch_damping=p["damping"], bend_damping=p["damping"] / 20.0, radius=p["radius"],
                                head=self.head)
        self.model = b.finalize(self.device)
        self.floor = ws.Plane((0.0, 1.0, 0.0), 0.0, restitution=0.0, friction=p["friction"], mode="project")
        self.roots = StrandRoots(self.hair, self.head)
        colliders = [self.head, self.roots, self.floor]
        if p["strand_friction"] > 0.0:
            colliders.append(ParticleCollisions(restitution=0.0, friction=p["strand_friction"]))
        forces = [ws.Gravity(), StrandForce(self.hair)]
        if p["air_drag"] > 0.0:
            forces.append(ws.Drag(linear=p["air_drag"]))
        self.implicit = p["solver"] == "implicit"
        self.steps_per_frame = int(p["steps"])
        if self.implicit:
            # inf for every groom style (see warpsim.strands.stability.implicit_limit)
            self.sim = ws.Simulator(self.model, integrator=StrandImplicitEuler(self.hair), forces=forces,
                                    colliders=colliders, max_speed=100.0)
            self.stable_dt = self.sim.stable_dt()
        else:
            self.stable_dt = strand_stable_dt(self.hair, self.model)
            # the measured step sets a frame's steps: refused now when a frame would take hours
            seconds = frame_seconds(self.strand_steps(1.0 / 60.0), self.model.particle_count, "explicit", self.device)
            if seconds > FRAME_SECONDS_LIMIT:
                raise ValueError(f"solver=explicit: at segments={p['segments']} the strands' stable step is "
                                 f"{self.stable_dt:.3g} s, {self.strand_steps(1.0 / 60.0):,} steps a frame of "
                                 f"{self.model.particle_count:,} particles take about {format_seconds(seconds)} a "
                                 "frame; use solver=implicit, or fewer segments or strands (the time estimated "
                                 f"{estimate_basis(self.device, False)})")
            self.sim = ws.Simulator(self.model, forces=forces, colliders=colliders, max_speed=100.0)
        # the blow-up test (a device read-back) once per frame, not once per strand step
        self.sim.check_every = self.strand_steps(1.0 / self.fps)
        self.sag_report = self._sag_free(p) if p["sag_free"] else None
        # a frame's strand steps read the head's poses from the device: one CUDA graph a frame on CUDA
        self.frame = HairFrame(self.sim, self.head, self.roots, use_graph=None if p["graph"] else False)
        self._curve_particles = self.hair.curve_particles().reshape(-1)
        self._free_particles = self.hair.free_particles()
        from ..bodies.shapes import icosphere

        verts, tris = icosphere(3)
        self._head_local = verts.astype(np.float64) * HEAD_RADIUS
        self._head_tris = tris

    # the sag-free solve's CGLS tolerance, for rounds whose direct per-strand solve leaves its bounds
    # (CGLS takes those): its residual force is floored near 0.3 % of the load by the float32 force
    # kernels whatever the tolerance (150 strands x 32 segments, CPU: rtol 1e-10 13,775 iterations,
    # residual 0.33 %; 1e-4 5,475 iterations, 0.31 %)
    SAG_FREE_RTOL = 1.0e-4
    # CGLS iterations a round at most: a load the bounds cannot carry (a heavy strand: mass=0.05) never
    # converges, and the default 50,000 a round ran for over 12 minutes at 2,000 x 16 on the CPU; the
    # solves that do converge took 5,475 (150 x 32 above)
    SAG_FREE_MAX_ITERATIONS = 8000
    # seconds per particle of the sag-free solve (the direct per-strand solve): CPU measured (36,000
    # particles in 0.29 s, 2 cores under load; 150 x 32: 0.23 s, tips within 0.009 mm over 2 s);
    # CUDA: a bound until measured (the CGLS solve took 2.6e-5 at 3.4 M particles on an H100)
    SAG_FREE_RATE = {"cpu": 1.0e-5, "cuda": 1.0e-6}

    def _sag_free(self, p):
        """``sag_free(self.sim)``, saying on stderr what it does and about how long it takes when
        that is more than 2 s (the viewer's start-up is mostly this)."""
        import sys
        import time

        device = str(self.model.device)
        estimate = self.model.particle_count * self.SAG_FREE_RATE["cpu" if device.startswith("cpu") else "cuda"]
        loud = estimate > 2.0
        if loud:
            print(f"warpsim: hair: solving the sag-free rest state of {p['strands']:,} strands x {p['segments']} "
                  f"segments on {device} (about {estimate:.0f} s; --set sag_free=false skips it) ...",
                  file=sys.stderr, flush=True)
        t0 = time.perf_counter()
        try:
            report = sag_free(self.sim, rtol=self.SAG_FREE_RTOL, max_iterations=self.SAG_FREE_MAX_ITERATIONS)
        except ValueError as exc:  # the scene's parameters that set the load and the bound, named
            raise ValueError(f"{exc} (scene parameters: segments={p['segments']}, mass={p['mass']:g}, "
                             f"bend_rigidity={p['bend_rigidity']:g}; more segments, a lighter mass, a stiffer bend "
                             "or sag_free=false)") from None
        if loud:
            print(f"warpsim: hair: sag-free done in {time.perf_counter() - t0:.1f} s", file=sys.stderr, flush=True)
        return report

    def strand_steps(self, h):
        """Strand steps per sub-step of ``h`` [s]: ``steps`` per 1/60 s (implicit), or inside the
        strands' measured stable step (explicit)."""
        n = math.ceil(h / (self.safety * self.stable_dt) - 1e-9) if math.isfinite(self.stable_dt) else 1
        if self.implicit:
            return max(1, n, math.ceil(h * 60.0 * self.steps_per_frame - 1e-9))
        return max(1, n)

    def frame_seconds(self, frame_dt, substeps):
        """Estimated seconds of one frame on this scene's device (said before the first step when long)."""
        solver = "implicit" if self.implicit else "explicit"
        return frame_seconds(self.frame_steps(frame_dt, substeps), self.model.particle_count, solver, self.device)

    def frame_steps(self, frame_dt, substeps):
        """Steps a frame takes: ``substeps`` sub-steps, each split into strand steps."""
        substeps = 1 if substeps == "auto" else int(substeps)
        return substeps * self.strand_steps(frame_dt / substeps)

    def advance(self, frame_dt, substeps):
        self.frame.advance(frame_dt, self.frame_steps(frame_dt, substeps))

    # ------------------------------------------------------------------ live parameters, dragging
    live_params = ("friction",)

    def apply_param(self, key, value):
        if not value >= 0.0:
            raise ValueError(f"{key}={value}: it must be >= 0")
        set_contact([self.head, self.floor], friction=value)

    @property
    def drag_stiffness_hint(self):
        """The viewer's drag spring [N/m] when the step is implicit (it takes the drag spring's
        Jacobian): the strands' median stretch stiffness, so a grabbed vertex follows about as
        firmly as its segments hold it; None for the explicit step (the viewer's cap)."""
        return float(np.median(self.hair.stretch_stiffness)) if self.implicit else None

    def drag_map(self):
        """The free strand vertices (``hair_vertices``) and the drawn curves (``hair``: per segment
        end, the particle of that curve vertex; the viewer picks the one nearest the pointer's ray)."""
        curves = self.hair.curve_particles()
        ends = np.stack([curves[:, :-1], curves[:, 1:]], axis=2).reshape(-1)
        return {"hair_vertices": self._free_particles, "hair": ends}

    # ------------------------------------------------------------------ output
    def declare(self, writer):
        h = self.hair
        writer.add_curves("hair", curve_vertex_counts=np.full(h.strand_count, h.segments + 1),
                          width=h.curve_widths(), color=(0.35, 0.22, 0.12))
        writer.add_mesh("head", np.full(len(self._head_tris), 3), self._head_tris.reshape(-1), velocities=False,
                        color=(0.85, 0.7, 0.6))
        writer.add_plane("floor", size=1.5)
        # the free strand vertices, what the viewer's mouse grabs: a guide (hidden by USD tools and
        # ``warpsim render`` unless asked for)
        decl = writer.add_points("hair_vertices", radius=float(h.radius.max()), color=(0.35, 0.22, 0.12),
                                 velocities=False)
        display_hints(decl, purpose="guide")

    def head_points(self):
        p, q = self.head.world_pose()
        u, w = q[:3], q[3]
        v = self._head_local
        return p + v + 2.0 * np.cross(u, np.cross(u, v) + w * v)

    def frame_arrays(self):
        """The strands' curve vertices and free vertices from the particle arrays; the head's
        points (moved by the head's clock) shared by every world of a batch."""
        from ..usd.frame_arrays import Particles, Shared

        return {"hair": {"points": Particles("positions", self._curve_particles)},
                "head": {"points": Shared(self.head_points)},
                "hair_vertices": {"points": Particles("positions", self._free_particles)}}

    def frame_data(self):
        from ..usd.frame_arrays import frame_data_from

        st = self.sim.state
        return frame_data_from(self.frame_arrays(), st.positions, st.velocities)

    def checkpoint(self):
        data = super().checkpoint()
        data["head_clock"] = np.float64(self.head.clock)
        return data

    def restore(self, data):
        super().restore(data)
        self.head.set_clock(float(data["head_clock"]))
        self.roots.reset_pose()
