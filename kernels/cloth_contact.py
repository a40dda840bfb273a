"""Contact inside the implicit cloth solve (Baraff & Witkin 1998, section 5.3: constraints by
filtering; the pre-filtered form of Ascher & Boxerman / Tamstorf et al. 2015).

A particle touching a static shape (gap <= tolerance at the step's start and at its end at its
velocity, not released by the previous step) is constrained along the shape's normal n: its new normal
velocity is 0 (an inelastic resting contact), its tangential motion is free; one that would reach an
inelastic shape (restitution 0) within the step is constrained to arrive at its surface at the step's
end (normal velocity -gap / h: a speculative contact). With S_i = I - n_i n_i^T
(S_i = I for a free particle: n_i = 0) and z_i = -(v_i . n_i) n_i the prescribed part of the
velocity change, the solve for dv = z + y, y_i perpendicular to n_i, is

    (S A S + I - S) y = S (b - A z)

which stays symmetric positive definite (block-Jacobi CG unchanged). Afterwards the constraint
impulse is J_i = (A dv - b)_i [N s] (A and b before filtering): J_i . n_i < 0 means the contact
pulled, so the particle is released for the next step; otherwise Coulomb friction removes at
most mu J_n / m of its tangential speed (never reversing it).

Why: with the contact left to a position projection after the step, the solve pulls a particle
held by the cloth's tension into the shape and the projection pushes it out again, stretching its
springs: energy from nowhere every step (the default ``cloth`` scene gained 1.4 J, 0.36x its energy
scale, over frames 16-23 at 1/60 s; ``warpsim.core.energy``).

Shapes (``ContactShape``): kind 0 a plane n . x = offset (free side along n); kind 1 a solid
capsule (segment [a, b], radius; a sphere when a == b); kind 2 a spherical or capsule container
(particles kept within radius of the segment).
"""

import warp as wp

from .collide import closest_point_segment
from .integrate import block_inverse

wp.set_module_options({"enable_backward": False})

SLIP_FLOOR = wp.constant(1.0e-4)  # [m/s], see friction_drag
SHAPE_PLANE = wp.constant(0)
SHAPE_CAPSULE = wp.constant(1)
SHAPE_CONTAINER = wp.constant(2)


@wp.struct
class ContactShape:
    """A static shape in world space: ``kind`` (module docstring); plane ``normal`` and ``offset``
    [m]; capsule ends ``a``, ``b`` [m] and ``radius`` [m]; the collider's ``thickness`` [m],
    Coulomb ``friction``, ``restitution`` and ``tolerance`` [m] (the gap that counts as touching)."""

    kind: int
    normal: wp.vec3
    offset: float
    a: wp.vec3
    b: wp.vec3
    radius: float
    thickness: float
    friction: float
    restitution: float
    tolerance: float


@wp.func
def shape_gap(s: ContactShape, x: wp.vec3, r: float):
    """(gap [m] between a particle of radius r at x and the shape's surface (negative inside),
    unit normal pointing to the free side)."""
    if s.kind == SHAPE_PLANE:
        return wp.dot(s.normal, x) - s.offset - r - s.thickness, s.normal
    d = x - closest_point_segment(x, s.a, s.b)
    dist = wp.length(d)
    n = wp.vec3(0.0, 1.0, 0.0)
    if dist > 0.0:
        n = d / dist
    if s.kind == SHAPE_CONTAINER:
        return s.radius - dist - r - s.thickness, -n
    return dist - s.radius - r - s.thickness, n


@wp.kernel
def find_contact_constraints(
    shapes: wp.array(dtype=ContactShape),
    q: wp.array(dtype=wp.vec3),
    qd: wp.array(dtype=wp.vec3),
    radius: wp.array(dtype=float),
    inv_mass: wp.array(dtype=float),
    released: wp.array(dtype=int),
    h: float,
    normal_out: wp.array(dtype=wp.vec3),
    friction_out: wp.array(dtype=float),
    z_out: wp.array(dtype=wp.vec3),
):
    """Per particle: the constraint normal (0 when free), its friction and the prescribed
    velocity change z = (u - v . n) n [m/s] (the closest shape, in shape order on ties). A particle
    touching a shape (gap within its tolerance, and still within it at the end of a step of h [s]
    at its velocity: one resting on it, whose normal velocity is 0 up to rounding, stays
    constrained, one leaving faster is free) gets u = 0; one that would reach an inelastic shape
    (restitution 0) within the step gets u = -gap / h: it arrives at the surface at the step's end
    inside the solve, with its neighbours, instead of being placed there by the collider after a
    step that moved its neighbours without it."""
    i = wp.tid()
    normal_out[i] = wp.vec3()
    friction_out[i] = 0.0
    z_out[i] = wp.vec3()
    if inv_mass[i] == 0.0 or released[i] != 0:
        return
    x = q[i]
    v = qd[i]
    best = float(1.0e30)
    best_n = wp.vec3()
    best_mu = float(0.0)
    best_u = float(0.0)
    for k in range(shapes.shape[0]):
        s = shapes[k]
        gap, n = shape_gap(s, x, radius[i])
        vn = wp.dot(v, n)
        u = float(0.0)
        ok = gap + h * wp.max(vn, 0.0) <= s.tolerance  # touching, not leaving within the step
        if not ok and s.restitution == 0.0 and gap + h * vn <= s.tolerance:
            ok = True  # reaches the shape within the step: arrive at its surface at the step's end
            u = -gap / h
        if ok and gap < best:
            best = gap
            best_n = n
            best_mu = s.friction
            best_u = u
    if best < 1.0e30:
        normal_out[i] = best_n
        friction_out[i] = best_mu
        z_out[i] = (best_u - wp.dot(v, best_n)) * best_n


