"""Scene presets for the command line (``warpsim list`` / ``warpsim run SCENE``).

Adding a scene is one decorator on a :class:`Scene` subclass in any module of this package
(``warpsim/scenes/*.py`` is imported by :func:`scenes`, and a built-in scene's module alone by
:func:`get_scene`: add a new one to :data:`BUILT_IN`; scenes elsewhere register when their module
is imported, or through the ``warpsim.scenes`` entry-point group)::

    import warpsim as ws
    from warpsim.scenes import SimulatorScene, register_scene

    @register_scene("drop", "a column of particles falling on a floor",
                    params={"count": (100, "number of particles"),
                            "restitution": (0.5, "normal bounce coefficient in [0, 1]"),
                            "dt": (1 / 240, "time step [s]"),
                            "integrator": ("semi_implicit_euler", "time integrator", sorted(ws.INTEGRATORS))})
    class Drop(SimulatorScene):
        substeps = 4                       # defaults for --substeps (and --fps when there is no dt)

        def build(self, p):                # p: the parameters, already typed and validated
            b = ws.ModelBuilder()
            for i in range(p["count"]):
                b.add_particle((0.0, 0.1 + 0.02 * i, 0.0), radius=0.01)
            self.sim = ws.Simulator(b.finalize(self.device), integrator=p["integrator"],
                                    colliders=[ws.Plane(restitution=p["restitution"])])

        def declare(self, writer):         # prims on the UsdCacheWriter
            self.declare_state(writer, "particles", radius=0.01)

        # frame_data() of SimulatorScene writes state positions/velocities into the points
        # declare_state declared; override it to add more prims (meshes, curves, primvars).

A parameter is ``(default, help)`` or ``(default, help, choices)``; its type comes from the
default (bool, int, float, str, or a tuple of floats written ``x,y,z``). A ``dt`` parameter is
the simulation step: frames are then ``dt * substeps`` apart (``--fps`` and ``--set dt`` are
two ways to say the same thing; ``--substeps N`` keeps that frame rate and splits the frame in N
steps: see :mod:`warpsim.scenes.timing`, whose :class:`FrameTiming` every command resolves once).
Scenes implement :class:`Scene`: ``build``, ``declare``, ``frame_data``, ``advance``, and
``checkpoint``/``restore`` (for ``--checkpoint-every`` and ``--resume``; :class:`SimulatorScene`
provides all but ``build`` and ``declare``).

``tests/test_cli.py`` runs every registered scene for a few frames on the CPU, validates its
cache and compares it with an independent run; give a heavy scene a class attribute
``smoke_params = {"count": 50}`` (parameter values) to keep that test small.
"""
from __future__ import annotations

import importlib
import pkgutil
import sys
from dataclasses import dataclass
from typing import Any, ClassVar, Optional

import numpy as np

from ..core.names import close_matches
from .timing import FrameTiming, resolve_timing

__all__ = ["FrameTiming", "Param", "Scene", "SimulatorScene", "get_scene", "parse_value", "register_scene",
           "resolve_timing", "scenes"]

_REGISTRY = {}
_LOADED = False

BUILT_IN = {
    "bounce": "basic", "pendulum": "basic", "springs": "basic",
    "cloth": "cloth", "drape": "cloth",
    "crowd": "agents", "flock": "agents", "school": "agents", "zombies": "agents",
    "dam_break": "fluids_sph", "pour": "fluids_sph",
    "donuts": "fracture", "wall": "fracture",
    "flip_splash": "grid_fluids", "liquid": "grid_fluids", "smoke": "grid_fluids",
    "hair": "hair", "metaballs": "meshing", "teapot": "teapot",
}
"""The module of this package that registers each built-in scene: :func:`get_scene` imports only
that one (``warpsim run bounce`` and ``warpsim sweep teapot`` do not define the fluids' or the
crowds' kernels); :func:`scenes` imports them all, and the plugins. A built-in name is always the
built-in scene. ``tests/test_public_api.py`` checks this table against the registry."""

CONTAINER = {"opacity": 0.2, "purpose": "render"}
"""Display hints for boxes of walls and tanks (``writer.add_box(..., **CONTAINER)``): render-purpose
geometry (Blender's importer and renderers load it; ``guide`` is kept for pure helpers, which they
skip) with a low ``displayOpacity`` and a bound ``UsdPreviewSurface`` material of that opacity, so
the container shows and what it holds shows through it."""


