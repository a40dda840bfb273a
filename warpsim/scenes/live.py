"""Helpers for scenes that change parameters while they run (``Scene.set_param``; the live viewer
calls it when a slider moves). Each edits a running simulation in place: Python-side
coefficients that the next launch reads, or device arrays overwritten without reallocation
(so captured graphs keep pointing at them; scenes whose simulator captures graphs call
:func:`drop_graphs` after changing a launch argument). Registers no scenes.
"""
from __future__ import annotations

import numpy as np

from ..bodies.colliders import damping_ratio_for_restitution
from ..core.forces import Gravity

__all__ = ["drop_graphs", "set_contact", "set_gravity", "set_springs"]


def set_contact(colliders, **values) -> None:
    """Set ``restitution`` (in [0, 1]), ``friction`` (>= 0) or penalty ``stiffness`` [N/m] (> 0)
    on every collider that has it; ValueError naming the value otherwise."""
    for key, value in values.items():
        value = float(value)
        bad = {"restitution": not 0.0 <= value <= 1.0, "friction": not value >= 0.0,
               "stiffness": not value > 0.0}[key]
        if bad or not np.isfinite(value):
            rule = {"restitution": "in [0, 1]", "friction": ">= 0", "stiffness": "> 0 [N/m]"}[key]
            raise ValueError(f"{key}={value}: it must be {rule}")
        for c in colliders:
            if hasattr(c, key):
                setattr(c, key, value)
                if key == "restitution" and hasattr(c, "damping_ratio"):
                    c.damping_ratio = damping_ratio_for_restitution(value)


def set_gravity(forces, g) -> None:
    """Set every ``ws.Gravity`` in ``forces`` to pull with ``g`` [m/s^2] along -y."""
    for f in forces:
        if isinstance(f, Gravity):
            f.g = (0.0, -float(g), 0.0)


def set_springs(model, attribute, value, start=0, count=None) -> None:
    """Overwrite ``model.spring_<attribute>`` (``stiffness`` [N/m] or ``damping`` [N s/m]) for
    springs [start, start + count) with ``value`` (>= 0), in place."""
    value = float(value)
    if not (np.isfinite(value) and value >= 0.0):
        raise ValueError(f"spring {attribute}={value}: it must be finite and >= 0")
    arr = getattr(model, f"spring_{attribute}")
    host = arr.numpy().copy()
    stop = len(host) if count is None else start + count
    host[start:stop] = value
    arr.assign(host)


def drop_graphs(sim) -> None:
    """Make a graph-capturing simulator (``ClothSimulator``) capture again on its next frame."""
    graphs = getattr(sim, "_graphs", None)
    if graphs is not None:
        graphs.clear()
