"""``StrandImplicitEuler``: hair strands stepped by backward Euler, one block-banded direct solve
per strand (``warpsim.kernels.strands_implicit``; Baraff and Witkin 1998 for the step, Golub and
Van Loan 4.3/4.5 for the band solve)."""

from __future__ import annotations

import warp as wp

from ..core import checks
from ..core.forces import Drag
from ..core.launch import cached_launch
from ..core.integrators import Integrator
from ..kernels import strands_implicit as K
from .builder import Strands
from .forces import StrandForce

__all__ = ["StrandImplicitEuler"]


class StrandImplicitEuler(Integrator):
    """Backward Euler for hair: (M + h C + h^2 K) dv = h f - h^2 K v0 per strand, K and C the
    positive semi-definite stretch, Gauss-Newton bending (the transported frames' coupling along
    the strand included through a twist unknown per vertex), air-drag and drag-spring Jacobians,
    solved directly per strand (one thread per strand, block band Cholesky), then
    ``newton_iterations - 1`` further Newton iterations that reuse the factors.

    Unconditionally stable for the strands (``Simulator.stable_dt()`` is inf); its numerical
    damping is backward Euler's: a mode of frequency omega loses amplitude by 1 / |1 - i omega h|
    a step (1 - (omega h)^2 / 2 for omega h << 1), so slow swinging keeps its energy at 1-4 steps
    a frame while the stiff stretch modes are damped out.

    Args:
      strands: the ``Strands`` handle (``ws.add_strands``); its ``StrandForce`` must be among the
        Simulator's forces (the right-hand side uses the exact forces).
      newton_iterations: >= 1 (1: the linearised step of Baraff and Witkin).

    Particles that are not free strand vertices step with semi-implicit Euler (the model must have
    no springs of its own: they would be explicit here; use ``ws.ImplicitEuler`` for those).
    """

    name = "strand_implicit_euler"

    def __init__(self, strands, newton_iterations: int = 1):
        super().__init__()
        if not isinstance(strands, Strands):
            raise TypeError(f"StrandImplicitEuler needs the Strands handle ws.add_strands returned, got "
                            f"{type(strands).__name__}")
        self.strands = strands
        self.newton_iterations = checks.count(newton_iterations, "StrandImplicitEuler newton_iterations",
                                              fix="give 1 (the linearised step) or a few")
        self._launches: dict = {}

    def _allocate(self, system):
        model = system.model
        if model.spring_count:
            raise ValueError(f"StrandImplicitEuler: the model has {model.spring_count} springs of its own, which it "
                             "would step explicitly; use integrator='implicit_euler' or a model of strands only")
        force = next((f for f in system.forces if isinstance(f, StrandForce) and f.strands is self.strands), None)
        if force is None:
            raise ValueError("StrandImplicitEuler: no StrandForce of these strands among the Simulator's forces; add "
                             "forces=[ws.Gravity(), StrandForce(strands), ...]")
        st, d = self.strands, system.device
        self.data = st.bind(model)
        slots = st.strand_count * st.stride
        self.pinv = wp.zeros(slots, dtype=wp.mat44d, device=d)  # the factors (float64; x, y, z and twist)
        self.up1 = wp.zeros(slots, dtype=wp.mat44d, device=d)
        self.up2 = wp.zeros(slots, dtype=wp.mat44d, device=d)
        self.rhs = wp.zeros(slots, dtype=wp.vec4d, device=d)
        n = system.count
        self.dv = wp.zeros(n, dtype=wp.vec3, device=d)
        if self.newton_iterations > 1:
            self.q_trial = wp.zeros(n, dtype=wp.vec3, device=d)
            self.v_trial = wp.zeros(n, dtype=wp.vec3, device=d)
            self.f_trial = wp.zeros(n, dtype=wp.vec3, device=d)
            self.delta = wp.zeros(n, dtype=wp.vec3, device=d)

    def _drag_spring(self, system):
        """(particle, stiffness [N/m], damping [N s/m]) of the first drag spring holding a particle."""
        for f in system.forces:
            p = getattr(f, "particle", None)
            if isinstance(p, int) and p >= 0 and hasattr(f, "target_at"):
                return p, float(f.stiffness), float(f.damping)
        return -1, 0.0, 0.0

    def step(self, system, q, qd, time, dt, f_out=None):
        self.prepare(system)
        st, d, h = self.strands, self.data, float(dt)
        dev = system.device
        f = self._forces(system, q, qd, time, 0.0, f_out)
        air = float(sum(x.linear for x in system.forces if isinstance(x, Drag)))
        grab = self._drag_spring(system)
        wp.launch(K.explicit_velocity_change, system.count, inputs=[f, system.inv_mass, h, self.dv], device=dev)
        inputs = (q, qd, f, system.mass, st.first, st.stride, d["rest_length"], d["bend_rest"],
                  d["stretch_stiffness"], d["bend_stiffness"], d["stretch_damping"], d["bend_damping"],
                  d["root_normal"], air, grab[0], grab[1], grab[2], h, self.pinv, self.up1, self.up2, self.rhs, 1,
                  self.dv)
        cached_launch(K.strand_implicit_solve, st.strand_count, inputs, dev, self._launches)
        for _ in range(self.newton_iterations - 1):
            wp.launch(K.apply_velocity_change, system.count,
                      inputs=[q, qd, self.dv, system.inv_mass, h, self.q_trial, self.v_trial], device=dev)
            system.eval_forces(self.q_trial, self.v_trial, time, h, self.f_trial)
            wp.launch(K.strand_resolve, st.strand_count,
                      inputs=[self.f_trial, system.mass, st.first, st.stride, h, self.pinv, self.up1, self.up2,
                              self.rhs, self.dv, self.delta], device=dev)
        wp.launch(K.apply_velocity_change, system.count, inputs=[q, qd, self.dv, system.inv_mass, h, q, qd],
                  device=dev)
