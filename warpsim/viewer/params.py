"""The parameter panel: one GUI input per registered scene parameter (viser front end).

:func:`widget_spec` (pure) chooses the input for a parameter: a dropdown for choices, a
checkbox for a bool, three numbers for a 3-vector, a slider with a sensible range for a number
(restitution-like coefficients in [0, 1], else [0, 4 x default], or symmetric for a negative
default), a decade slider for mass-like numbers (masses, stiffnesses, densities: the slider and
its number box hold the physical value, and after each change its range is fitted to the value,
from the lowest allowed value (1/1000 of the default's decade) to the next power of ten above the
value, so dragging to the right end reaches the next decade and 0.001 kg is a few drags, or one
typed value, from 1 kg), a slider in milliseconds for the time step ``dt`` (with the stability limit
marked on it and shown beside it, values past it flagged), a number box for zero defaults, a text
box for free text. Labels carry the unit the parameter's help names (``stiffness [N/m]``), and the
hover text speaks the slider's unit (``dt``: [ms]).
:func:`build_param_panel` adds the inputs; a change goes to ``Session.set_param`` and the panel
says whether it applied live or rebuilt the scene. :func:`sync_param_handles` shows the values the
session runs with (after a Reset restored the last stable ones, in every open tab and new ones).
"""
from __future__ import annotations

import math
import re
import time

__all__ = ["build_param_panel", "clamp_echo", "dt_limit_text", "format_param", "hint_for", "label_for", "log_window", "refresh_dt_limit",
           "sync_param_handles", "widget_spec"]

UNIT_KEYS = ("restitution", "friction", "tilt_fraction", "opacity")
LOG_KEYS = ("mass", "stiffness", "density")
"""Parameters (by substring) that span decades: a log10 slider."""
_UNIT = re.compile(r"\[([^\]]+)\]")
SLIDERS = ("slider", "log_slider", "dt_slider")
CLAMP_ECHO_SECONDS = 2.0
"""A slider's number box clamps a value typed past its range to the range's end when the box is
left: the range is widened to the typed value at once, and such an end arriving within this time
after the typed value was applied (the handler's end: a rebuild may take seconds, the clamp waits
behind it) is ignored (the value typed is the value run and shown)."""


def label_for(key, param, live=False):
    """The input's label: the key, its unit from the help text (``[N/m]``; ``dt`` in [ms], as its
    slider), and ``(live)`` for parameters applied to the running simulation."""
    unit = "ms" if key == "dt" else None
    if unit is None and isinstance(param.default, (int, float, tuple, list)) and not isinstance(param.default, bool):
        units = [u for u in _UNIT.findall(param.help or "") if "," not in u]  # "[0, 1]" is a range
        unit = units[0] if units else None
    return key + (f" [{unit}]" if unit else "") + (" (live)" if live else "")


def format_param(key, param, value):
    """``value`` as the panel shows it, with the unit of its label: ``dt`` in ms as its slider
    (``dt = 1.667 ms``), ``mass = 1 kg``; the same words in every message that names a value."""
    unit = _UNIT.search(label_for(key, param))
    unit = f" {unit.group(1)}" if unit else ""
    if key == "dt" and isinstance(value, (int, float)):
        return f"{key} = {1e3 * float(value):.4g}{unit}"
    if isinstance(value, bool) or not isinstance(value, (int, float, tuple, list)):
        return f"{key} = {value}"
    if isinstance(value, (tuple, list)):
        return f"{key} = ({', '.join(f'{float(v):.4g}' for v in value)}){unit}"
    return f"{key} = {value:.6g}{unit}"


def hint_for(key, param):
    """The input's hover text: the parameter's help, with the time step's unit as its slider's
    ([ms], not the [s] of ``dt``'s help, which the command line's --set uses)."""
    hint = param.help or None
    if key == "dt" and hint:
        hint = hint.replace("[s]", "[ms]") if "[s]" in hint else hint + " [ms]"
    return hint


def log_window(value, lo, hi):
    """(min, max) of a decade slider showing ``value``: from ``lo`` (the lowest allowed value) to
    the power of ten above ``value`` (the value sits in the top 90 % of the track; the right end
    is the next decade), never past ``hi``."""
    import math

    if not (isinstance(value, (int, float)) and value > 0.0 and math.isfinite(value)):
        return lo, hi
    top = 10.0 ** (math.floor(math.log10(value)) + 1)
    return lo, float(f"{min(max(top, 10.0 * lo), hi):.6g}")


def dt_limit_text(info):
    """Markdown beside the time-step slider from ``Session.stability()``."""
    limit = info["limit"]
    if limit is None:
        return "stability limit: not estimated for this scene"
    if not math.isfinite(limit):
        return "stability limit: none (every step is stable with this integrator)"
    if limit <= 0.0:
        return f"**no stable step** with this integrator: {info['reason']}"
    text = f"stable up to **{1e3 * limit:.3g} ms** ({info['who']})"
    if info["auto"]:
        text += f"; auto sub-steps of {1e3 * info['step']:.3g} ms"
    if info["exceeded"] or (not info["auto"] and info["dt_exceeded"]):
        text += f"  \n**past the limit**: a {1e3 * info['step']:.3g} ms step will blow up"
    return text


