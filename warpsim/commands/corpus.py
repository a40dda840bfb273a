"""The full-length corpus: every scene run as a user runs it, and the blow-ups the alarm must catch.

One case list and one runner, shared by ``benchmarks/check_scenes.py`` (full size, e.g. on a GPU)
and ``tests/test_full_length.py`` (the CPU, resolution lowered, never frames):

- ``default``: every scene of ``warpsim list`` at its default parameters for its default length
  (``warpsim run``'s 120 frames: no scene has a length of its own); ``long``: the same for
  ``slider_frames`` (600);
- ``KEY=END``: each end of the physical sliders the viewer gives a scene (damping, restitution,
  stiffnesses, wind, masses and densities: :func:`slider_ends`), for ``slider_frames`` frames;
- ``README``: every ``warpsim run`` command of README.md at its README length (a re-run of a sweep's
  world, ``--from-sweep``, is left out: it is the sweep's world, not a run of its own);
- ``blowup INTEGRATOR``: each explicit integrator at ``BLOWUP`` (1.2) x its stability limit in
  springs, teapot, cloth (semi_implicit_euler, its only explicit one) and hair (its explicit
  solver): the alarm must stop the run within ``GRACE`` (2) frames of the frame where the
  energy of an unchecked twin run started to grow (:func:`growth_frame`).

A case runs through ``warpsim run``'s own code (:func:`run_case`): its command line is parsed by
the command's parser, the parameters and the timing resolved by the functions the command uses
(``parse_sets``, ``timing_from_flags``, ``stability_check``), the scene built, given its timing and
advanced frame by frame with ``frame_data()`` read as the cache writer reads it; only the USD
cache is not written. A ``SimulationError`` is the alarm (the command's exit 1), and the
simulator's ``energy_gain`` is read after every frame.

``small=True`` lowers only resolution-type parameters (``SMALL``: cells, particles, strands,
agents, tori), never frames, fps or steps."""

from __future__ import annotations

import argparse
import math
import os
import re
import shlex
import time
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Optional

import numpy as np

__all__ = ["BLOWUP", "BLOWUP_SCENES", "DEFAULT_FRAMES", "GRACE", "KINDS", "SLIDER_FRAMES", "SMALL", "Case",
           "Result", "blowup_cases", "cases", "default_cases", "format_table", "growth_frame", "long_cases",
           "issue_cases", "readme_cases", "resolve_blowup", "run_case", "slider_cases", "slider_ends"]

DEFAULT_FRAMES = 120
"""The default length of every scene: ``warpsim run``'s ``--frames`` default (no scene has its own)."""

SLIDER_FRAMES = 600
"""Frames of a slider end (the issue's 600; capped by a scene length when one is given)."""

BLOWUP = 1.2
"""A blow-up case's step against its stability limit."""

GRACE = 2
"""Frames after the growth by which a blow-up must be stopped."""

EXPLICIT = ("explicit_euler", "semi_implicit_euler", "rk2", "rk4")

BLOWUP_SCENES = {"springs": EXPLICIT, "teapot": EXPLICIT, "cloth": ("semi_implicit_euler",),
                 "hair": ("explicit",)}
"""Scenes and the explicit integrators (hair: its ``solver=explicit``) run at ``BLOWUP`` x the limit."""

WIND_END = 10.0
"""The right end of the cloth's wind [m/s]: a number box from 0 in the viewer (no slider range); a
strong gale."""

SMALL: dict[str, dict[str, Any]] = {
    "cloth": {"resolution": 12},
    "drape": {"resolution": 12},
    "teapot": {"resolution": "2"},
    "donuts": {"count": 2, "segments": 8, "sides": 4, "lattice_cells": 3},
    "wall": {"bricks": "2,2", "spacing": 0.1},
    "hair": {"strands": 12, "segments": 4},
    "crowd": {"people": 10},
    "flock": {"birds": 20, "geese": 4},
    "school": {"fish": 8},
    "zombies": {"zombies": 8},
    "dam_break": {"spacing": 0.06},
    "pour": {"spacing": 0.06},
    "flip_splash": {"resolution": 8, "particles_per_cell": 2},
    "liquid": {"resolution": 10, "particles_per_cell": 4},
    "smoke": {"resolution": 8},
    "metaballs": {"resolution": 16},
}
"""Resolution-type parameters the CPU lowers (cells, particle spacing, counts of strands, agents,
tori, bricks): the scene's dynamics and its frames stay; a README command's own value of one of
them is lowered too (e.g. the donuts heap's count=1000 -> 2)."""

