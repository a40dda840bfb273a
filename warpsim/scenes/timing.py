"""How a scene's frames are timed: one :class:`FrameTiming`, resolved once by :func:`resolve_timing`
from the scene class, its parameters and the options (``--fps``, ``--substeps``), and used alike by
``warpsim run``, ``view``, ``sweep``, the re-run of one world and the API (a scene receives it with
``Scene.use_timing``).

The rules (``warpsim run --help`` says the same):

- A scene without a ``dt`` parameter: frames are ``1 / fps`` apart (``--fps`` or the scene's
  ``fps``), ``substeps`` steps each (``--substeps N`` or the scene's ``substeps``).
- A scene with a ``dt`` parameter (bounce, teapot, ...): ``dt`` is the step and its frames are
  ``dt x`` the scene's own ``substeps`` apart (25 fps for bounce, 60 for teapot); ``--set dt=X``
  changes the step and the frame with it. ``--fps F`` sets the frame, and dt becomes
  ``1 / (F x steps)``. ``--substeps N`` means N steps a frame at the scene's frame rate: the
  step becomes ``frame_dt / N`` and overrides dt (a one-line note, ``warpsim: warning``, that
  ``--strict`` turns into a refusal) unless N is the scene's own count. ``--set dt`` with
  ``--fps`` and/or ``--substeps`` must agree (``dt x N x fps == 1``) or the request is refused.
- ``--substeps auto`` (and the default of scenes with ``substeps_auto``, unless dt is set by
  hand): at least the scene's own count of steps a frame, and as many as keep each step within
  ``AUTO_SAFETY`` (0.5) x the stability limit; the count is resolved against the built scene
  (a batch of worlds: each world its own count, the one its own run takes).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

__all__ = ["CHOSEN", "FrameTiming", "resolve_timing"]

CHOSEN = ("default", "by hand", "auto")
"""How a timing was chosen: the scene's defaults, options given by hand, or automatic steps."""


@dataclass(frozen=True)
class FrameTiming:
    """When frames are and how they are stepped.

    Attributes:
        fps: frames per second of the output [1/s].
        frame_dt: simulated time between two frames [s].
        steps: steps per frame (``chosen == "auto"`` and not ``fixed``: the fewest; the scene's
            stability limit may ask for more).
        step_dt: the step [s], ``frame_dt / steps``.
        chosen: "default", "by hand" or "auto".
        fixed: whether ``steps`` is final (False only for automatic steps not yet resolved
            against a scene's limit).
        note: a line to show before running ("" when none): ``--substeps N`` overriding dt.
    """

    fps: float
    frame_dt: float
    steps: int
    step_dt: float
    chosen: str = "default"
    fixed: bool = True
    note: str = ""

    def __post_init__(self):
        if self.chosen not in CHOSEN:
            raise ValueError(f"FrameTiming chosen={self.chosen!r}: give one of {', '.join(CHOSEN)}")
        if not (isinstance(self.steps, int) and self.steps >= 1):
            raise ValueError(f"FrameTiming steps={self.steps!r}: give a whole number >= 1")
        if not (math.isfinite(self.frame_dt) and self.frame_dt > 0):
            raise ValueError(f"FrameTiming frame_dt={self.frame_dt!r}: it must be > 0 [s]")

    @property
    def auto(self) -> bool:
        """Whether the steps per frame follow the stability limit."""
        return self.chosen == "auto"

    def with_steps(self, steps: int) -> "FrameTiming":
        """This timing with ``steps`` steps a frame, final (an automatic count resolved)."""
        steps = int(steps)
        return replace(self, steps=steps, step_dt=self.frame_dt / steps, fixed=True)

    def scene_params(self, params: dict) -> dict:
        """``params`` with a ``dt`` parameter set to the step taken (the fewest steps' step for
        automatic timing), so a scene that reads dt sees the step it is run with."""
        step = self.frame_dt / self.steps
        if "dt" not in params or math.isclose(float(params["dt"]), step, rel_tol=1e-12):
            return dict(params)  # the scene's own dt, bit for bit
        return {**params, "dt": step}