def _nice_step(span):
    import math

    if span <= 0:
        return 0.01
    return 10.0 ** math.floor(math.log10(span / 100.0))


def widget_spec(key, param):
    """(kind, options) of the input for ``param``: kind in dropdown, checkbox, vector3, slider,
    number, text; options hold min/max/step/initial/choices as the kind needs."""
    d = param.default
    if param.choices is not None:
        return "dropdown", {"options": [str(c) for c in param.choices], "initial": str(d)}
    if isinstance(d, bool):
        return "checkbox", {"initial": d}
    if isinstance(d, (tuple, list)):
        if len(d) == 3:
            return "vector3", {"initial": tuple(float(v) for v in d)}
        return "text", {"initial": ",".join(f"{v:g}" for v in d)}
    if isinstance(d, int):
        if d > 0:
            return "slider", {"min": 1 if d >= 1 else 0, "max": max(4 * d, d + 4), "step": 1, "initial": d}
        return "number", {"initial": d, "step": 1}
    if isinstance(d, float):
        if key == "dt" and d > 0.0:  # a slider in ms, from a tenth of the default to 4x
            hi = 4.0 * d * 1e3
            return "dt_slider", {"min": 0.1 * d * 1e3, "max": hi, "step": _nice_step(hi) / 10.0, "initial": d * 1e3}
        if key == "dt" or d == 0.0:
            return "number", {"initial": d, "step": _nice_step(abs(d)) if d else 0.01}
        if any(k in key for k in UNIT_KEYS) and 0.0 <= d <= 1.0:
            return "slider", {"min": 0.0, "max": 1.0, "step": 0.01, "initial": d}
        if any(k in key for k in LOG_KEYS) and d > 0.0:
            import math

            decade = math.floor(math.log10(d))
            lo, hi = 10.0 ** (decade - 3), 10.0 ** (decade + 4)
            if param.lowest is not None:  # the scene's model stops holding below it
                lo = max(lo, float(param.lowest))
            lo_w, hi_w = log_window(d, lo, hi)
            return "log_slider", {"min": lo_w, "max": hi_w, "step": float(f"{lo / 100.0:.1g}"), "initial": d,
                                  "lo": lo, "hi": hi}
        lo, hi = (0.0, 4.0 * d) if d > 0 else (4.0 * d, -4.0 * d)
        return "slider", {"min": lo, "max": hi, "step": _nice_step(hi - lo), "initial": d}
    return "text", {"initial": str(d)}


def build_param_panel(gui, session, on_result):
    """Add one input per parameter of ``session``'s scene to ``gui`` (a viser GUI API, inside
    the caller's folder). ``on_result(key, outcome or error text, ok)`` reports each change.
    Returns {key: handle}."""
    cls = session.cls
    live = set(getattr(cls, "live_params", ()))
    gui.add_markdown("Live: " + (", ".join(sorted(live)) if live else "none") +
                     ". Other changes rebuild the scene.")
    handles = {}
    typed = {}  # key -> (value typed in the slider's unit, the (min, max) it arrived in, when [s])
    for key, param in cls.params.items():
        kind, o = widget_spec(key, param)
        label = label_for(key, param, key in live)
        value = session.params[key]
        hint = hint_for(key, param)
        if kind == "dt_slider":
            info = session.stability()
            marks = _dt_marks(info, o)
            v = min(max(1e3 * value, o["min"]), o["max"])
            h = gui.add_slider(label, o["min"], o["max"], o["step"], v, marks=marks, hint=hint)
            handles["_dt_limit"] = gui.add_markdown(dt_limit_text(info))
        elif kind == "dropdown":
            h = gui.add_dropdown(label, o["options"], initial_value=str(value), hint=hint)
        elif kind == "checkbox":
            h = gui.add_checkbox(label, bool(value), hint=hint)
        elif kind == "vector3":
            h = gui.add_vector3(label, tuple(float(v) for v in value), hint=hint)
        elif kind == "slider":
            lo, hi = o["min"], o["max"]
            v = min(max(value, lo), hi) if isinstance(value, (int, float)) else o["initial"]
            h = gui.add_slider(label, lo, hi, o["step"], v, hint=hint)
        elif kind == "log_slider":  # the slider and its box hold the value; the range follows it
            v = float(value) if isinstance(value, (int, float)) and value > 0 else o["initial"]
            lo, hi = log_window(v, o["lo"], o["hi"])
            h = gui.add_slider(label, lo, hi, o["step"], min(max(v, lo), hi),
                               hint=(hint or key) + " (the range follows the value: drag to the right end "
                                                    "for the next power of ten, or type a value)")
        elif kind == "number":
            h = gui.add_number(label, value, step=o["step"], hint=hint)
        else:
            h = gui.add_text(label, ",".join(f"{v:g}" for v in value) if isinstance(value, tuple) else str(value),
                             hint=hint)
        handles[key] = h
        handles.setdefault("_kinds", {})[key] = (kind, o.get("lo"), o.get("hi"))  # for sync_param_handles

        bounds = (o.get("lo"), o.get("hi"))  # a decade slider's allowed values

        def changed(event, key=key, h=h, kind=kind, bounds=bounds):
            if getattr(event, "client", True) is None:
                return  # the server set the input (sync_param_handles): nothing changed by the user
            shown = h.value
            if kind in SLIDERS:
                now = time.monotonic()
                if clamp_echo(typed.get(key), shown, now):  # the box's clamp to the range it knew
                    h.value = typed[key][0]  # shown again as typed (the server's setting: no change)
                    return
                typed[key] = (shown, (h.min, h.max), now)
            value = shown * 1e-3 if kind == "dt_slider" else shown
            if kind == "log_slider":
                value = float(f"{float(value):.6g}")  # the box's typed value, without float noise
                _fit_log_range(h, value, *bounds)  # at once: the page knows the new range before its blur
            elif kind in SLIDERS:
                _widen(h, shown)
            try:
                outcome = session.set_param(key, value)
            except ValueError as exc:
                sync_param_handles(handles, session, keys=(key,))  # the value it still runs with
                on_result(key, str(exc), False)
                return
            finally:
                if kind in SLIDERS:  # the box's clamp is queued behind this handler (a rebuild can take
                    typed[key] = typed[key][:2] + (time.monotonic(),)  # seconds): its window starts now
            on_result(key, outcome, True)

        h.on_update(changed)
    return handles