SLIDER_KEYS = re.compile(r"^(dt|damping|restitution|wind|mass|ball_mass|density|structural|shear|bend|"
                         r"stretch_rigidity|bend_rigidity|stiffness|ball_stiffness|mortar_stiffness|"
                         r"brick_stiffness|contact_stiffness)$")
"""The physical sliders whose ends the corpus runs: damping (0 is the undamped end), restitution (1),
stiffnesses and rigidities (the largest), wind (the largest) and masses and densities (the smallest).
Left out: sizes and counts (resolution), gravity and friction (a driving force the balance books,
a dissipation), and the drag spring's and the penalty wall's sliders, which act only with a drag or
``collision=penalty`` (off by default)."""


@dataclass(frozen=True)
class Case:
    """One run of the corpus: ``warpsim run SCENE`` with ``sets`` (``KEY=VALUE`` texts), ``fps``,
    ``substeps`` and ``integrator``, for ``frames`` frames; ``expect`` "clean" (no alarm) or
    "flagged" (stopped within ``GRACE`` frames of the growth). ``blowup``: the step as a multiple
    of the stability limit (resolved by :func:`resolve_blowup` against the built scene).
    ``attrs``: attributes set on the built scene (only where no command-line option reaches: the
    hair's explicit solver sub-steps itself inside half its limit, ``safety``)."""

    scene: str
    case: str
    frames: int
    sets: tuple = ()
    fps: Optional[float] = None
    substeps: Any = None
    integrator: Optional[str] = None
    expect: str = "clean"
    kind: str = "default"
    blowup: Optional[float] = None
    attrs: tuple = ()
    command: str = ""

    @property
    def name(self) -> str:
        """``scene/case``, the id of a test."""
        return f"{self.scene}/{self.case}"

    def argv(self, out="corpus.usda") -> list:
        """The ``warpsim`` arguments of this run (``run SCENE ...``)."""
        argv = ["run", self.scene, "--frames", str(self.frames), "--out", out, "--no-progress"]
        if self.fps is not None:
            argv += ["--fps", repr(float(self.fps))]
        if self.substeps is not None:
            argv += ["--substeps", str(self.substeps)]
        if self.integrator is not None:
            argv += ["--integrator", self.integrator]
        for item in self.sets:
            argv += ["--set", item]
        return argv

    def shell(self) -> str:
        """This run as a shell command (without ``--out``/``--no-progress``)."""
        argv = self.argv()
        i = argv.index("--out")
        del argv[i:i + 3]
        return "warpsim " + " ".join(shlex.quote(a) for a in argv)

    def sized(self, small: bool) -> "Case":
        """This case with the CPU's ``SMALL`` sizes (``small``) in place of the scene's and its own."""
        if not small or self.scene not in SMALL:
            return self
        keys = SMALL[self.scene]
        kept = tuple(s for s in self.sets if s.split("=", 1)[0] not in keys)
        return replace(self, sets=tuple(f"{k}={v}" for k, v in keys.items()) + kept)


