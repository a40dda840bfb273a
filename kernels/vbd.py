"""Vertex block descent (Chen, Macklin, Yang, Sifakis, Kavan, "Vertex Block Descent", SIGGRAPH 2024)
for mass-spring bodies: ``warpsim.bodies.vbd.VBD`` drives these kernels.

A backward Euler step of size h minimises the incremental potential

    G(x) = sum_i m_i / (2 h^2) |x_i - y_i|^2 + sum_s E_s(x) + sum_c E_c(x),    y = x^t + h v^t + h^2 a_ext,

E_s the springs' energies k_s / 2 (|x_i - x_j| - L_s)^2 (with damping c_s along the spring, c_s / h
(n n^T) (dx_i - dx_j) for the step displacements dx), E_c the contact energies of
``warpsim.kernels.vbd_contact``. VBD descends G one vertex at a time: with the others fixed,
vertex i takes one Newton step on its 3 coordinates,

    H_i dx = f_i,    f_i = m_i / h^2 (y_i - x_i) - dG_rest / dx_i,    H_i = m_i / h^2 I + sum d^2 E / dx_i^2,

each spring's block taken positive semi-definite (k [n n^T + max(0, 1 - L / l) (I - n n^T)]).
Vertices of one colour share no spring, so ``solve_colour`` updates a colour in parallel; it reads
one buffer of positions and writes the other, so no thread of a colour reads a position another thread
of the same launch writes (contact pairs may join two vertices of one colour: they see each other's
positions from before the colour, Jacobi between them, and the result does not depend on thread order). Vertices
of one colour in one pair move at once, so each of them takes the pair's Hessian block times 1 + the number of the
pair's other particles of its colour (``vbd_contact.same_colour``): together they close at most the pair's gap
(a contact k_c = 2,000 N/m against a vertex's m / h^2 of 27-167 N/m closed nearly twice its gap each sweep, and a
resting heap jittered at up to 0.8 m/s); a larger Hessian shortens the step but leaves the minimiser as it is.
``solve_colour`` gives each particle a thread; ``solve_colour_lanes`` a block of B lanes that split its springs
and contact entries and add their partial sums by a fixed-order tile reduction (faster on a GPU, where a colour
of a few thousand particles as threads leaves most of it idle behind the particles with the longest lists). Split
sweeps (``ws.VBD(split=)``) give the colour solve only the particles that can touch a contact before the next search
(``list_contact_particles``, after each search) and solve the rest by ``solve_free``, a thread each over the inertia
and springs (``inertia_spring_force_hessian``): where no contact reaches, G is those alone. With
``ws.VBD(line_search=)`` each colour's solve is followed by ``check_colour``, which keeps a particle's step only when
the force at its end does not push back along it harder than the force at its start pushed (``accepts``), halving it
up to ``backtracks`` times: a whole Newton step of a positive semi-definite model can overshoot into a contact or
across a compressed spring, and a pressed heap's sweeps then cycle. A separate launch, so the solve's code (and its
registers) stay those of the plain solve, and the check costs only where a particle can touch a contact.
The colours alternate the two buffers, and each launch also copies the previous colour's new positions
from the buffer it reads into the one it writes (no thread of the launch reads that one): the buffer a
colour writes then holds every colour solved so far, and a sweep ends with one ``commit_colour`` of its
last colour, after which both buffers hold the same positions (the bits of solving into a second buffer
and copying back after each colour, with half the launches). Every step is clipped to the particle's bound
around its reference position (``clip_to_bound``), the bound of ``vbd_contact.displacement_bounds``.
"""

import warp as wp

from .vbd_contact import contact_force_hessian, guessed_share, sphere_gap

wp.set_module_options({"enable_backward": False})


@wp.func
def clip_to_bound(x: wp.vec3, reference: wp.vec3, bound: float) -> wp.vec3:
    """x moved onto the ball of radius ``bound`` [m] around ``reference`` when outside it."""
    d = x - reference
    length = wp.length(d)
    if length > bound:
        return reference + d * (bound / length)
    return x


