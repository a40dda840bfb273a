"""Hair: strands of stretch and bending springs on a head (``builder``: ``add_strands``), their
forces and kinematic roots (``forces``), and sag-free initialization (``sag_free``: rest states
solved so the groomed shape is a static equilibrium; it also serves cloth and soft bodies).

Drives ``warpsim.kernels.strands`` and ``warpsim.kernels.sag_free``.
Entry names: add_strands, Strands, StrandForce, StrandRoots, StrandImplicitEuler (``implicit``: the
backward Euler strand step), HairFrame and PosedSphere (``frame``: a frame's steps with the head's
poses on the device, one CUDA graph a frame), sag_free, SagFreeReport.
"""

from typing import TYPE_CHECKING

# imported here, not on first use: the function sag_free shares its module's name, and a package attribute
# bound by a later ``import warpsim.strands.sag_free`` would otherwise be the module
from .._lazy import lazy_attributes
from .sag_free import SagFreeReport, sag_free

if TYPE_CHECKING:  # the same names for static tools; at run time each is imported on first use (below)
    from .builder import Strands, add_strands, head_signed_distance
    from .forces import StrandForce, StrandRoots, strand_stable_dt
    from .frame import HairFrame, HeadPoses, PosedSphere
    from .implicit import StrandImplicitEuler

__all__ = ["HairFrame", "HeadPoses", "PosedSphere", "SagFreeReport", "StrandForce", "StrandImplicitEuler",
           "StrandRoots", "Strands", "add_strands", "head_signed_distance", "sag_free", "strand_stable_dt"]

_HOMES = {
    "Strands": ".builder", "add_strands": ".builder", "head_signed_distance": ".builder",
    "StrandForce": ".forces", "StrandRoots": ".forces", "strand_stable_dt": ".forces",
    "HairFrame": ".frame", "HeadPoses": ".frame", "PosedSphere": ".frame",
    "StrandImplicitEuler": ".implicit",
}
"""Where each name imported on first use lives: importing ``warpsim.strands.preflight`` (a sweep's memory
estimate) defines none of the strands' own kernels."""


__getattr__ = lazy_attributes(__name__, _HOMES, globals())