@dataclass
class Result:
    """What a case did: frames run of frames asked, the exit ("ok", "alarm at frame N",
    "error: ..."), the largest energy gain (None: the scene has no energy balance), the message,
    and for a blow-up the growth frame of its unchecked twin."""

    case: Case
    device: str
    frames_run: int = 0
    exit: str = "ok"
    alarm_frame: Optional[int] = None
    energy_gain: Optional[float] = None
    message: str = ""
    growth: Optional[int] = None
    seconds: float = 0.0
    step: Optional[float] = None
    limit: Optional[float] = None
    warnings: list = field(default_factory=list)

    @property
    def stopped(self) -> bool:
        """Whether the run was stopped at its time budget before its last frame, without an alarm."""
        return self.exit.startswith("stopped")

    @property
    def refused(self) -> bool:
        """Whether the command refused the case before simulating (a usage mistake, exit 2: a
        slider end the scene does not take, such as the hair's stretch_rigidity=0)."""
        return self.exit.startswith("refused")

    @property
    def passed(self) -> bool:
        """Clean cases: no alarm and no error (a slider end the scene refuses, before any frame,
        is no alarm: it passes, counted apart). Blow-ups: stopped by the alarm within ``GRACE``
        frames of the unchecked twin's growth."""
        if self.refused:
            return self.case.kind == "slider"
        if self.stopped:
            return False
        if self.exit.startswith("error"):
            return False
        if self.case.expect == "clean":
            return self.alarm_frame is None
        if self.growth is None:  # the unchecked twin never grew within the frames: nothing to flag
            return self.case.kind != "blowup" or self.alarm_frame is not None
        return self.alarm_frame is not None and self.alarm_frame <= self.growth + GRACE

    @property
    def verdict(self) -> str:
        if self.refused:
            return "REFUSED" if self.passed else "FAIL (refused)"
        if self.stopped:
            return "INCOMPLETE"
        if self.passed:
            return "PASS"
        if self.exit.startswith("error"):
            return "FAIL (error)"
        return "FAIL (false alarm)" if self.case.expect == "clean" else "FAIL (missed)"

    def summary(self) -> str:
        """One line: the case, its command, what it did and the message."""
        gain = "-" if self.energy_gain is None else f"{self.energy_gain:.3g}"
        growth = "" if self.growth is None else f", growth at frame {self.growth}"
        step = "" if self.step is None or self.limit is None else \
            f", step {self.step:.4g} s = {self.step / self.limit:.3g}x the limit {self.limit:.4g} s"
        head = f"{self.case.name}: {self.verdict}: {self.exit} ({self.frames_run} of {self.case.frames} " \
               "frames, "
        return f"{head}energy gain {gain}{growth}{step})\n  {self.case.shell()}\n  {self.message}".rstrip()


# ---------------------------------------------------------------------------------------- cases
def _scenes():
    from ..scenes import scenes

    return {name: cls for name, cls in scenes().items() if cls.__module__.startswith("warpsim.")}


def default_cases(names=None) -> list:
    """Every scene at its defaults for its default length."""
    return [Case(name, "default", DEFAULT_FRAMES, kind="default") for name in _scenes()
            if not names or name in names]


def long_cases(names=None, frames=SLIDER_FRAMES) -> list:
    """Every scene at its defaults for ``frames`` (600: the issue's goal for the cloth and the drape)."""
    return [Case(name, f"default {frames} frames", frames, kind="long") for name in _scenes()
            if not names or name in names]


def _number(value) -> str:
    return f"{float(value):.6g}" if isinstance(value, float) else str(value)


def slider_ends(cls) -> list:
    """(key, value) of each end of the scene's physical sliders (``SLIDER_KEYS``), as the viewer's
    parameter panel makes them (``warpsim.viewer.params.widget_spec``): a linear slider's
    [min, max] (restitution [0, 1], damping [0, 4 x default]); a decade slider (masses,
    stiffnesses) from its lowest allowed value to the right end it opens with (the next power of
    ten above the default; a drag there widens it by a decade, not chased here). The cloth's wind
    and the donuts' restitution are number boxes from 0: their other ends are ``WIND_END`` and 1.
    Ends equal to the default are left out (the default case runs them)."""
    from ..viewer.params import widget_spec

    ends = []
    for key, param in cls.params.items():
        if not SLIDER_KEYS.match(key):
            continue
        kind, o = widget_spec(key, param)
        if kind in ("slider", "log_slider"):
            pair = (o["min"], o["max"])
        elif kind == "dt_slider":  # [ms] on the slider
            pair = (1e-3 * o["min"], 1e-3 * o["max"])
        elif key == "wind":
            pair = (0.0, WIND_END)
        elif key == "restitution":
            pair = (0.0, 1.0)
        else:
            continue
        for value in pair:
            value = type(param.default)(value) if isinstance(param.default, (int, float)) else value
            if value != param.default:
                ends.append((key, value))
    return ends


