"""The parameter panel: one GUI input per registered scene parameter (viser front end).

:func:`widget_spec` (pure) chooses the input for a parameter: a dropdown for choices, a
checkbox for a bool, three numbers for a 3-vector, a slider with a sensible range for a number
(restitution-like coefficients in [0, 1], else [0, 4 x default], or symmetric for a negative
default), a logarithmic slider for mass-like numbers (masses, stiffnesses, densities: the slider
moves the power of ten, from 1/1000 of the default's decade to 1000 times it, so 0.001 kg is
reachable from 1 kg), a slider in milliseconds for the time step ``dt`` (with the stability limit
marked on it and shown beside it, values past it flagged), a number box for zero defaults, a text
box for free text. Labels carry the unit the parameter's help names (``stiffness [N/m]``).
:func:`build_param_panel` adds the inputs; a change goes to ``Session.set_param`` and the panel
says whether it applied live or rebuilt the scene.
"""
from __future__ import annotations

import math
import re

__all__ = ["build_param_panel", "dt_limit_text", "label_for", "refresh_dt_limit", "widget_spec"]

UNIT_KEYS = ("restitution", "friction", "tilt_fraction", "opacity")
LOG_KEYS = ("mass", "stiffness", "density")
"""Parameters (by substring) that span decades: a log10 slider."""
_UNIT = re.compile(r"\[([^\]]+)\]")


def label_for(key, param, live=False):
    """The input's label: the key, its unit from the help text (``[N/m]``; ``dt`` in [ms], as its
    slider), and ``(live)`` for parameters applied to the running simulation."""
    unit = "ms" if key == "dt" else None
    if unit is None and isinstance(param.default, (int, float, tuple, list)) and not isinstance(param.default, bool):
        units = [u for u in _UNIT.findall(param.help or "") if "," not in u]  # "[0, 1]" is a range
        unit = units[0] if units else None
    return key + (f" [{unit}]" if unit else "") + (" (live)" if live else "")


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
            return "log_slider", {"min": float(decade - 3), "max": float(decade + 3), "step": 0.01,
                                  "initial": math.log10(d)}
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
    for key, param in cls.params.items():
        kind, o = widget_spec(key, param)
        label = label_for(key, param, key in live)
        value = session.params[key]
        hint = param.help or None
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
        elif kind == "log_slider":  # the slider holds log10(value); the label shows the value
            import math

            exp = math.log10(value) if isinstance(value, (int, float)) and value > 0 else o["initial"]
            h = gui.add_slider(f"{label} = {10.0 ** exp:.3g}", o["min"], o["max"], o["step"],
                               min(max(exp, o["min"]), o["max"]), hint=(hint or key) + " (logarithmic slider)")
        elif kind == "number":
            h = gui.add_number(label, value, step=o["step"], hint=hint)
        else:
            h = gui.add_text(label, ",".join(f"{v:g}" for v in value) if isinstance(value, tuple) else str(value),
                             hint=hint)
        handles[key] = h

        def changed(event, key=key, h=h, scale=1e-3 if kind == "dt_slider" else None, log=kind == "log_slider",
                    label=label):
            value = h.value * scale if scale else h.value
            if log:
                value = float(f"{10.0 ** float(value):.6g}")  # 10^-3 is 0.001, not 0.0010000000000000002
                h.label = f"{label} = {value:.3g}"
            try:
                outcome = session.set_param(key, value)
            except ValueError as exc:
                on_result(key, str(exc), False)
                return
            on_result(key, outcome, True)

        h.on_update(changed)
    return handles


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
    if text.content != content:
        text.content = content
        slider = handles.get("dt")
        if slider is not None:
            try:  # viser keeps the marks in a private prop; the text above says it either way
                from viser._gui_api import _build_slider_marks

                o = {"min": slider.min, "max": slider.max}
                slider._marks = _build_slider_marks(_dt_marks(info, o))
            except (ImportError, AttributeError):
                pass