@wp.kernel
def assume_external_acceleration(qd: wp.array(dtype=wp.vec3), f_ext: wp.array(dtype=wp.vec3),
                                 inv_mass: wp.array(dtype=float), h: float, qd_prev_out: wp.array(dtype=wp.vec3)):
    """qd_prev = qd - h f_ext / m [m/s]: a step before this one that took the external acceleration whole, for the
    adaptive guess's share s (``guessed_share``: 1 here) where that step is unknown (the first step, a state set from
    outside): the guess is then the inertial target y, as VBD's plain guess. Pinned particles: qd_prev = qd."""
    i = wp.tid()
    qd_prev_out[i] = qd[i] - h * inv_mass[i] * f_ext[i]


@wp.kernel
def predict(
    qd: wp.array(dtype=wp.vec3), qd_prev: wp.array(dtype=wp.vec3), f_ext: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float), h: float, adaptive: int, reference: wp.array(dtype=wp.vec3),
    bound: wp.array(dtype=float), q_io: wp.array(dtype=wp.vec3), q0_out: wp.array(dtype=wp.vec3),
    y_out: wp.array(dtype=wp.vec3), deficit_out: wp.array(dtype=wp.vec3), q_copy_out: wp.array(dtype=wp.vec3),
):
    """Step start q0 = q, inertial target y = q + h v + h^2 a_ext [m] and the initial guess in q:
    q + h v + h^2 s a_ext with s = clamp(a_prev . a_ext / |a_ext|^2, 0, 1) and a_prev = (v - v_prev) / h
    (VBD's adaptive guess: a body resting on the floor starts where it rests; ``adaptive`` 0: s = 1),
    clipped to the bound (``bound[i]`` [m]); what the clip left out goes to ``deficit_out`` [m]
    (``restore_guess``); the guess also into ``q_copy_out`` (the sweeps' second buffer)."""
    i = wp.tid()
    x = q_io[i]
    q0_out[i] = x
    deficit_out[i] = wp.vec3()
    if inv_mass[i] == 0.0:
        y_out[i] = x
        q_copy_out[i] = x
        return
    a = f_ext[i] * inv_mass[i]
    v = qd[i]
    y_out[i] = x + h * v + h * h * a
    s = guessed_share(v, qd_prev[i], a, h, adaptive)
    guess = x + h * v + h * h * s * a
    clipped = clip_to_bound(guess, reference[i], bound[i])
    q_io[i] = clipped
    q_copy_out[i] = clipped
    deficit_out[i] = guess - clipped


@wp.struct
class SpringEntry:
    """One entry of a particle's CSR spring row, as the sweeps of one step read it (``pack_springs``)."""

    other: int  # the spring's other particle; -1: the spring is broken
    rest: float  # rest length [m]
    stiffness: float  # [N/m]
    damping: float  # [N s/m]
    other_start: wp.vec3  # the other particle's position at the step's start [m]


@wp.kernel
def pack_springs(
    entry_particle: wp.array(dtype=int), spring_list: wp.array(dtype=int), spring_indices: wp.array(dtype=int),
    rest: wp.array(dtype=float), stiffness: wp.array(dtype=float), damping: wp.array(dtype=float),
    broken: wp.array(dtype=int), q0: wp.array(dtype=wp.vec3), entries_out: wp.array(dtype=SpringEntry),
):
    """Entry a of the CSR spring rows (particle ``entry_particle[a]``, spring ``spring_list[a]``) packed with what
    the step's sweeps read of it: its other particle, the spring's rest length, stiffness and damping, and the
    other particle's step-start position ``q0`` [m]. A thread an entry (written in order: coalesced), at the
    step's start (after ``predict``), so the model's springs as they are now, broken ones included; each sweep
    then reads one contiguous record an entry instead of six arrays indexed by spring (the same values in the
    same order: the same bits)."""
    a = wp.tid()
    p = entry_particle[a]
    s = spring_list[a]
    o = spring_indices[2 * s]
    if o == p:
        o = spring_indices[2 * s + 1]
    e = SpringEntry()
    e.other = o
    if broken[s] != 0:
        e.other = -1
    e.rest = rest[s]
    e.stiffness = stiffness[s]
    e.damping = damping[s]
    e.other_start = q0[o]
    entries_out[a] = e