def slider_cases(names=None, frames=SLIDER_FRAMES) -> list:
    """Each slider end of each scene (:func:`slider_ends`) for ``frames`` frames."""
    out = []
    for name, cls in _scenes().items():
        if names and name not in names:
            continue
        for key, value in slider_ends(cls):
            text = f"{key}={_number(value)}"
            # a step past the stability limit (the time-step slider's right end) is to be flagged:
            # decided against the built scene (run_case)
            expect = "auto" if key == "dt" else "clean"
            out.append(Case(name, text, frames, sets=(text,), kind="slider", expect=expect))
    return out


README = Path(__file__).resolve().parents[2] / "README.md"
_RUN = re.compile(r"warpsim run [^`\n#]*")


def readme_commands(text=None) -> list:
    """The ``warpsim run`` commands of README.md (indented blocks and inline code; backslash
    continuations joined), in README order, each once."""
    if text is None:
        if not README.exists():
            return []
        text = README.read_text()
    text = re.sub(r"\\\n\s*", " ", text)
    found = []
    for match in _RUN.finditer(text):
        command = " ".join(match.group(0).split())
        if command not in found:
            found.append(command)
    return found


def _run_parser():
    from .run import add_parser

    parser = argparse.ArgumentParser(prog="warpsim")
    add_parser(parser.add_subparsers(dest="command"))
    return parser


def readme_cases(text=None, names=None) -> list:
    """A case per README ``warpsim run`` command at its README length (``--frames``, else the
    default 120), with its --fps, --substeps, --integrator and --set; options that do not change
    the simulation (--out, --flatten, --preview, --checkpoint-every) are left out, and so are the
    re-runs of a sweep's world (``--from-sweep``)."""
    parser = _run_parser()
    out = []
    for command in readme_commands(text):
        argv = shlex.split(command)[1:]
        if "--from-sweep" in argv:
            continue
        args = parser.parse_args(argv)
        if names and args.scene not in names:
            continue
        frames = DEFAULT_FRAMES if args.frames is None else args.frames
        label = " ".join(argv[2:]) or "(defaults)"
        out.append(Case(args.scene, f"README {label}", frames, sets=tuple(args.sets), fps=args.fps,
                        substeps=args.substeps, integrator=args.integrator, kind="readme", command=command))
    return out


def blowup_cases(names=None, frames=SLIDER_FRAMES, factor=BLOWUP) -> list:
    """Each explicit integrator at ``factor`` x its limit in ``BLOWUP_SCENES`` (expected: flagged), for
    ``frames`` frames (600: where damping sets the limit, explicit Euler and RK2 at 1.2x gain energy
    only after the damping's losses, RK2 in springs near frame 300)."""
    out = []
    for name, integrators in BLOWUP_SCENES.items():
        if names and name not in names or name not in _scenes():
            continue
        for integrator in integrators:
            if name == "hair":
                out.append(Case(name, f"blowup {integrator}", frames, sets=("solver=explicit",),
                                expect="flagged", kind="blowup", blowup=factor))
            else:
                out.append(Case(name, f"blowup {integrator}", frames, integrator=integrator, expect="flagged",
                                kind="blowup", blowup=factor))
    return out


ISSUE = (("springs", ("--set", "damping=0"), 600), ("springs", ("--fps", "24"), 48))
"""The issue's own reproductions that no other kind holds (``warpsim run springs --set damping=0 --frames
600``, ``warpsim run springs --frames 48 --fps 24``)."""


def issue_cases(names=None) -> list:
    """The ``ISSUE`` runs, parsed by ``warpsim run``'s parser."""
    parser = _run_parser()
    out = []
    for scene, extra, frames in ISSUE:
        if names and scene not in names:
            continue
        args = parser.parse_args(["run", scene, *extra])
        out.append(Case(scene, "issue " + " ".join(extra), frames, sets=tuple(args.sets), fps=args.fps,
                        substeps=args.substeps, kind="issue"))
    return out