def add_floor(writer, lower, upper, *, margin=0.5, color=(0.55, 0.55, 0.55)):
    """Declare an opaque floor prim under a container: a +Y-facing quad at height ``lower[1]`` [m]
    covering the container's footprint [lower, upper] widened by ``margin`` times its size on every
    side, so DCC tools show what the bodies rest on (the container's own walls are see-through)."""
    lo, hi = np.asarray(lower, np.float64), np.asarray(upper, np.float64)
    pad = margin * (hi - lo)
    x0, x1, z0, z1, y = lo[0] - pad[0], hi[0] + pad[0], lo[2] - pad[2], hi[2] + pad[2], lo[1]
    points = np.array([[x0, y, z0], [x0, y, z1], [x1, y, z1], [x1, y, z0]])  # counter-clockwise from +Y
    return writer.add_static_mesh("floor", points, [4], [0, 1, 2, 3], color=color, double_sided=False)


@dataclass(frozen=True)
class Param:
    """A settable scene parameter: default value (its type is the parameter's), help, choices, and
    ``lowest``: the smallest value the viewer's slider offers (None: its usual range), where the
    scene's model stops holding below it."""

    default: object
    help: str = ""
    choices: Optional[tuple] = None
    lowest: Optional[float] = None

    @property
    def type_name(self):
        d = self.default
        if isinstance(d, bool):
            return "bool"
        if isinstance(d, int):
            return "int"
        if isinstance(d, float):
            return "float"
        if isinstance(d, (tuple, list)):
            return f"{len(d)} floats x,y,..."
        return "str"


def parse_value(param, key, text):
    """Parse command-line text for ``param``; ValueError naming ``key`` and the expected form."""
    d = param.default
    text = str(text).strip()
    try:
        if isinstance(d, bool):
            low = text.lower()
            if low not in ("1", "0", "true", "false", "yes", "no", "on", "off"):
                raise ValueError
            value = low in ("1", "true", "yes", "on")
        elif isinstance(d, int):
            value = int(text)
        elif isinstance(d, float):
            value = float(text)
            if not np.isfinite(value):
                raise ValueError
        elif isinstance(d, (tuple, list)):
            value = tuple(float(x) for x in text.split(","))
            if len(value) != len(d) or not np.isfinite(value).all():
                raise ValueError
        else:
            value = text
    except ValueError:
        raise ValueError(f"{key}={text!r} is not a valid {param.type_name} (default {format_value(d)})") from None
    if param.choices is not None and value not in param.choices:
        raise ValueError(f"{key}={text!r} is not one of {', '.join(map(str, param.choices))}."
                         f"{close_matches(text, param.choices)}")
    return value


def format_value(value):
    if isinstance(value, (tuple, list)):
        return ",".join(f"{v:g}" for v in value)
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)