@wp.func
def inertia_spring_force_hessian(
    p: int, x: wp.vec3, lane: int, lanes: int, q: wp.array(dtype=wp.vec3), q0: wp.array(dtype=wp.vec3),
    y: wp.array(dtype=wp.vec3), mass: wp.array(dtype=float), inv_h: float,
    spring_offsets: wp.array(dtype=int), springs: wp.array(dtype=SpringEntry),
):
    """Lane ``lane``'s share (of ``lanes``) of the inertia's and springs' part of f_i [N] and H_i [N/m] of particle p
    at ``x`` [m] (module docstring): the inertia (lane 0), then the springs at positions lane, lane + lanes, ... of p's
    CSR row (``springs``, packed by ``pack_springs``), in that order. Lane 0 of 1 is the whole sum."""
    f = wp.vec3()
    H = wp.mat33()
    if lane == 0:
        inertia = mass[p] * inv_h * inv_h
        f = inertia * (y[p] - x)
        H = inertia * wp.identity(3, dtype=float)
    dxp = x - q0[p]
    for a in range(spring_offsets[p] + lane, spring_offsets[p + 1], lanes):
        e = springs[a]
        if e.other < 0:
            continue  # broken
        qo = q[e.other]
        u = x - qo
        length = wp.length(u)
        if length < 1.0e-12:
            continue
        n = u / length
        nn = wp.outer(n, n)
        c = e.damping * inv_h
        f -= e.stiffness * (length - e.rest) * n + c * (nn * (dxp - (qo - e.other_start)))
        H += e.stiffness * (nn + wp.max(0.0, 1.0 - e.rest / length) * (wp.identity(3, dtype=float) - nn)) + c * nn
    return f, H


@wp.func
def vertex_force_hessian(
    p: int, x: wp.vec3, lane: int, lanes: int, q: wp.array(dtype=wp.vec3), q0: wp.array(dtype=wp.vec3),
    y: wp.array(dtype=wp.vec3), mass: wp.array(dtype=float), inv_h: float,
    spring_offsets: wp.array(dtype=int), springs: wp.array(dtype=SpringEntry),
    slot: wp.array(dtype=int), tri: wp.array(dtype=int), edges: wp.array(dtype=int), capacity: int,
    vt_list: wp.array(dtype=int), vt_count: wp.array(dtype=int), tri_offsets: wp.array(dtype=int),
    tris: wp.array(dtype=int), tv_list: wp.array(dtype=int), tv_count: wp.array(dtype=int),
    edge_offsets: wp.array(dtype=int), edge_list: wp.array(dtype=int), ee_list: wp.array(dtype=int),
    ee_count: wp.array(dtype=int), near: wp.array(dtype=int), near_end: wp.array(dtype=int), near_capacity: int,
    vt_distance: wp.array(dtype=float), tv_distance: wp.array(dtype=float), ee_distance: wp.array(dtype=float),
    planes: wp.array(dtype=wp.vec4), spheres: wp.array(dtype=wp.vec4), radius: float,
    contact_stiffness: float,
    friction: float, friction_eps: float, reference: wp.array(dtype=wp.vec3), colour: wp.array(dtype=int),
):
    """Lane ``lane``'s share (of ``lanes``) of f_i [N] and H_i [N/m] of particle p at ``x`` [m] (module docstring):
    the inertia and springs (``inertia_spring_force_hessian``), then its share of the contacts
    (``contact_force_hessian``). Lane 0 of 1 is the whole sum, in the order of the CSR row and the contact lists."""
    f, H = inertia_spring_force_hessian(p, x, lane, lanes, q, q0, y, mass, inv_h, spring_offsets, springs)
    fc, Hc = contact_force_hessian(p, x, lane, lanes, q, q0, slot, tri, edges, capacity, vt_list, vt_count,
                                   tri_offsets, tris, tv_list, tv_count, edge_offsets, edge_list, ee_list, ee_count,
                                   near, near_end, near_capacity, vt_distance, tv_distance, ee_distance, planes,
                                   spheres, radius, contact_stiffness, friction, friction_eps, reference, colour)
    return f + fc, H + Hc


