"""The strands' forces (``StrandForce``) and their kinematic roots (``StrandRoots``)."""

from __future__ import annotations

import numpy as np
import warp as wp

from ..core.collider import Collider
from ..core.forces import Force, cached_launch
from ..kernels import strands as K
from .builder import Strands

__all__ = ["StrandForce", "StrandRoots", "strand_stable_dt"]


def _check_strands(strands, owner):
    if not isinstance(strands, Strands):
        raise ValueError(f"{owner} needs the Strands handle ws.add_strands returned, got {type(strands).__name__}")
    return strands


class StrandForce(Force):
    """Stretch and bending springs of hair strands (``warpsim.kernels.strands``): one thread per
    strand adds every force on its particles in a fixed order (bit-reproducible, no atomics).

    For explicit integrators (semi-implicit Euler with sub-steps: see :func:`strand_stable_dt`);
    it has no Jacobian, so implicit Euler would treat it explicitly."""

    def __init__(self, strands):
        self.strands = _check_strands(strands, "StrandForce")
        self._launches = {}

    def bind(self, model):
        super().bind(model)
        self.data = self.strands.bind(model)

    def eval(self, q, qd, time, time_offset, f_out):
        st, d = self.strands, self.data
        inputs = (q, qd, st.first, st.stride, d["rest_length"], d["bend_rest"], d["stretch_stiffness"],
                  d["bend_stiffness"], d["stretch_damping"], d["bend_damping"], d["root_normal"], f_out)
        cached_launch(K.eval_strand_forces, st.strand_count, inputs, self.model.device, self._launches,
                      key=(st.strand_count, id(q), id(qd), id(f_out), id(d["rest_length"]), id(d["bend_rest"])))


class StrandRoots(Collider):
    """Moves every strand's ghost and root with ``head`` (a kinematic collider: ``ws.Sphere``,
    ``ws.TriangleMesh``, ... moved by ``motion=`` or ``set_transform``) after each step: positions
    from the head pose, velocities from the displacement over the step, and the root frame turns
    with it. List it after the head among the Simulator's colliders so it reads the head's pose of
    the same step. ``head=None``: the roots stay where they were built."""

    def __init__(self, strands, head=None):
        self.strands = _check_strands(strands, "StrandRoots")
        if head is not None and not hasattr(head, "world_pose"):
            raise ValueError(f"StrandRoots head must be a kinematic collider with world_pose() (ws.Sphere, "
                             f"ws.TriangleMesh, ...), got {type(head).__name__}")
        self.head = head if head is not None else strands.head

    def bind(self, model):
        super().bind(model)
        self.data = self.strands.bind(model)

    def _pose(self):
        if self.head is None:
            return wp.transform_identity()
        p, q = self.head.world_pose()
        return wp.transform(wp.vec3(*[float(c) for c in p]), wp.quat(*[float(c) for c in q]))

    def apply(self, model, state, q_prev, dt):
        st, d = self.strands, self.data
        wp.launch(K.set_strand_roots, st.strand_count,
                  inputs=[st.first, st.stride, self._pose(), d["ghost_local"], d["root_local"], d["normal_local"],
                          1.0 / float(dt), state.positions, state.velocities, d["root_normal"]],
                  device=model.device)


def strand_stable_dt(strands) -> float:
    """The largest stable semi-implicit Euler step [s] for the strands' springs alone: 2 / omega_max
    with omega_max^2 <= (4 k_stretch + 16 k_bend) / m_vertex (Gershgorin bound of the stiffness over
    the lightest vertex; damping and collisions not included)."""
    m = strands.mass / strands.segments
    omega2 = (4.0 * strands.stretch_stiffness + 16.0 * strands.bend_stiffness) / m
    return float(2.0 / np.sqrt(omega2.max()))