class Scene:
    """A simulation preset the command line can run and stream to a USD cache.

    Class attributes (set by :func:`register_scene`): ``name``, ``description``, ``params``
    ({key: Param}). Defaults for the run: ``fps`` (when there is no ``dt`` parameter) and
    ``substeps``. ``self.params`` holds the typed parameter values, ``self.device`` the Warp device.
    """

    name: ClassVar[str] = ""
    description: ClassVar[str] = ""
    params: ClassVar[dict] = {}
    fps: ClassVar[float] = 60.0
    substeps: ClassVar[int] = 1
    substeps_auto: ClassVar[bool] = False
    """True for scenes whose frames sub-step automatically inside the stability limit by default
    (:func:`~warpsim.scenes.timing.resolve_timing` turns it off when dt or --substeps N is given
    by hand)."""
    smoke_params: ClassVar[dict] = {}  # small parameter values for the test suite's smoke run
    _steps_limit: Any = None  # the limit automatic steps keep inside (None: the scene's own; see use_timing)

    def __init__(self, params=None, device=None):
        import warp as wp

        self.device = wp.get_device(device)
        self.params = self.resolve_params(params or {})
        self.frame = 0
        cls = type(self)  # a dt other than the scene's is the user's step (automatic timing off)
        given = tuple(k for k in (params or {}) if self.params[k] != cls.params[k].default)
        self.timing = resolve_timing(cls, self.params, given=given)
        """The scene's :class:`~warpsim.scenes.timing.FrameTiming` (its defaults until a command or
        a batch gives it one with :meth:`use_timing`); with ``timing.auto`` each frame takes at
        least ``substeps`` steps and as many as half the stability limit needs (:meth:`steps_for`)."""
        self._steps_limit = None
        self.build(self.params)

    @property
    def auto_substeps(self) -> bool:
        """Whether frames sub-step automatically (``self.timing.auto``; give the scene another
        timing with :meth:`use_timing` to change it)."""
        return self.timing.auto

    def use_timing(self, timing, *, limit=None):
        """Time the frames to come by ``timing`` (a :class:`~warpsim.scenes.timing.FrameTiming` from
        :func:`~warpsim.scenes.timing.resolve_timing`; a fixed automatic count, e.g. the one a
        whole sweep took, is used as it is). ``limit``: the ``ws.StabilityLimit`` automatic steps
        keep inside (anything with ``substeps_for(frame_dt, minimum=...)``: a batch of worlds gives
        itself, the most steps any of its worlds needs), None: the scene's own."""
        self.timing = timing
        self._steps_limit = limit

    def current_timing(self):
        """``self.timing`` with the steps a frame takes now (automatic: resolved against the limit)."""
        t = self.timing
        return t if t.fixed else t.with_steps(self.frame_steps(t.frame_dt, t.steps))

    def stability(self):
        """The ``ws.StabilityLimit`` of the scene's simulator (``self.sim``, linearised about its
        initial positions) or None for scenes without one."""
        sim: Any = getattr(self, "sim", None)
        if not hasattr(sim, "stability"):
            return None
        return sim.stability(positions=sim.model.particle_q)

    def frame_steps(self, frame_dt, substeps) -> int:
        """Steps :meth:`advance` takes in a frame (``steps_for`` unless a scene steps otherwise)."""
        return self.steps_for(frame_dt, substeps)

    def stability_warning(self, frame_dt, substeps):
        """One line when the step this scene takes (frame_dt / steps) is above its stability
        limit, naming the limiter and the remedies, else the scene's own (:meth:`scene_warning`);
        None when it is inside or unknown."""
        limit = self.stability()
        if limit is not None:
            h = frame_dt / self.frame_steps(frame_dt, substeps)
            if limit.exceeded_by(h):
                return limit.warning(h)
        return self.scene_warning(frame_dt, substeps)

    def scene_warning(self, frame_dt, substeps):
        """A line of the scene's own about its step (frame_dt / steps) that no stability limit gives (e.g. a fall
        faster than its contact can follow), with the remedies; None (the default) when it has none. A sweep gives
        its first world's (``warpsim.worlds.batch.WorldBatch.stability_warning``)."""
        return None

    def steps_for(self, frame_dt, substeps) -> int:
        """Steps in a frame of ``frame_dt`` [s]: ``substeps``, or with automatic timing
        (``self.timing.auto``, or ``substeps="auto"``: at least one step) at least that many and
        enough to keep each step within ``warpsim.core.stability.AUTO_SAFETY`` x the stability
        limit (:meth:`auto_steps`; a fixed automatic timing, e.g. the count a whole sweep took,
        gives its count)."""
        timing = self.timing
        if substeps == "auto":
            return self.auto_steps(frame_dt, 1)
        if not timing.auto:
            return int(substeps)
        if timing.fixed:
            return timing.steps
        return self.auto_steps(frame_dt, int(substeps))

    def auto_steps(self, frame_dt, minimum) -> int:
        """Steps (at least ``minimum``) keeping each step of a frame of ``frame_dt`` [s] within
        ``AUTO_SAFETY`` x the limit: the one :meth:`use_timing` was given, else that of
        ``self.sim`` (computed once about the initial positions, again after a parameter change);
        ``minimum`` for scenes without a limit."""
        if self._steps_limit is not None:
            return self._steps_limit.substeps_for(frame_dt, minimum=int(minimum))
        sim: Any = getattr(self, "sim", None)
        if not hasattr(sim, "auto_substeps"):
            return int(minimum)
        return sim.auto_substeps(frame_dt, minimum=int(minimum))

    @classmethod
    def resolve_params(cls, given):
        """Defaults overridden by ``given`` (typed values or strings); ValueError on unknown keys."""
        out = {k: p.default for k, p in cls.params.items()}
        for key, value in given.items():
            if key not in cls.params:
                raise ValueError(f"scene {cls.name!r} has no parameter {key!r}; its parameters are "
                                 f"{', '.join(cls.params) or 'none'}.{close_matches(key, cls.params)}")
            param = cls.params[key]
            out[key] = parse_value(param, key, value) if isinstance(value, str) else value
        if isinstance(out.get("seed"), int) and not isinstance(out["seed"], bool) and out["seed"] < 0:
            raise ValueError(f"seed={out['seed']}: a random seed must be an integer >= 0")
        return out

    def build(self, params):
        """Create the simulation from ``params``."""
        raise NotImplementedError

    def declare(self, writer):
        """Declare this scene's prims on a :class:`warpsim.usd.writer.UsdCacheWriter`."""
        raise NotImplementedError

    def frame_data(self):
        """The current frame as ``{prim name: {key: array}}`` for ``writer.write_frame``."""
        raise NotImplementedError

    def frame_arrays(self):
        """The frame data as arrays derived from the simulator's particle arrays
        (:mod:`warpsim.usd.frame_arrays`: ``{prim: {key: Particles(...) | PerWorld(...) |
        Shared(...)}}``), from which :meth:`frame_data` is made, so a batch of worlds makes every
        world's samples at once; None (the default) when the frame data is not a function of the
        particle arrays (agents, fluids, broken springs): a batch then asks each world in turn."""
        return None

    def advance(self, frame_dt, substeps):
        """Simulate one frame of ``frame_dt`` [s] in ``substeps`` equal steps."""
        raise NotImplementedError

    # ------------------------------------------------------------------ live viewer hooks
    live_params: ClassVar[tuple] = ()
    """Parameters :meth:`set_param` changes in the running simulation (the viewer rebuilds the
    scene for any other)."""

    def set_param(self, key, value) -> bool:
        """Apply parameter ``key`` = ``value`` (typed, see :func:`parse_value`) to the running
        simulation: True when applied live (``key`` in ``live_params``), False when the scene
        must be rebuilt for it. ValueError for a bad value."""
        if key not in self.live_params:
            return False
        self.apply_param(key, value)
        self.params[key] = value
        sim: Any = getattr(self, "sim", None)
        if hasattr(sim, "invalidate_stability"):  # stiffness, masses, contacts: the limit moves
            sim.invalidate_stability()
        return True

    def apply_param(self, key, value) -> None:
        """Change one of ``live_params`` in place (see :mod:`warpsim.scenes.live`)."""
        raise NotImplementedError(f"scene {self.name!r} lists {key!r} as live but does not apply it")

    def drag_map(self):
        """What the mouse can grab: ``{drawn prim name: None}`` when vertex i of that prim is
        particle i of the simulation, or ``{name: int array}`` of particle indices per drawn
        vertex; ``{}`` when nothing can be grabbed."""
        return {}

    def add_drag(self, drag) -> None:
        """Attach a ``ws.DragSpring`` (unbound) to the running simulation."""
        raise NotImplementedError(f"scene {self.name!r} cannot be dragged")

    # ------------------------------------------------------------------ sweep hooks
    track_anchors: ClassVar[tuple] = ()
    """Names ``warpsim sweep --track NAME`` takes besides particle indices (:meth:`anchor_particle`)."""

    def anchor_particle(self, name) -> int:
        """The particle index of anchor ``name`` (one of ``track_anchors``) in this built scene."""
        raise ValueError(f"scene {self.name!r} has no anchor {name!r}; give a particle index")

    def checkpoint(self):
        """Everything needed to continue exactly: a dict of NumPy arrays / scalars."""
        raise NotImplementedError(f"scene {self.name!r} does not support checkpoints")

    def restore(self, data):
        """Inverse of :meth:`checkpoint`."""
        raise NotImplementedError(f"scene {self.name!r} does not support checkpoints")