@wp.func
def accepts(f_start: wp.vec3, f_end: wp.vec3, d: wp.vec3) -> bool:
    """Whether a particle's step ``d`` [m] is taken: the force at its end [N] does not push back along it harder
    than the force at its start pushed along it, f_end . d >= -f_start . d. Along a step where the particle's
    energy is quadratic that is exactly "the step does not raise the energy" (E(d) - E(0) = -(f_start + f_end) . d
    / 2), and it asks nothing of the forces but their values, so it holds the springs' damping (a force with no
    potential) to the same rule; where the energy is not quadratic (a contact the step enters, a spring it
    compresses) it rejects the step whose end pushes back hard, the overshoot."""
    return wp.dot(f_end, d) >= -wp.dot(f_start, d)


@wp.func
def may_touch(p: int, x: wp.vec3, slot: wp.array(dtype=int), near_end: wp.array(dtype=int),
              planes: wp.array(dtype=wp.vec4), spheres: wp.array(dtype=wp.vec4), radius: float, bound: float) -> bool:
    """Whether particle p at ``x`` [m] has a contact its step can touch: a listed pair the search kept as able to
    push before the next one (``keep_near_pairs``; or its kept pairs did not fit), or a plane or sphere nearer than
    the thickness ``radius`` + twice its ``bound`` [m] (x and the step's end both lie within the bound of its
    reference). Without one its share of G is its inertia and springs alone."""
    s = slot[p]
    if s >= 0:
        if near_end[3 * s] < 0 or near_end[3 * s + 2] > 0:
            return True
    reach = radius + 2.0 * bound
    for k in range(planes.shape[0]):
        plane = planes[k]
        if wp.dot(wp.vec3(plane[0], plane[1], plane[2]), x) - plane[3] < reach:
            return True
    for k in range(spheres.shape[0]):
        gap, normal = sphere_gap(spheres[k], x)
        if gap < reach:
            return True
    return False


@wp.func
def newton_update(p: int, x: wp.vec3, f: wp.vec3, H: wp.mat33, reference: wp.array(dtype=wp.vec3),
                  bound: wp.array(dtype=float), force: wp.array(dtype=wp.vec3), step: wp.array(dtype=wp.vec3),
                  q_out: wp.array(dtype=wp.vec3)):
    """Particle p's Newton step H dx = f from ``x`` [m], clipped to its bound, into ``q_out``; with ``step`` not
    empty also f [N] into ``force`` and dx (before its clip) [m] into ``step`` (for ``check_colour``)."""
    dx = wp.inverse(H) * f
    q_out[p] = clip_to_bound(x + dx, reference[p], bound[p])
    if step.shape[0] > 0:
        force[p] = f
        step[p] = dx


@wp.kernel
def solve_free(
    colour_particles: wp.array(dtype=int), start: int, count: int, previous_start: int, previous_count: int,
    q: wp.array(dtype=wp.vec3), q0: wp.array(dtype=wp.vec3), y: wp.array(dtype=wp.vec3),
    mass: wp.array(dtype=float), inv_mass: wp.array(dtype=float), inv_h: float,
    spring_offsets: wp.array(dtype=int), springs: wp.array(dtype=SpringEntry), reference: wp.array(dtype=wp.vec3),
    bound: wp.array(dtype=float), listed: wp.array(dtype=int), q_out: wp.array(dtype=wp.vec3),
):
    """One Newton step of particle ``colour_particles[start + k]`` (k < ``count``) on its inertia and springs,
    clipped to its bound, into ``q_out``, unless ``listed[p]`` (a particle that can touch a contact before the next
    search, ``list_contact_particles``: ``solve_colour`` over the colour's list solves it; for every other particle
    the contacts add nothing, so this is G's whole step there). A thread a particle, its sums in the order of its CSR row (the bits of
    ``vertex_force_hessian`` with lane 0 of 1). Thread k < ``previous_count`` also copies particle
    ``colour_particles[previous_start + k]`` (the previous colour's, solved into ``q``) into ``q_out``. Launched over
    max(count, previous_count) threads."""
    k = wp.tid()
    if k < previous_count:
        o = colour_particles[previous_start + k]
        q_out[o] = q[o]
    if k >= count:
        return
    p = colour_particles[start + k]
    if listed[p] != 0:
        return
    x = q[p]
    if inv_mass[p] == 0.0:
        q_out[p] = x
        return
    f, H = inertia_spring_force_hessian(p, x, 0, 1, q, q0, y, mass, inv_h, spring_offsets, springs)
    dx = wp.inverse(H) * f
    q_out[p] = clip_to_bound(x + dx, reference[p], bound[p])


