"""The strands' forces (``StrandForce``) and their kinematic roots (``StrandRoots``)."""

from __future__ import annotations

from typing import Optional

import numpy as np
import warp as wp

from ..core.collider import Collider
from ..core.forces import Force
from ..core.launch import cached_launch
from ..core.stability import StabilityLimit
from ..kernels import strands as K
from .builder import Strands

__all__ = ["StrandForce", "StrandRoots", "strand_stable_dt"]


def _check_strands(strands, owner):
    if not isinstance(strands, Strands):
        raise TypeError(f"{owner} needs the Strands handle ws.add_strands returned, got {type(strands).__name__}")
    return strands


class StrandForce(Force):
    """Stretch and bending springs of hair strands (``warpsim.kernels.strands``; conservative: the
    bending forces are the exact gradient of the bending energy, frames included): one thread per
    strand adds every force on its particles in a fixed order (bit-reproducible, no atomics).

    Explicit integrators step it within ``Simulator.stable_dt()`` (``stability_limit``); the
    implicit step of hair is ``StrandImplicitEuler`` (its Jacobians are there; ``ws.ImplicitEuler``
    sees no Jacobian of these forces)."""

    def __init__(self, strands):
        self.strands = _check_strands(strands, "StrandForce")
        self._launches = {}

    def bind(self, model):
        super().bind(model)
        self.data = self.strands.bind(model)

    def eval(self, q, qd, time, time_offset, f_out):
        st, d = self.strands, self.data
        inputs = (q, qd, st.first, st.stride, d["rest_length"], d["bend_rest"], d["stretch_stiffness"],
                  d["bend_stiffness"], d["stretch_damping"], d["bend_damping"], d["root_normal"], d["frame_t"],
                  d["frame_n"], f_out)
        cached_launch(K.eval_strand_forces, st.strand_count, inputs, self.model.device, self._launches,
                      key=(st.strand_count, id(q), id(qd), id(f_out), id(d["rest_length"]), id(d["bend_rest"])))


    def stability_limit(self, positions, integrator, forces=()) -> Optional[StabilityLimit]:
        """The strands' ``StabilityLimit`` for ``integrator`` about ``positions`` (a wp.array of the
        model's particles), damping and linear ``Drag`` among ``forces`` included; None under
        ``StrandImplicitEuler`` (see ``warpsim.strands.stability``)."""
        from ..core.forces import Drag
        from .stability import strand_limit

        drag = float(sum(f.linear for f in forces or () if isinstance(f, Drag)))
        return strand_limit(self.strands, self.data, positions.numpy(), integrator, drag=drag)


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
        self.frame_poses = None
        self.step_index = 0

    def use_poses(self, poses) -> None:
        """Inside a ``HairFrame``: read the head's pose of each step from ``poses`` (``HeadPoses``,
        on the device) instead of launch parameters, so the frame can be captured as a graph."""
        self.frame_poses = poses
        self.step_index = 0

    def bind(self, model):
        super().bind(model)
        self.data = self.strands.bind(model)
        self.reset_pose()

    def reset_pose(self) -> None:
        """Take the head's current pose as the previous one (after moving the head by hand or
        restoring a checkpoint): the next step's root velocities come from it."""
        self._prev = self._pose()

    def _pose(self):
        if self.head is None:
            return wp.transform_identity()
        p, q = self.head.world_pose()
        return wp.transform(wp.vec3(*[float(c) for c in p]), wp.quat(*[float(c) for c in q]))

    def apply(self, model, state, q_prev, dt):
        st, d = self.strands, self.data
        fp = self.frame_poses
        if fp is not None and self.step_index < fp.steps:
            k, self.step_index = self.step_index, self.step_index + 1
            wp.launch(K.set_strand_roots_posed, st.strand_count,
                      inputs=[st.first, st.stride, fp.poses, k, d["ghost_local"], d["root_local"], d["normal_local"],
                              1.0 / float(dt), state.positions, state.velocities, d["root_normal"]],
                      device=model.device)
            if self.step_index == fp.steps:
                self._prev = self._pose()  # the head's pose after the frame (its host pose is there)
            return
        pose = self._pose()
        prev, self._prev = self._prev, pose
        wp.launch(K.set_strand_roots, st.strand_count,
                  inputs=[st.first, st.stride, prev, pose, d["ghost_local"], d["root_local"], d["normal_local"],
                          1.0 / float(dt), state.positions, state.velocities, d["root_normal"]],
                  device=model.device)


def strand_stable_dt(strands, model=None, iterations: int = 40, seed: int = 0) -> float:
    """The largest stable semi-implicit Euler step [s] for the strands' springs alone: 2 / omega_max.

    Without ``model``: the Gershgorin bound omega_max^2 <= (4 k_stretch + 16 k_bend) / m_vertex of
    straight strands. With ``model`` (finalized, holding the strands at its initial positions):
    also ``iterations`` power iterations on M^-1 K, K the finite-difference Jacobian of the strand
    forces there (curved rest shapes add stiffness through the bending frames: the wavy groom at
    12 segments measured 3.7x the bound's omega); the larger omega is used. Damping and
    collisions are not included."""
    m = strands.mass / strands.segments
    omega2 = float(((4.0 * strands.stretch_stiffness + 16.0 * strands.bend_stiffness) / m).max())
    if model is not None:
        omega2 = max(omega2, _power_iteration(strands, model, iterations, seed))
    return float(2.0 / np.sqrt(omega2))


def _power_iteration(strands, model, iterations, seed):
    """Largest eigenvalue [1/s^2] of M^-1 K of the strand forces at model.particle_q."""
    force = StrandForce(strands)
    force.bind(model)
    d, n = model.device, model.particle_count
    inv_mass = model.particle_inv_mass.numpy().astype(np.float64)
    free = np.zeros(n, bool)
    free[strands.free_particles()] = True
    free &= inv_mass > 0.0
    x0 = model.particle_q.numpy().astype(np.float64)
    zero = wp.zeros(n, dtype=wp.vec3, device=d)
    out = wp.zeros(n, dtype=wp.vec3, device=d)
    x = wp.zeros(n, dtype=wp.vec3, device=d)

    def forces(positions):
        x.assign(positions.astype(np.float32))
        out.zero_()
        force.eval(x, zero, None, 0.0, out)
        return out.numpy().astype(np.float64)

    f0 = forces(x0)
    p = np.random.default_rng(seed).normal(size=(n, 3)) * free[:, None]
    p /= np.linalg.norm(p)
    eps = 1.0e-5 * max(1.0, float(np.abs(x0).max()))
    lam = 0.0
    for _ in range(iterations):
        y = -(forces(x0 + eps * p) - f0) / eps * (inv_mass * free)[:, None]
        lam = float(np.linalg.norm(y))
        if lam == 0.0:
            break
        p = y / lam
    return lam
