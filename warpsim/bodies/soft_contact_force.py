"""A SoftContact's contacts as a penalty force inside an implicit solve (:class:`SoftContactForce`,
made by ``SoftContact.implicit_force``): forces and Jacobian blocks from the contact slots the
collider's last search stored. Kernels: ``warpsim.kernels.soft_contact`` (implicit contact)."""

from __future__ import annotations

import warp as wp

from ..core import checks
from ..core.forces import Force
from ..kernels import soft_contact as K


class SoftContactForce(Force):
    """A SoftContact's contacts as a penalty force inside an implicit solve (``implicit_euler``).

    The contacts found by the collider's last search (the end of the previous step) push while
    they are closer than the thickness: particle k of a contact gets (k_c d - c_c u_n) a_k n with d
    the depth [m] and u_n the normal relative speed [m/s] (see ``warpsim.kernels.soft_contact``).
    By default the solve gets diagonal blocks m a_k^2 n n^T that bound the true stiffness (also for
    solvers without coupling blocks, ``ClothImplicitEuler``); with ``coupling`` the exact Jacobian
    -(k_c + c_c / h) (a a^T) (x) n n^T (diagonal blocks and 12 coupling blocks a contact:
    ``ws.ImplicitEuler``). Either keeps implicit Euler stable at any step. The penalty only sees
    pairs the last search kept, so at large steps give the SoftContact a speculative ``reach``
    (pairs that close during the step are in the solve before they touch). Measured (CPU, 4 tori of
    14 x 7 vertices, implicit Euler, k_c = 2,000 N/m, 1/240 s): without reach 1-29 edges passed
    through the other torus from frame 19 and a vertex went 2.6 mm deep, with ``reach=0.012`` none
    deeper than the thickness (6 mm) and no edge through, over 40 frames with edge
    contact down to 0.6 degrees from parallel (at 11.5 degrees, 6-22 edges crossed while the
    squashed stack sprang back; ``benchmarks/check_heap.py``). The
    collider still runs after the step: new contacts, friction and any depth left are resolved
    there. Momentum is conserved, sums are fixed point (bit-identical runs).

    Args:
        contact: the SoftContact (also in the Simulator's colliders).
        stiffness: k_c [N/m] per contact.
        damping: c_c [N s/m] per contact (normal relative velocity only).
        coupling: the exact Jacobian with coupling blocks (True) or the diagonal bound (False, default).

    Example::

        contact = ws.SoftContact(bodies, thickness=0.006)
        sim = ws.Simulator(model, integrator="implicit_euler",
                           forces=[ws.Gravity(), contact.implicit_force(stiffness=500.0)],
                           colliders=[contact])
    """

    def __init__(self, contact, stiffness: float, damping: float = 0.0, coupling: bool = False):
        if not callable(getattr(contact, "contact_slots", None)):
            raise ValueError(f"SoftContactForce contact is {type(contact).__name__}; give the ws.SoftContact that "
                             "the Simulator also has among its colliders")
        self.contact = contact
        self.stiffness = float(checks.positive(stiffness, "SoftContactForce stiffness", unit="N/m", fix="e.g. 500"))
        self.damping = float(checks.nonnegative(damping, "SoftContactForce damping", unit="N s/m", fix="e.g. 0"))
        self.coupling = checks.flag(coupling, "SoftContactForce coupling")

    def jacobian_triplet_count(self) -> int:
        """12 coupling blocks per contact slot with ``coupling`` (zero blocks where no contact pushes);
        known before the SoftContact is bound (the forces are bound first)."""
        return 12 * self.contact.slot_count() if self.coupling else 0

    def bind(self, model) -> None:
        super().bind(model)
        n, d = model.particle_count, model.device
        self._f = wp.zeros((n, 3), dtype=wp.int64, device=d)
        self._blocks = wp.zeros((n, 9), dtype=wp.int64, device=d)

    def _slots(self):
        c = self.contact
        if getattr(c, "model", None) is not self.model:
            raise ValueError("SoftContactForce: its SoftContact is not bound to this model; put it in the same "
                             "Simulator's colliders")
        return c.contact_slots()

    def eval(self, q, qd, time, time_offset, f_out) -> None:
        particles, weights, normal = self._slots()
        d = self.model.device
        wp.launch(K.eval_contact_forces, particles.shape[0], inputs=[q, qd, particles, weights, normal,
                                                                     self.contact.thickness, self.stiffness,
                                                                     self.damping, self._f], device=d)
        wp.launch(K.add_fixed_forces, self.model.particle_count, inputs=[self._f, f_out], device=d)

    def eval_jacobian(self, q, qd, time, time_offset, ck, cd, diag, rows, cols, values) -> None:
        particles, weights, normal = self._slots()
        d = self.model.device
        coefficient = -(float(ck) * self.stiffness + float(cd) * self.damping)
        if self.coupling:
            wp.launch(K.eval_contact_coupling, particles.shape[0], inputs=[
                q, particles, weights, normal, self.contact.thickness, coefficient, self._blocks, rows, cols, values],
                device=d)
        else:
            wp.launch(K.eval_contact_jacobian, particles.shape[0], inputs=[q, particles, weights, normal,
                                                                           self.contact.thickness, coefficient,
                                                                           self._blocks], device=d)
        wp.launch(K.add_fixed_blocks, self.model.particle_count, inputs=[self._blocks, diag], device=d)