@wp.kernel
def list_contact_particles(
    colour: wp.array(dtype=int), colour_offsets: wp.array(dtype=int), inv_mass: wp.array(dtype=float),
    reference: wp.array(dtype=wp.vec3), bound: wp.array(dtype=float), slot: wp.array(dtype=int),
    near_end: wp.array(dtype=int), planes: wp.array(dtype=wp.vec4), spheres: wp.array(dtype=wp.vec4), radius: float,
    listed_out: wp.array(dtype=int), colour_list_out: wp.array(dtype=int), listed_count_io: wp.array(dtype=int),
):
    """After a search (run or skipped): whether particle p can touch a contact before the next one, into
    ``listed_out`` (1 or 0), and if so p into its colour's part of ``colour_list_out`` (colour c's at
    ``colour_offsets[c]``, ``listed_count_io[c]`` of them; zeroed before). Every position until the next search lies
    within ``bound`` [m] of ``reference`` (the step bound), so ``may_touch`` with the reach widened by one bound, at
    the reference, holds wherever it holds at any of them: a particle left out has no contact force until the next
    search and ``solve_free`` solves it. The order within a colour's list follows the integer atomics (it varies run
    to run), but nothing depends on it: a colour's particles read the buffer no thread of the launch writes and each
    writes only its own entries, so a list in any order gives the same bits."""
    p = wp.tid()
    touching = int(0)
    if inv_mass[p] != 0.0:
        b = bound[p]
        if may_touch(p, reference[p], slot, near_end, planes, spheres, radius + b, b):
            touching = 1
    listed_out[p] = touching
    if touching != 0:
        c = colour[p]
        colour_list_out[colour_offsets[c] + wp.atomic_add(listed_count_io, c, 1)] = p