@wp.func
def filter_of(n: wp.vec3) -> wp.mat33:
    """S = I - n n^T (the identity for n = 0)."""
    return wp.identity(n=3, dtype=float) - wp.outer(n, n)


@wp.func
def friction_drag(n: wp.vec3, v: wp.vec3, mu: float, impulse: float, h: float) -> float:
    """Coefficient c [kg/s] of the tangential drag -c v_t that stands for Coulomb friction of a
    contact pressed with ``impulse`` [N s] over the last step of h [s]: c = mu (impulse / h) / |v_t|,
    |v_t| floored at ``SLIP_FLOOR`` [m/s] (slower slip is viscous; backward Euler's drag then holds
    the particle almost still). Taken implicitly it removes energy and never reverses v_t."""
    vt = v - wp.dot(v, n) * n
    return mu * impulse / (h * wp.max(wp.length(vt), SLIP_FLOOR))


@wp.kernel
def filter_contact_system(
    offsets: wp.array(dtype=int),
    columns: wp.array(dtype=int),
    diagonal_slots: wp.array(dtype=int),
    normal: wp.array(dtype=wp.vec3),
    friction: wp.array(dtype=float),
    impulse: wp.array(dtype=float),
    qd: wp.array(dtype=wp.vec3),
    h: float,
    Az: wp.array(dtype=wp.vec3),
    values_io: wp.array(dtype=wp.mat33),
    rhs_io: wp.array(dtype=wp.vec3),
    inverse_out: wp.array(dtype=wp.mat33),
):
    """Row i of A -> S_i A_ij S_j (+ n_i n_i^T on the diagonal), b_i -> S_i (b_i - (A z)_i); a
    constrained particle's friction enters as the implicit tangential drag h c S_i on the diagonal
    and -h c S_i v in b (``friction_drag`` from the previous step's normal impulse); the diagonal
    block's inverse (the block-Jacobi preconditioner) recomputed."""
    i = wp.tid()
    ni = normal[i]
    Si = filter_of(ni)
    for k in range(offsets[i], offsets[i + 1]):
        values_io[k] = Si * values_io[k] * filter_of(normal[columns[k]])
    d = diagonal_slots[i]
    block = values_io[d] + wp.outer(ni, ni)
    b = Si * (rhs_io[i] - Az[i])
    if wp.dot(ni, ni) > 0.0 and friction[i] > 0.0 and impulse[i] > 0.0:
        hc = h * friction_drag(ni, qd[i], friction[i], impulse[i], h)
        block = block + hc * Si
        b = b - hc * (Si * qd[i])
    values_io[d] = block
    inverse_out[i] = block_inverse(block)
    rhs_io[i] = b


@wp.kernel
def add_prescribed(z: wp.array(dtype=wp.vec3), dv_io: wp.array(dtype=wp.vec3)):
    """dv = y + z: the solved free part plus the prescribed normal part [m/s]."""
    i = wp.tid()
    dv_io[i] = dv_io[i] + z[i]


@wp.kernel
def finish_contact_step(
    normal: wp.array(dtype=wp.vec3),
    Adv: wp.array(dtype=wp.vec3),
    rhs: wp.array(dtype=wp.vec3),
    released_out: wp.array(dtype=int),
    impulse_out: wp.array(dtype=float),
):
    """With dv = y + z (``add_prescribed``): for a constrained particle the constraint impulse
    J = (A dv - b) . n [N s] (unfiltered A and b; the friction drag is not in them): J < 0
    (pulling) releases it for the next step, J >= 0 is kept as the next step's normal impulse
    (its friction); 0 for free particles."""
    i = wp.tid()
    released_out[i] = 0
    impulse_out[i] = 0.0
    n = normal[i]
    if wp.dot(n, n) > 0.0:
        j = wp.dot(Adv[i] - rhs[i], n)
        if j < 0.0:
            released_out[i] = 1
        else:
            impulse_out[i] = j