KINDS = ("default", "long", "slider", "readme", "issue", "blowup")
"""The kinds of case, in the corpus's order."""


def cases(names=None, kinds=KINDS, slider_frames=SLIDER_FRAMES) -> list:
    """The corpus (``names``: only these scenes; ``kinds``: of these kinds; ``slider_frames``: the
    length of the slider ends and the long defaults)."""
    out = []
    if "default" in kinds:
        out += default_cases(names)
    if "long" in kinds:
        out += long_cases(names, slider_frames)
    if "slider" in kinds:
        out += slider_cases(names, slider_frames)
    if "readme" in kinds:
        out += readme_cases(names=names)
    if "issue" in kinds:
        out += issue_cases(names)
    if "blowup" in kinds:
        out += blowup_cases(names)
    return out


# ---------------------------------------------------------------------------------------- runs
def _limit_of(scene) -> Optional[float]:
    if hasattr(scene, "stable_dt") and getattr(scene, "implicit", True) is False:
        return float(scene.stable_dt)  # the hair's explicit strands: their measured limit
    limit = scene.stability()
    return None if limit is None else float(limit.dt)


def resolve_blowup(case: Case, device) -> Case:
    """The blow-up ``case`` with the flags that put its step at ``case.blowup`` x the stability
    limit of the scene it builds (its own sizes), frames about as far apart as the scene's own:
    ``--fps F --substeps N`` with N steps a frame (the cloth: N x its explicit_substeps), so the
    step 1 / (F x N) is the factor times the limit (a scene with a ``dt`` parameter takes it as
    its dt). The hair sub-steps itself inside ``safety`` (0.5) x its measured limit whatever the
    flags: its ``safety`` is set to the factor (no command-line option reaches it), N strand
    steps a frame."""
    if case.blowup is None:
        return case
    from ..cli_common import parse_sets
    from ..scenes import get_scene, resolve_timing

    cls = get_scene(case.scene)
    params = cls.resolve_params(parse_sets(cls, list(case.sets), case.integrator))
    probe = cls(params, device=device)
    limit = _limit_of(probe)
    if limit is None or not math.isfinite(limit) or limit <= 0.0:
        raise ValueError(f"{case.name}: no finite stability limit to exceed ({limit})")
    h = case.blowup * limit
    per = int(getattr(probe, "steps_per_substep", 1))  # the cloth's explicit_substeps a sub-step
    frame_dt = resolve_timing(cls, params).frame_dt  # the scene's own frame
    steps = max(1, round(frame_dt / (per * h)))
    fps = 1.0 / (steps * per * h)
    if case.scene == "hair":
        return replace(case, fps=fps, substeps=1, attrs=(("safety", case.blowup),))
    return replace(case, fps=fps, substeps=steps)


def _mechanical_energy(sim) -> tuple:
    """(K + U of the springs (the model's) + U of gravity, K + U of the springs) [J] of a
    simulator's state, on the host in float64: the twin's own measure, apart from the balance's."""
    m = sim.model
    x = sim.state.positions.numpy().astype(np.float64)
    v = sim.state.velocities.numpy().astype(np.float64)
    mass = m.particle_mass.numpy().astype(np.float64)
    moving = 0.5 * float((mass * (v * v).sum(axis=1)).sum())
    gravity = 0.0
    for f in sim.forces:
        g = getattr(f, "g", None)
        if g is not None and type(f).__name__ == "Gravity":
            gravity -= float((mass * (x @ np.asarray(g, np.float64).reshape(3))).sum())
    if getattr(m, "spring_count", 0):
        ij = m.spring_indices.numpy().reshape(-1, 2)
        k = m.spring_stiffness.numpy().astype(np.float64)
        rest = m.spring_rest_length.numpy().astype(np.float64)
        stretch = np.linalg.norm(x[ij[:, 0]] - x[ij[:, 1]], axis=1) - rest
        moving += 0.5 * float((k * stretch * stretch).sum())
    return moving + gravity, moving


