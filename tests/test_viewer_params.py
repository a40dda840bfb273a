"""The viewer's parameter panel: mass-like parameters get a logarithmic slider reaching a
thousandth of their default's decade (0.001 kg from 1 kg), and moving it sets the scene parameter
to the power of ten the slider shows. Driven through a stand-in for viser's GUI API."""

import math

import pytest

from warpsim.scenes import Param, get_scene
from warpsim.viewer.params import build_param_panel, widget_spec


def test_mass_like_params_get_log_sliders():
    kind, o = widget_spec("mass", Param(1.0))
    assert kind == "log_slider" and o["min"] <= math.log10(0.001) and o["max"] >= math.log10(100.0)
    assert o["initial"] == pytest.approx(0.0)
    kind, o = widget_spec("stiffness", Param(40.0))
    assert kind == "log_slider" and 10.0 ** o["min"] <= 0.04 and 10.0 ** o["max"] >= 4000.0
    assert widget_spec("restitution", Param(0.5))[0] == "slider"  # unit coefficients stay linear
    assert widget_spec("mass", Param(0.0))[0] == "number"  # nothing to take a logarithm of


class _Handle:
    def __init__(self, label, value):
        self.label, self.value, self.callbacks = label, value, []

    def on_update(self, fn):
        self.callbacks.append(fn)

    def move(self, value):
        self.value = value
        for fn in self.callbacks:
            fn(None)


class _Gui:
    def __init__(self):
        self.handles = {}

    def _add(self, label, value):
        h = self.handles[label.split(" ")[0]] = _Handle(label, value)
        return h

    def add_markdown(self, text):
        pass

    def add_dropdown(self, label, options, initial_value, hint=None):
        return self._add(label, initial_value)

    def add_checkbox(self, label, value, hint=None):
        return self._add(label, value)

    def add_vector3(self, label, value, hint=None):
        return self._add(label, value)

    def add_slider(self, label, lo, hi, step, value, hint=None, marks=None):
        h = self._add(label, value)
        h.range = (lo, hi)
        return h

    def add_number(self, label, value, step=None, hint=None):
        return self._add(label, value)

    def add_text(self, label, value, hint=None):
        return self._add(label, value)


class _Session:
    def __init__(self, cls):
        self.cls = cls
        self.params = {k: p.default for k, p in cls.params.items()}
        self.set = []

    def stability(self):  # the time-step slider's limit (Session.stability): none estimated here
        return {"limit": None, "reason": "", "who": "", "auto": False, "step": 0.0, "exceeded": False,
                "dt_exceeded": False}

    def set_param(self, key, value):
        self.set.append((key, value))
        return "rebuilt"


def test_teapot_mass_slider_reaches_a_gram():
    cls = get_scene("teapot")
    session, gui = _Session(cls), _Gui()
    build_param_panel(gui, session, lambda *a: None)
    h = gui.handles["mass"]
    assert h.range[0] <= -3.0 and h.value == pytest.approx(math.log10(cls.params["mass"].default))
    h.move(-3.0)
    assert session.set[-1] == ("mass", 0.001)
    assert h.label.endswith("= 0.001")