class SimulatorScene(Scene):
    """A Scene driving one ``ws.Simulator`` in ``self.sim``: stepping, checkpoints and the
    frame data of points prims declared with :meth:`declare_state` come for free."""

    sim: Any = None
    _state_prims = None

    def advance(self, frame_dt, substeps):
        # the solver protocol's frame: its steps, then the energy balance (an instability the speed
        # bound misses)
        self.sim.frame(frame_dt, self.frame_steps(frame_dt, substeps))

    def frame_arrays(self):
        """Each points prim declared with :meth:`declare_state` holds every particle's position and
        velocity."""
        from ..usd.frame_arrays import Particles

        return {name: {"points": Particles("positions"), "velocities": Particles("velocities")}
                for name in self._state_prims or ()}

    def frame_data(self):
        from ..usd.frame_arrays import frame_data_from

        state = self.sim.state
        return frame_data_from(self.frame_arrays(), state.positions, state.velocities)

    def drag_map(self):
        return {name: None for name in self._state_prims or ()}

    def add_drag(self, drag):
        self.sim.add_force(drag)

    def declare_state(self, writer, name="particles", **kw):
        """Declare a points prim filled from the simulator state every frame."""
        decl = writer.add_points(name, from_state=True, **kw)
        self._state_prims = (self._state_prims or ()) + (name,)
        return decl

    def checkpoint(self):
        from ..usd.checkpoint import simulator_checkpoint

        return simulator_checkpoint(self.sim)

    def restore(self, data):
        from ..usd.checkpoint import restore_simulator

        restore_simulator(self.sim, data)