def clamp_echo(last, value, now):
    """Whether a slider's new ``value`` is its number box clamping the value typed before it to
    the range the page knew (on leaving the box), not a change: ``last`` = (typed value, (min,
    max) when it arrived, time [s]) of the slider's last change; ``now`` [s]."""
    if last is None or now - last[2] > CLAMP_ECHO_SECONDS:
        return False
    typed, (lo, hi) = last[0], last[1]
    return (typed > hi and value == hi) or (typed < lo and value == lo)


def _widen(h, value):
    """A slider's range grown to hold a typed ``value`` (in the slider's unit)."""
    if value > h.max:
        h.max = value
    elif value < h.min:
        h.min = value


def _fit_log_range(h, value, lo, hi):
    """Fit a decade slider's range to ``value`` (see :func:`log_window`)."""
    lo_w, hi_w = log_window(value, lo, hi)
    if (h.min, h.max) != (lo_w, hi_w):
        h.max = max(hi_w, h.min)  # widen first, so the value stays inside while the range moves
        h.min = lo_w
        h.max = hi_w


def sync_param_handles(handles, session, keys=None):
    """Show in every input (those of ``keys``: None, all) the value the session runs with (after a
    Reset restored the last stable parameters; viser sends it to every open tab and to tabs opened
    later). Setting an input from here does not count as a change (see ``changed`` in
    :func:`build_param_panel`)."""
    for key, (kind, lo, hi) in handles.get("_kinds", {}).items():
        if keys is not None and key not in keys:
            continue
        h, value = handles[key], session.params.get(key)
        if value is None:
            continue
        try:
            if kind == "dt_slider":
                shown = min(max(1e3 * float(value), h.min), h.max)
            elif kind == "log_slider":
                _fit_log_range(h, float(value), lo, hi)
                shown = min(max(float(value), h.min), h.max)
            elif kind == "slider":
                shown = min(max(value, h.min), h.max)
            elif kind == "dropdown":
                shown = str(value)
            elif kind == "vector3":
                shown = tuple(float(v) for v in value)
            elif kind == "text":
                shown = ",".join(f"{v:g}" for v in value) if isinstance(value, tuple) else str(value)
            else:
                shown = value
            if h.value != shown:
                h.value = shown
        except (TypeError, ValueError):  # an input the value does not fit: left as it is
            continue


def _dt_marks(info, o):
    limit = info["limit"]
    if limit is None or not math.isfinite(limit) or not o["min"] <= 1e3 * limit <= o["max"]:
        return None
    return ((1e3 * limit, "limit"),)


def refresh_dt_limit(handles, session):
    """Update the limit text (and the slider's mark) after a parameter change or a rebuild."""
    text = handles.get("_dt_limit")
    if text is None:
        return
    info = session.stability()
    content = dt_limit_text(info)
    if text.content != content:  # (the dt slider's mark stays where it was drawn: viser has no public way
        text.content = content   # to move a mark, and this text gives the limit as it is now)
