"""The live viewer: watch a scene in the browser while it runs, tune it, grab it with the mouse.

Built on ``viser`` (optional extra: ``pip install -e ".[viewer]"``), imported only when a viewer
starts, so ``import warpsim`` stays lean. One scene description, several sinks: the viewer draws
the prims a scene declares in ``declare(sink)`` and fills from ``frame_data()``, exactly what
the USD writer records.

Modules: ``sink`` (ViewerSink: declarations -> draw items, pure NumPy), ``geometry``
(triangulation, prototype meshes), ``picking`` (ray casts, the camera-facing drag plane),
``session`` (the server-side state: stepping, speed, parameters, dragging, recording, errors;
no viser), ``record`` (recording into a crash-safe USD cache), ``playback`` (caches read on
demand), ``server`` (the viser front end: Viewer), ``controls`` and ``params`` (the GUI panels),
``framing`` (where the camera starts, and aiming it), ``pace`` (whether the page keeps up: long
curve sets thinned while it lags), ``starting`` (the page served while a scene is built),
``command`` (``warpsim view``). Drives no kernels of its own (dragging uses
``warpsim.bodies.drag.DragSpring``). Entry class: :class:`Viewer` (``ws.Viewer``).
"""

__all__ = ["Viewer"]


def __getattr__(name):
    if name == "Viewer":
        from .server import Viewer

        return Viewer
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