def register_scene(name, description, params=None, *, fps=None, substeps=None):
    """Class decorator adding a :class:`Scene` subclass to the registry under ``name``.

    ``params``: {key: (default, help) or (default, help, choices) or Param}."""

    def wrap(cls):
        if not (isinstance(cls, type) and issubclass(cls, Scene)):
            raise TypeError(f"@register_scene({name!r}) decorates Scene subclasses, not {cls!r}")
        home = BUILT_IN.get(name)
        if home is not None and cls.__module__ != f"{__name__}.{home}":
            raise ValueError(f"scene name {name!r} is taken by a built-in scene (warpsim/scenes/{home}.py): "
                             f"register {cls.__name__} under another name")
        old = _REGISTRY.get(name)
        if old is not None and (old.__module__, old.__qualname__) != (cls.__module__, cls.__qualname__):
            raise ValueError(f"scene name {name!r} is already registered by {_REGISTRY[name].__module__}")
        spec = {}
        for key, value in (params or {}).items():
            spec[key] = value if isinstance(value, Param) else Param(*value) if isinstance(value, tuple) else Param(value)
            if spec[key].choices is not None:
                spec[key] = Param(spec[key].default, spec[key].help, tuple(spec[key].choices), spec[key].lowest)
        cls.name, cls.description, cls.params = name, description, spec
        if fps is not None:
            cls.fps = float(fps)
        if substeps is not None:
            cls.substeps = int(substeps)
        _REGISTRY[name] = cls
        return cls

    return wrap


def _load():
    """Import every module of this package (and entry points) so their scenes register."""
    global _LOADED
    if _LOADED:
        return
    _LOADED = True
    for info in pkgutil.iter_modules(__path__, __name__ + "."):
        try:
            importlib.import_module(info.name)
        except Exception as exc:  # noqa: BLE001  (a broken scene module must not take the others down)
            print(f"warpsim: warning: scene module {info.name} failed to import: {exc}", file=sys.stderr)
    from importlib.metadata import entry_points

    try:
        eps = entry_points(group="warpsim.scenes")
    except TypeError:  # pragma: no cover - Python 3.9: no group selection
        eps = entry_points().get("warpsim.scenes", [])
    for ep in eps:
        try:
            ep.load()
        except Exception as exc:  # noqa: BLE001
            print(f"warpsim: warning: scene entry point {ep.name} failed to load: {exc}", file=sys.stderr)


def scenes():
    """{name: Scene class} of every registered scene, sorted by name."""
    _load()
    return dict(sorted(_REGISTRY.items()))


def get_scene(name):
    """The Scene class registered as ``name``; ValueError with close matches otherwise. A built-in
    scene imports only its own module (:data:`BUILT_IN`)."""
    module = BUILT_IN.get(name)
    if module is not None and not _LOADED:
        try:
            importlib.import_module(f"{__name__}.{module}")
        except Exception:  # noqa: BLE001  (scenes() below imports it again and reports why it failed)
            pass
        if _REGISTRY.get(name) is not None and _REGISTRY[name].__module__ == f"{__name__}.{module}":
            return _REGISTRY[name]
    registry = scenes()
    if name not in registry:
        raise ValueError(f"unknown scene {name!r}.{close_matches(name, registry)} Known scenes: "
                         f"{', '.join(registry) or 'none'} (see 'warpsim list').")
    return registry[name]