def _whole(substeps):
    if isinstance(substeps, bool) or not isinstance(substeps, int) and not (
            isinstance(substeps, float) and substeps.is_integer()):
        raise ValueError(f"--substeps {substeps!r}: give a whole number >= 1 or 'auto'")
    if int(substeps) < 1:
        raise ValueError(f"--substeps {substeps}: it must be >= 1")
    return int(substeps)


def _rate(frame_dt):
    return float(f"{1.0 / frame_dt:.12g}")  # 1 / (0.04 * 1) -> 25, not 25.000000000000004


def resolve_timing(cls, params, *, fps=None, substeps=None, given=()) -> FrameTiming:
    """The :class:`FrameTiming` of scene class ``cls`` with resolved ``params`` (see the module's
    rules). ``fps``: frames per second or None (the scene's); ``substeps``: steps a frame (int),
    ``"auto"`` or None (the scene's); ``given``: the parameter keys set by hand (``--set``; a
    ``dt`` among them is the user's step). ValueError (one line, naming the option and a fix) for
    a bad fps or count, a dt <= 0, or dt, fps and steps that disagree."""
    if substeps is not None and not (isinstance(substeps, str) and substeps.strip().lower() == "auto"):
        substeps = _whole(substeps)
    elif substeps is not None:
        substeps = "auto"
    if fps is not None:
        try:
            fps = float(fps)
        except (TypeError, ValueError):
            raise ValueError(f"--fps {fps!r}: give frames per second > 0") from None
        if not (math.isfinite(fps) and fps > 0):
            raise ValueError(f"--fps {fps:g}: it must be > 0")
    own = int(cls.substeps)
    dt_by_hand = "dt" in given
    auto = substeps == "auto" or (substeps is None and bool(getattr(cls, "substeps_auto", False)) and not dt_by_hand)
    steps = own if substeps in (None, "auto") else substeps
    chosen = "auto" if auto else ("by hand" if fps is not None or substeps is not None or
                                  (dt_by_hand and "dt" in cls.params) else "default")
    note = ""
    if "dt" not in cls.params:
        frame_dt = 1.0 / (fps if fps is not None else float(cls.fps))
        return FrameTiming(fps=fps if fps is not None else float(cls.fps), frame_dt=frame_dt, steps=steps,
                           step_dt=frame_dt / steps, chosen=chosen, fixed=not auto)
    dt = float(params.get("dt", cls.params["dt"].default))
    if not dt > 0:
        raise ValueError(f"dt={dt:g}: it must be > 0 [s]; e.g. --set dt={cls.params['dt'].default:g}")
    if fps is not None:
        step = 1.0 / (fps * steps)
        if dt_by_hand and not math.isclose(step, dt, rel_tol=1e-9):
            raise ValueError(f"--fps {fps:g} with {steps} steps a frame means dt = {step:g} s, but --set dt={dt:g}; "
                             "give one of them")
        frame_dt = step * steps
    elif dt_by_hand and steps != own:
        raise ValueError(f"--set dt={dt:g} with --substeps {steps}: frames are dt x {own} (the scene's steps) = "
                         f"{dt * own:g} s apart, so {steps} steps would not be dt; give --fps {1.0 / (dt * steps):g} "
                         f"as well (frames dt x {steps} apart), or leave out one of --set dt and --substeps")
    else:
        frame_dt = dt * own  # the scene's frame: its dt times its own steps
        if steps != own:
            note = (f"--substeps {steps} keeps the scene's {_rate(frame_dt):g} fps: {steps} step"
                    f"{'s' if steps > 1 else ''} of {frame_dt / steps:.4g} s a frame instead of the scene's "
                    f"dt = {dt:.4g} s ({own} a frame); give --fps {_rate(frame_dt):g} too to set both by hand")
    return FrameTiming(fps=_rate(frame_dt), frame_dt=frame_dt, steps=steps, step_dt=frame_dt / steps,
                       chosen=chosen, fixed=not auto, note=note)