def colour_kernel(tiled: bool, max_registers: int | None = None, check: bool = False):
    """``solve_colour`` (``tiled`` False: a thread a particle) or ``solve_colour_lanes`` (True: a block of lanes a
    particle, ``wp.launch_tiled``), or with ``check`` their ``check_colour`` and ``check_colour_lanes``: one
    signature and one kernel body, the variant chosen at code generation (``wp.static``), each in a module of its own
    (a tiled module is compiled for each block size); ``max_registers``: CUDA's registers a thread at most (None: the
    compiler's choice)."""
    options = {} if max_registers is None else {"cuda_max_registers": int(max_registers)}
    name = ("check_colour" if check else "solve_colour") + ("_lanes" if tiled else "")

    @wp.kernel(name=name, module="unique", enable_backward=False, **options)
    def kernel(
        particles: wp.array(dtype=int), start: int, count: int, listed_count: wp.array(dtype=int), colour_index: int,
        stride: int, previous_start: int, previous_count: int, q: wp.array(dtype=wp.vec3), q0: wp.array(dtype=wp.vec3),
        y: wp.array(dtype=wp.vec3), mass: wp.array(dtype=float), inv_mass: wp.array(dtype=float), inv_h: float,
        spring_offsets: wp.array(dtype=int), springs: wp.array(dtype=SpringEntry),
        slot: wp.array(dtype=int), tri: wp.array(dtype=int), edges: wp.array(dtype=int), capacity: int,
        vt_list: wp.array(dtype=int), vt_count: wp.array(dtype=int), tri_offsets: wp.array(dtype=int),
        tris: wp.array(dtype=int), tv_list: wp.array(dtype=int), tv_count: wp.array(dtype=int),
        edge_offsets: wp.array(dtype=int), edge_list: wp.array(dtype=int), ee_list: wp.array(dtype=int),
        ee_count: wp.array(dtype=int), near: wp.array(dtype=int), near_end: wp.array(dtype=int), near_capacity: int,
        vt_distance: wp.array(dtype=float), tv_distance: wp.array(dtype=float), ee_distance: wp.array(dtype=float),
        planes: wp.array(dtype=wp.vec4), spheres: wp.array(dtype=wp.vec4), radius: float,
        contact_stiffness: float,
        friction: float, friction_eps: float, reference: wp.array(dtype=wp.vec3), bound: wp.array(dtype=float),
        colour: wp.array(dtype=int), force: wp.array(dtype=wp.vec3), step: wp.array(dtype=wp.vec3), backtracks: int,
        q_out: wp.array(dtype=wp.vec3),
    ):
        k = int(0)
        lane = int(0)
        lanes = int(1)
        if wp.static(tiled):
            k, lane = wp.tid()
            lanes = wp.block_dim()
        else:
            k = wp.tid()
        if lane == 0 and k < previous_count:
            o = particles[previous_start + k]
            q_out[o] = q[o]
        n = count
        if listed_count.shape[0] > 0:
            n = listed_count[colour_index]
        for j in range(k, n, stride):  # the colour's (listed) particles k, k + stride, ...
            p = particles[start + j]
            x = q[p]
            if wp.static(check):  # the colour's steps, solved from q into q_out, checked at their ends
                if inv_mass[p] == 0.0 or not may_touch(p, x, slot, near_end, planes, spheres, radius, bound[p]):
                    continue  # nothing the step can enter: taken whole
                x_try = q_out[p]
                scale = float(1.0)
                attempt = int(0)
                while attempt <= backtracks:  # the same decisions in every lane (f is the block's sum)
                    f, H = vertex_force_hessian(p, x_try, lane, lanes, q, q0, y, mass, inv_h, spring_offsets,
                                                springs, slot, tri, edges, capacity, vt_list, vt_count, tri_offsets,
                                                tris, tv_list, tv_count, edge_offsets, edge_list, ee_list, ee_count,
                                                near, near_end, near_capacity, vt_distance, tv_distance, ee_distance,
                                                planes, spheres, radius, contact_stiffness, friction, friction_eps,
                                                reference, colour)
                    if wp.static(tiled):
                        f = wp.tile_sum(wp.tile(f, preserve_type=True))[0]
                    if accepts(force[p], f, x_try - x):
                        attempt = backtracks + 2
                    else:
                        scale = 0.5 * scale
                        x_try = clip_to_bound(x + scale * step[p], reference[p], bound[p])
                        attempt += 1
                if attempt == backtracks + 1:  # no step passed: the particle stays
                    x_try = x
                if lane == 0:
                    q_out[p] = x_try
            else:
                if inv_mass[p] == 0.0:
                    if lane == 0:
                        q_out[p] = x
                    continue
                f, H = vertex_force_hessian(p, x, lane, lanes, q, q0, y, mass, inv_h, spring_offsets, springs, slot,
                                            tri, edges, capacity, vt_list, vt_count, tri_offsets, tris, tv_list,
                                            tv_count, edge_offsets, edge_list, ee_list, ee_count, near, near_end,
                                            near_capacity, vt_distance, tv_distance, ee_distance, planes, spheres,
                                            radius, contact_stiffness, friction, friction_eps, reference, colour)
                if wp.static(tiled):  # the lanes' shares summed in a fixed tree (tile_sum: no atomics), to every lane
                    f = wp.tile_sum(wp.tile(f, preserve_type=True))[0]
                    H = wp.tile_sum(wp.tile(H, preserve_type=True))[0]
                if lane == 0:
                    newton_update(p, x, f, H, reference, bound, force, step, q_out)

    return kernel


solve_colour = colour_kernel(False)
solve_colour.__doc__ = """One Newton step on G (module docstring) of particle ``particles[start + j]``, clipped to
its bound, into ``q_out``, for j < ``count`` (a colour's particles) or, with ``listed_count`` not empty, j <
``listed_count[colour_index]`` (the colour's particles that can touch a contact, ``list_contact_particles``; the
others are ``solve_free``'s); thread k takes j = k, k + ``stride``, ... (``stride``: the launch's threads).
Forces and Hessians are summed by one thread in the fixed order of the CSR row and contact lists
(``vertex_force_hessian``, lane 0 of 1). Thread k < ``previous_count`` also copies particle
``particles[previous_start + k]`` (the previous colour's, solved into ``q``) into ``q_out``. With ``step`` not empty
(``ws.VBD(line_search=)``), also the force at the start [N] into ``force`` and the step before its clip [m] into
``step`` (``check_colour``); ``backtracks`` unused."""

