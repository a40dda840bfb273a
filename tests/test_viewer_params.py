"""The viewer's parameter panel: mass-like parameters get a decade slider whose number box shows
and takes the physical value (1 kg shows 1, typing 40 sets 40 N/m), reaching a thousandth of their
default's decade (0.001 kg from 1 kg) with its range fitted to the value after each change; the
inputs follow the session's values (a Reset's restored parameters); the dt hover text says [ms]
as its slider. Driven through a stand-in for viser's GUI API."""


import pytest

from warpsim.scenes import Param, get_scene
from warpsim.viewer.params import build_param_panel, log_window, sync_param_handles, widget_spec


def test_mass_like_params_get_log_sliders():
    kind, o = widget_spec("mass", Param(1.0))
    assert kind == "log_slider" and o["lo"] <= 0.001 and o["hi"] >= 100.0
    assert o["initial"] == 1.0 and (o["min"], o["max"]) == (o["lo"], 10.0)  # the value, its decade above
    assert o["step"] <= 0.001 / 10  # the box can hold the lowest value
    kind, o = widget_spec("stiffness", Param(40.0))
    assert kind == "log_slider" and o["lo"] <= 0.04 and o["hi"] >= 4000.0 and o["max"] == 100.0
    assert log_window(0.002, 0.001, 1e4) == (0.001, 0.01) and log_window(1e5, 0.001, 1e4) == (0.001, 1e4)
    assert widget_spec("restitution", Param(0.5))[0] == "slider"  # unit coefficients stay linear
    assert widget_spec("mass", Param(0.0))[0] == "number"  # nothing to take a logarithm of


class _Handle:
    def __init__(self, label, value, hint=None):
        self.label, self.value, self.callbacks, self.hint = label, value, [], hint
        self.min = self.max = None

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
        h.min, h.max, h.hint = lo, hi, hint
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
    assert h.min <= 0.001 and h.value == cls.params["mass"].default == 1.0  # the box shows 1, not log10 = 0
    h.move(0.001)
    assert session.set[-1] == ("mass", 0.001)
    assert (h.min, h.max) == (0.001, 0.01)  # the range follows: 0.001 kg sits at the left of its decade
    k = gui.handles["stiffness"]
    assert k.value == cls.params["stiffness"].default  # the physical value, not 1.60206
    k.move(40.0)  # typed into the box
    assert session.set[-1] == ("stiffness", 40.0) and k.max == 100.0
    k.move(3.0e4)  # past the right end: the next decades
    assert session.set[-1] == ("stiffness", 3.0e4) and k.max == 1.0e5
    assert "[ms]" in gui.handles["dt"].hint and "[s]" not in gui.handles["dt"].hint


def test_the_inputs_show_the_values_the_session_runs_with():
    """After a Reset restored the last stable parameters, every input shows them; setting the
    inputs from the server is no change of the user's (nothing is set on the session)."""
    cls = get_scene("teapot")
    session, gui = _Session(cls), _Gui()
    handles = build_param_panel(gui, session, lambda *a: None)
    session.params.update(dt=0.0005, mass=0.02, restitution=0.25)
    sync_param_handles(handles, session)
    assert gui.handles["dt"].value == pytest.approx(0.5)  # [ms]
    assert gui.handles["mass"].value == 0.02 and gui.handles["mass"].max == 0.1
    assert gui.handles["restitution"].value == 0.25 and session.set == []