def _unchecked(case: Case, device):
    scene, timing = _build(case, device, None)[:2]
    scene.sim.check_every = 0  # no speed bound, no energy balance: it runs on as the physics goes
    scene.sim.max_speed = float("inf")
    for key, value in case.attrs:
        setattr(scene, key, value)
    return scene, timing


def growth_frame(case: Case, device, frames=None, rise=0.01) -> Optional[int]:
    """The first frame at which an unchecked twin of the (resolved) blow-up ``case`` holds more
    energy than the same scene stepped inside its limit: its mechanical energy
    (:func:`_mechanical_energy`, not the balance's) above the reference's by more than ``rise`` of
    the scale (the most kinetic plus spring energy held at frame 0 or by the reference since: the
    energy in motion, as the balance's budget; not |E|, whose gravity term depends on where y = 0
    is), or non-finite. The reference is the case with ``--substeps auto`` (steps within half the
    limit at the same frame rate; the hair at its own ``safety``), also unchecked, so damping and
    contacts take the same energy from both. The twin must also hold that much more than its own
    frame 0 (energy from nowhere, what the balance judges): where damping takes more than the unstable
    mode adds (RK2 and explicit Euler at 1.2x a limit that damping sets) the run has not yet gained
    energy, however far it has left the reference. None when the twin never grew within ``frames``."""
    twin, timing = _unchecked(case, device)
    if case.scene == "hair":
        ref, ref_timing = _unchecked(replace(case, attrs=()), device)
    else:
        ref, ref_timing = _unchecked(replace(case, substeps="auto"), device)
    e0, scale = _mechanical_energy(twin.sim)  # scale: the energy in motion (kinetic + spring), as the balance's
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for frame in range(1, (frames or case.frames) + 1):
            try:
                twin.advance(timing.frame_dt, timing.steps)
            except Exception:  # noqa: BLE001  (a twin that failed has blown up)
                return frame
            try:
                ref.advance(ref_timing.frame_dt, ref_timing.steps)
            except Exception:  # noqa: BLE001  (the reference failed: no measure from here on)
                return None
            e, _ = _mechanical_energy(twin.sim)
            e_ref, moving_ref = _mechanical_energy(ref.sim)
            if not math.isfinite(e):
                return frame
            scale = max(scale, moving_ref)
            if e - max(e_ref, e0) > rise * max(scale, 1e-12):
                return frame
    return None


def _build(case: Case, device, err):
    """(scene, timing, args) of ``case`` built as ``warpsim run`` builds it."""
    from ..cli_common import UsageError, parse_sets, stability_check, timing_from_flags, timing_note
    from ..scenes import get_scene

    args = _run_parser().parse_args(case.argv())
    cls = get_scene(args.scene)
    given = parse_sets(cls, args.sets, args.integrator)
    params = cls.resolve_params(given)
    timing, params = timing_from_flags(cls, params, given, args.fps, args.substeps)
    if err is not None:
        timing_note(timing, False, err)
    try:  # as warpsim run builds it (commands.run._built_scene)
        scene = cls(params, device=str(device))
    except ValueError as exc:
        raise UsageError(f"scene {cls.name!r}: {exc}") from None
    scene.use_timing(timing)
    if err is not None:
        stability_check(scene, timing.frame_dt, timing.steps, False, err)
    return scene, timing, args


class _Sink:
    """A stand-in for the cache writer: takes every declaration (``scene.declare``) and keeps
    nothing, so ``frame_data()`` returns what the writer would write."""

    def __getattr__(self, name):
        return lambda *args, **kwargs: _Sink()


def _gain(scene) -> Optional[float]:
    sim = getattr(scene, "sim", None)
    gain = getattr(sim, "energy_gain", None)
    return None if gain is None else float(gain)