solve_colour_lanes = colour_kernel(True)
solve_colour_lanes.__doc__ = """``solve_colour`` with each particle's sums spread over the B lanes of a block
(``wp.launch_tiled(dim=G, block_dim=B)``, block k taking j = k, k + G, ..., ``stride`` = G): lane l sums, in order,
the inertia (l = 0) and the springs of the CSR row and entries of the contact lists at positions l, l + B, l + 2B,
... (``vertex_force_hessian``); the B partial f and H are then added by ``wp.tile_sum``, whose order is fixed for a
given B: on CUDA a warp's shuffle-down tree (lane l += lane l + 16, then + 8, 4, 2, 1; at B = 32 that is all), for
B > 32 then the warps' sums in warp order; on the CPU (``wp.config.enable_cpu_blocks``) lane 0, 1, ..., B - 1 in
turn. No float atomics: two runs give the same bits. Lane 0 takes the Newton step and the clip and copies the
previous colour's particle k."""

COMPACT_REGISTERS = 64
"""Registers a thread of ``solve_colour_lanes_compact`` at most (on CUDA): the compiler gives the colour solve 161 of
them (sm_90), so 12 warps a multiprocessor at most; at 64, 32 warps, the rest spilled to local memory (416 bytes a
thread, in L1): one colour sweep of 1,000 tori 9.67 -> 6.02 ms on an H200 (benchmarks/RESULTS.md, every particle
then solved in lanes)."""

solve_colour_lanes_compact = colour_kernel(True, COMPACT_REGISTERS)
solve_colour_lanes_compact.__doc__ = """``solve_colour_lanes`` compiled for at most ``COMPACT_REGISTERS`` registers a
thread on CUDA (the same code: the same sums in the same order; more blocks resident on a multiprocessor, some values
spilled to local memory). The CPU ignores the limit."""


check_colour = colour_kernel(False, check=True)
check_colour.__doc__ = """After ``solve_colour`` (with ``step``) of a colour, over the same particles: each step, from
``q`` [m] (the buffer the solve read) to its end in ``q_out``, is kept when the force there does not push back along
it harder than ``force`` (the force at its start) pushed (``accepts``), else halved (``step``, the step before its
clip, clipped again) up to ``backtracks`` times until one passes, else the particle stays at ``q``; the result into
``q_out``. Only particles that can touch a contact from where they are (``may_touch``): elsewhere G is the inertia
and springs alone and the step is kept. The neighbours are read from ``q``, as the solve read them."""

check_colour_lanes = colour_kernel(True, check=True)
check_colour_lanes.__doc__ = """``check_colour`` with each force spread over a block of lanes as in
``solve_colour_lanes`` (the same sums: the force at a step's end as the solve would sum it there)."""


@wp.kernel
def commit_colour(colour_particles: wp.array(dtype=int), start: int, q_new: wp.array(dtype=wp.vec3),
                  q_out: wp.array(dtype=wp.vec3)):
    """Copy the colour's new positions [m] into the other buffer (a sweep's last colour)."""
    p = colour_particles[start + wp.tid()]
    q_out[p] = q_new[p]


@wp.kernel
def restore_guess(reference: wp.array(dtype=wp.vec3), bound: wp.array(dtype=float),
                  deficit_io: wp.array(dtype=wp.vec3), q_io: wp.array(dtype=wp.vec3),
                  q_copy_out: wp.array(dtype=wp.vec3)):
    """After a search within the step: add back what the bound cut from the initial guess, as far as the
    new bound allows (a falling body whose guess was cut moves on as a whole, instead of being dragged
    back by its springs, sweep by sweep, to its neighbours' cut positions); the positions also into
    ``q_copy_out`` (the sweeps' second buffer)."""
    i = wp.tid()
    x = q_io[i]
    moved = clip_to_bound(x + deficit_io[i], reference[i], bound[i])
    deficit_io[i] = deficit_io[i] - (moved - x)
    q_io[i] = moved
    q_copy_out[i] = moved


@wp.kernel
def clip_positions(reference: wp.array(dtype=wp.vec3), bound: wp.array(dtype=float), q_io: wp.array(dtype=wp.vec3)):
    """Every position [m] back inside its bound (after the Chebyshev extrapolation)."""
    i = wp.tid()
    q_io[i] = clip_to_bound(q_io[i], reference[i], bound[i])