def run_case(case: Case, device="cpu", small=False, twin=True, seconds=None) -> Result:
    """Run ``case`` (sized by ``small``; a blow-up resolved against its built scene) as ``warpsim
    run`` does and return its :class:`Result`. ``twin``: for a blow-up also run the unchecked twin
    for its growth frame. ``seconds``: stop after the frame that passes this wall time (the result
    is then "stopped", neither passed nor failed: its frames run say how far it got)."""
    import io

    from ..cli_common import UsageError
    from ..core.errors import SimulationError
    from ..core.stability import StabilityWarning

    t0 = time.perf_counter()
    case = case.sized(small)
    result = Result(case, str(device))
    err = io.StringIO()
    try:
        case = resolve_blowup(case, device)
        result.case = case
        scene, timing, _ = _build(case, device, err)
    except UsageError as exc:  # the command's exit 2, before any frame
        result.exit, result.message = "refused", " ".join(str(exc).split())
        result.seconds = time.perf_counter() - t0
        return result
    except Exception as exc:  # noqa: BLE001
        result.exit, result.message = f"error: {type(exc).__name__}", " ".join(str(exc).split())
        result.seconds = time.perf_counter() - t0
        return result
    scene.declare(_Sink())
    for key, value in case.attrs:
        setattr(scene, key, value)
    sim: Any = getattr(scene, "sim", None)
    if case.attrs and hasattr(scene, "strand_steps") and sim is not None and sim.check_every:
        sim.check_every = scene.strand_steps(timing.frame_dt)  # the check once a frame, as built
    result.warnings = [line for line in err.getvalue().splitlines() if line.strip()]
    if case.blowup is not None or case.expect == "auto":
        result.limit = _limit_of(scene)
        result.step = timing.frame_dt / scene.frame_steps(timing.frame_dt, timing.steps)
    if case.expect == "auto":  # a time step past the limit is to be flagged (after the twin's growth)
        past = result.limit is not None and result.step is not None and result.step > result.limit
        case = replace(case, expect="flagged" if past else "clean")
        result.case = case
    frame = 0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", StabilityWarning)  # said once above, as one line (warpsim run)
        try:
            scene.frame_data()
            for frame in range(1, case.frames + 1):
                scene.advance(timing.frame_dt, timing.steps)
                scene.frame_data()
                result.frames_run = frame
                gain = _gain(scene)
                if gain is not None:
                    result.energy_gain = max(result.energy_gain or 0.0, gain)
                if seconds is not None and frame < case.frames and time.perf_counter() - t0 > seconds:
                    result.exit = f"stopped at {seconds:g} s"
                    break
        except SimulationError as exc:
            result.alarm_frame = frame
            result.message = " ".join(str(exc).split())
            figure = re.search(r"grew (?:by|to) ([0-9.eE+-]+)x", result.message)
            result.exit = f"alarm at frame {frame}" + (f" ({figure.group(0)})" if figure else "")
            gain = _gain(scene)
            if gain is not None:
                result.energy_gain = max(result.energy_gain or 0.0, gain)
        except Exception as exc:  # noqa: BLE001
            result.exit = f"error at frame {frame}: {type(exc).__name__}"
            result.message = " ".join(str(exc).split())
    if case.expect == "flagged" and twin and not result.stopped:
        result.growth = growth_frame(case, device, frames=case.frames)
    result.seconds = time.perf_counter() - t0
    return result


def format_table(results) -> str:
    """The results as a fixed-width table, one row a case."""
    head = ("scene", "case", "device", "frames", "exit", "energy_gain", "expected", "result", "s")
    rows = [head]
    for r in results:
        gain = "" if r.energy_gain is None else f"{r.energy_gain:.3g}"
        exit_ = r.exit + ("" if r.growth is None else f" (growth {r.growth})")
        rows.append((r.case.scene, r.case.case, r.device, f"{r.frames_run}/{r.case.frames}", exit_, gain,
                     r.case.expect if r.case.expect == "clean" else "flagged", r.verdict, f"{r.seconds:.1f}"))
    widths = [max(len(str(row[i])) for row in rows) for i in range(len(head))]
    return "\n".join("  ".join(str(c).ljust(w) for c, w in zip(row, widths)).rstrip() for row in rows)


def environment_note() -> str:  # pragma: no cover - a line for the benchmark's header
    import platform

    import warp as wp

    return f"warp {wp.config.version}, Python {platform.python_version()}, {os.cpu_count()} CPUs"
