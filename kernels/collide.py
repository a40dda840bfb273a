"""Collision kernels, run after integration on the new positions and velocities (in place).

Conventions
- A contact is a unit normal ``n`` pointing to the free side and a penetration depth ``h > 0``
  [m] measured against the particle's radius plus the collider's ``thickness``.
- Plane: ``n . x = offset`` with unit normal ``n`` pointing into the free side; a particle of
  radius ``r`` penetrates by ``h = r + thickness - (n . x - offset)`` when ``h > 0``.
- Finite shapes (spheres, capsules, rectangles, triangle meshes) are described in their own
  local frame; ``pose`` is the local-to-world transform at the end of the step and
  ``pose_prev`` the one at its start, so moving (kinematic) shapes see the particle path
  relative to themselves and push with the velocity of the touched surface point.
- Continuous detection: the segment from ``q_prev`` (start of the step) to the new position is
  tested against the shape, not only the end point, so fast particles do not tunnel.

Handling modes (``resolve_contact``), applied to the velocity relative to the surface:
- reflect (0), resolved at the time of impact: along the normal the step's path is the
  parabola s(t) = d0 + b t + a_n t^2 / 2 from the start distance d0 [m] (``q_prev``) to the end
  distance -h, with the step's normal acceleration a_n [m/s^2] (``State.forces``); for
  semi-implicit Euler this is exactly the integrator's own trajectory (its samples lie on it with
  the synchronised velocity w = v + a dt / 2). The particle moves to contact at the first root
  t_c, its normal velocity there is reflected with the restitution (u -> -e u), and it finishes
  the step on the reflected parabola; the velocity is handed back staggered (v = w - a_n dt / 2).
  A contact too slow to leave the surface within the step settles on it at rest (v_n = 0).
  A ballistic bounce therefore keeps the apex of its parabola for e = 1 and scales the impact's
  kinetic energy by e^2 otherwise: no energy appears at any dt. (The samples of semi-implicit
  Euler released at rest lie on a parabola whose apex is g dt^2 / 8 above the release point, the
  integrator's own offset, so a sampled rebound may show up to that much above it.)
- seed (3): the lecture's update: the position is mirrored out scaled by restitution, h' = e h;
  v_n' = -e v_n. It gains energy at large steps (the reflected velocity was accumulated over the
  whole step although the particle spent part of it below the surface): the seed's ball at
  dt = 0.04 s, e = 0.9, released at 2 cm, rebounds to 4.15 cm.
- project (1): the particle is placed on the surface (position correction); v_n' = -e v_n.
- penalty (2): a penalty spring f = k h n - c v_n n acts over the step as an impulse
  (velocity level, position untouched); c = 2 zeta sqrt(k m), zeta chosen by the host from
  the restitution (a linear spring-dashpot, which may pull slightly while still overlapping).
Coulomb friction removes at most mu times the normal velocity change of tangential speed and
never reverses it.

Particle-particle collisions (``count_particle_contacts`` / ``collide_particle_pairs``) use a
``wp.HashGrid``: every overlapping pair gets the 1D two-body impulse along its normal
(momentum conserved, relative normal velocity -> -c_R times itself), scaled by
1 / max(contacts of either particle) so that simultaneous contacts never add energy.
"""

import warp as wp

from .worlds import world_key

wp.set_module_options({"enable_backward": False, "fuse_fp": False})  # no FMA contraction: see world_step.py

COLLIDE_REFLECT = wp.constant(0)
COLLIDE_PROJECT = wp.constant(1)
COLLIDE_PENALTY = wp.constant(2)
COLLIDE_SEED = wp.constant(3)


# --------------------------------------------------------------------------------------
# Contact response
# --------------------------------------------------------------------------------------
@wp.func
def respond_velocity(v: wp.vec3, n: wp.vec3, restitution: float, friction: float) -> wp.vec3:
    """Normal velocity v_n -> -e v_n when approaching; Coulomb friction removes at most
    mu (1 + e) |v_n| of tangential speed and never reverses it."""
    vn = wp.dot(v, n)
    if vn >= 0.0:
        return v
    vt = v - vn * n
    vt_len = wp.length(vt)
    impulse = (1.0 + restitution) * (-vn)
    if vt_len > 0.0:
        vt = vt * wp.max(0.0, 1.0 - friction * impulse / vt_len)
    return vt - restitution * vn * n


@wp.func
def penalty_velocity(
    v: wp.vec3, n: wp.vec3, h: float, stiffness: float, damping_ratio: float, friction: float, inv_mass: float,
    dt: float,
) -> wp.vec3:
    """Velocity after a linear spring-dashpot (Kelvin-Voigt) contact acts along n for dt [s]:
    f = k h - c v_n with stiffness k [N/m], depth h [m], c = 2 zeta sqrt(k m). The damper never
    reverses v_n within a step. Like the continuous model (whose restitution is exactly
    exp(-zeta pi / sqrt(1 - zeta^2))) it may pull slightly while the particle still overlaps;
    friction uses the magnitude of the normal impulse."""
    vn = wp.dot(v, n)
    spring = dt * stiffness * h * inv_mass
    damp = wp.min(1.0, dt * 2.0 * damping_ratio * wp.sqrt(stiffness * inv_mass))
    dvn = spring - damp * vn
    vt = v - vn * n
    vt_len = wp.length(vt)
    if vt_len > 0.0:
        vt = vt * wp.max(0.0, 1.0 - friction * wp.abs(dvn) / vt_len)
    return vt + (vn + dvn) * n


@wp.func
def impact_state(
    v: wp.vec3, n: wp.vec3, h: float, d0: float, a_n: float, restitution: float, friction: float, dt: float
):
    """Reflect mode (module docstring): the normal displacement [m] that ends the step on the
    reflected parabola and the new velocity [m/s], from the depth h > 0 [m], the start distance
    d0 [m], the step's normal acceleration a_n [m/s^2] and dt [s]. Coulomb friction removes at most
    mu times the normal velocity change of tangential speed and never reverses it."""
    vn = wp.dot(v, n)
    b = (-h - d0) / dt - 0.5 * a_n * dt  # sync normal velocity at the start of the step
    tc = float(0.0)  # noqa: UP018 (mutable in Warp)
    if d0 > 0.0:
        root = wp.sqrt(wp.max(b * b - 2.0 * a_n * d0, 0.0))
        tc = wp.clamp(2.0 * d0 / wp.max(root - b, 1.0e-30), 0.0, dt)
    else:
        d0 = 0.0
    u = -restitution * (b + a_n * tc)  # reflected normal velocity at contact
    r = dt - tc
    s_end = u * r + 0.5 * a_n * r * r
    vn_new = u + a_n * r - 0.5 * a_n * dt  # the parabola's velocity at the step's end, staggered
    if s_end < 0.0:  # a slow, inelastic contact settles: on the surface, at rest along n
        s_end = 0.0
        vn_new = 0.0
    vt = v - vn * n
    vt_len = wp.length(vt)
    if vt_len > 0.0:
        vt = vt * wp.max(0.0, 1.0 - friction * wp.max(vn_new - vn, 0.0) / vt_len)
    return (s_end + h) * n, vt + vn_new * n


@wp.func
def resolve_contact(
    x: wp.vec3,
    v: wp.vec3,
    n: wp.vec3,
    h: float,
    d0: float,
    a_n: float,
    v_surface: wp.vec3,
    mode: int,
    restitution: float,
    friction: float,
    stiffness: float,
    damping_ratio: float,
    inv_mass: float,
    dt: float,
):
    """Resolve one contact (normal n, depth h > 0 [m]) against a surface moving at v_surface
    [m/s]; d0 [m] is the particle's distance from the surface at the start of the step and a_n
    [m/s^2] the step's normal acceleration (reflect mode); returns the corrected position and
    velocity (see module docstring for the modes)."""
    v_rel = v - v_surface
    if mode == COLLIDE_PENALTY:
        v_rel = penalty_velocity(v_rel, n, h, stiffness, damping_ratio, friction, inv_mass, dt)
    elif mode == COLLIDE_REFLECT:
        dx, v_rel = impact_state(v_rel, n, h, d0, a_n, restitution, friction, dt)
        x = x + dx
    else:
        if mode == COLLIDE_SEED:
            x = x + (1.0 + restitution) * h * n
        else:
            x = x + h * n
        v_rel = respond_velocity(v_rel, n, restitution, friction)
    return x, v_rel + v_surface


# --------------------------------------------------------------------------------------
# Planes and boxes of walls (infinite half-spaces, static)
# --------------------------------------------------------------------------------------
@wp.kernel
def collide_planes(
    inv_mass: wp.array(dtype=float),
    radius: wp.array(dtype=float),
    normals: wp.array(dtype=wp.vec3),
    offsets: wp.array(dtype=float),
    restitution: float,
    friction: float,
    mode: int,
    thickness: float,
    stiffness: float,
    damping_ratio: float,
    dt: float,
    q_prev: wp.array(dtype=wp.vec3),
    forces: wp.array(dtype=wp.vec3),
    q_io: wp.array(dtype=wp.vec3),
    qd_io: wp.array(dtype=wp.vec3),
):
    """Resolve particle i against every plane of one collider, in order (modes: module
    docstring); q_prev: positions at the start of the step [m], forces: the step's force [N]."""
    i = wp.tid()
    collide_particle_planes(i, inv_mass, radius, normals, offsets, restitution, friction, mode, thickness, stiffness,
                            damping_ratio, dt, q_prev, forces, q_io, qd_io)


@wp.func
def collide_particle_planes(
    i: int,
    inv_mass: wp.array(dtype=float),
    radius: wp.array(dtype=float),
    normals: wp.array(dtype=wp.vec3),
    offsets: wp.array(dtype=float),
    restitution: float,
    friction: float,
    mode: int,
    thickness: float,
    stiffness: float,
    damping_ratio: float,
    dt: float,
    q_prev: wp.array(dtype=wp.vec3),
    forces: wp.array(dtype=wp.vec3),
    q_io: wp.array(dtype=wp.vec3),
    qd_io: wp.array(dtype=wp.vec3),
):
    """Particle i against every plane, in order (the body of ``collide_planes``; batched worlds
    call it with their own world's restitution, friction and damping ratio)."""
    w = inv_mass[i]
    if w == 0.0:
        return
    x = q_io[i]
    d = radius[i] + thickness
    touching = int(0)
    for p in range(normals.shape[0]):
        if d - (wp.dot(normals[p], x) - offsets[p]) > 0.0:  # resolve_plane's test on the unmoved x
            touching = 1
    if touching == 0:  # no plane moves x, so every plane sees this x: nothing changes
        return
    v = qd_io[i]
    x0 = q_prev[i]
    a = w * forces[i]
    for p in range(normals.shape[0]):
        x, v = resolve_plane(x, v, x0, a, normals[p], offsets[p], d, mode, restitution, friction, stiffness,
                             damping_ratio, w, dt)
    q_io[i] = x
    qd_io[i] = v


@wp.func
def resolve_plane(
    x: wp.vec3,
    v: wp.vec3,
    x0: wp.vec3,
    a: wp.vec3,
    n: wp.vec3,
    offset: float,
    d: float,
    mode: int,
    restitution: float,
    friction: float,
    stiffness: float,
    damping_ratio: float,
    inv_mass: float,
    dt: float,
):
    """One plane n . x = offset against a particle of radius d (radius + thickness) [m] that
    started the step at x0 [m] and was accelerated by a [m/s^2]: the corrected (x, v), unchanged
    without contact (h = d - (n . x - offset) <= 0)."""
    h = d - (wp.dot(n, x) - offset)
    if h > 0.0:
        d0 = wp.dot(n, x0) - offset - d
        return resolve_contact(x, v, n, h, d0, wp.dot(a, n), wp.vec3(0.0), mode, restitution, friction, stiffness,
                               damping_ratio, inv_mass, dt)
    return x, v


@wp.kernel
def collide_planes_worlds(
    inv_mass: wp.array(dtype=float),
    radius: wp.array(dtype=float),
    particle_world: wp.array(dtype=int),
    normals: wp.array(dtype=wp.vec3),
    offsets: wp.array(dtype=float),
    world_restitution: wp.array(dtype=float),
    world_friction: wp.array(dtype=float),
    world_damping_ratio: wp.array(dtype=float),
    mode: int,
    thickness: float,
    stiffness: float,
    dt: float,
    q_prev: wp.array(dtype=wp.vec3),
    forces: wp.array(dtype=wp.vec3),
    q_io: wp.array(dtype=wp.vec3),
    qd_io: wp.array(dtype=wp.vec3),
):
    """``collide_planes`` for batched worlds: particle i uses the restitution, friction and
    penalty damping ratio of its world ``particle_world[i]`` (arrays of shape (world_count,))."""
    i = wp.tid()
    w = particle_world[i]
    collide_particle_planes(i, inv_mass, radius, normals, offsets, world_restitution[w], world_friction[w], mode,
                            thickness, stiffness, world_damping_ratio[w], dt, q_prev, forces, q_io, qd_io)


# --------------------------------------------------------------------------------------
# Geometry helpers (local frame)
# --------------------------------------------------------------------------------------
@wp.func
def closest_point_segment(x: wp.vec3, a: wp.vec3, b: wp.vec3) -> wp.vec3:
    """Closest point to x on the segment [a, b] (a == b allowed)."""
    ab = b - a
    ll = wp.dot(ab, ab)
    if ll == 0.0:
        return a
    s = wp.clamp(wp.dot(x - a, ab) / ll, 0.0, 1.0)
    return a + s * ab


@wp.func
def ray_sphere_entry(o: wp.vec3, d: wp.vec3, c: wp.vec3, r: float) -> float:
    """Smallest t >= 0 with |o + t d - c| = r for unit d entering the sphere, or -1."""
    oc = o - c
    b = wp.dot(oc, d)
    cc = wp.dot(oc, oc) - r * r
    disc = b * b - cc
    if disc < 0.0:
        return -1.0
    t = -b - wp.sqrt(disc)
    if t < 0.0:
        return -1.0
    return t


@wp.func
def ray_capsule_entry(o: wp.vec3, d: wp.vec3, a: wp.vec3, b: wp.vec3, r: float) -> float:
    """First entry t >= 0 of the ray o + t d (unit d) into the capsule of radius r around
    segment [a, b], or -1 when it does not enter (o is assumed outside)."""
    best = -1.0
    ta = ray_sphere_entry(o, d, a, r)
    if ta >= 0.0:
        best = ta
    tb = ray_sphere_entry(o, d, b, r)
    if tb >= 0.0 and (best < 0.0 or tb < best):
        best = tb
    ab = b - a
    length = wp.length(ab)
    if length > 0.0:
        u = ab / length
        oa = o - a
        op = oa - wp.dot(oa, u) * u
        dp = d - wp.dot(d, u) * u
        aa = wp.dot(dp, dp)
        if aa > 1.0e-12:
            bb = wp.dot(op, dp)
            cc = wp.dot(op, op) - r * r
            disc = bb * bb - aa * cc
            if disc >= 0.0:
                t = (-bb - wp.sqrt(disc)) / aa
                if t >= 0.0:
                    s = wp.dot(oa + t * d, u)
                    if s >= 0.0 and s <= length and (best < 0.0 or t < best):
                        best = t
    return best


@wp.func
def capsule_contact(x0: wp.vec3, x: wp.vec3, a: wp.vec3, b: wp.vec3, r: float, inside: int):
    """Contact of a particle moving x0 -> x with the capsule (radius r, already inflated by the
    particle radius and thickness) around [a, b]; a == b is a sphere. Returns (h, n, p): depth
    (> 0 on contact), normal and touched surface point, all local.

    Solid (inside == 0): the path is tested for entry (continuous detection), then the end
    point (``capsule_contact_point``). Container (inside == 1, spheres): particles are kept
    within distance r of a."""
    if inside == 1:
        return capsule_contact_point(x, a, b, r, inside)
    # continuous detection: entered during the step from outside?
    c0 = closest_point_segment(x0, a, b)
    dist0 = wp.length(x0 - c0)
    path = x - x0
    path_len = wp.length(path)
    if dist0 >= r and path_len > 0.0:
        d = path / path_len
        t = ray_capsule_entry(x0, d, a, b, r)
        if t >= 0.0 and t <= path_len:
            p = x0 + t * d
            cp = closest_point_segment(p, a, b)
            n = wp.normalize(p - cp)
            h = -wp.dot(x - p, n)
            if h > 0.0:
                return h, n, p
            return 0.0, n, p
    return capsule_contact_point(x, a, b, r, inside)


@wp.func
def capsule_contact_point(x: wp.vec3, a: wp.vec3, b: wp.vec3, r: float, inside: int):
    """Discrete contact of the point x with the capsule (inside == 0) or spherical container
    (inside == 1) of radius r around [a, b]: (h, n, p) as ``capsule_contact``, from x alone."""
    c = closest_point_segment(x, a, b)
    delta = x - c
    dist = wp.length(delta)
    if inside == 1:
        if dist > r:
            n = -delta / dist
            return dist - r, n, c - r * n
        return 0.0, wp.vec3(0.0), x
    if dist < r:
        n = wp.vec3(0.0, 1.0, 0.0)
        if dist > 0.0:
            n = delta / dist
        return r - dist, n, c + r * n
    return 0.0, wp.vec3(0.0), x


@wp.func
def quad_contact(x0: wp.vec3, x: wp.vec3, half_x: float, half_z: float, d: float):
    """Contact with the two-sided rectangle |x| <= half_x, |z| <= half_z in the local plane
    y = 0, thickened by d (particle radius + thickness). Returns (h, n, p) as capsule_contact.

    Continuous: if the path x0 -> x crosses the plane inside the rectangle, the contact normal
    faces the side x0 came from, whatever the speed. Otherwise the end point is tested against
    the rectangle's closest point (rounded edges)."""
    y0 = x0[1]
    y1 = x[1]
    side = 1.0
    if y0 < 0.0 or (y0 == 0.0 and y1 > 0.0):
        side = -1.0
    if side * y1 < 0.0 and side * y0 >= 0.0:
        tau = y0 / (y0 - y1)
        p = x0 + tau * (x - x0)
        if wp.abs(p[0]) <= half_x and wp.abs(p[2]) <= half_z:
            n = wp.vec3(0.0, side, 0.0)
            return d - side * y1, n, wp.vec3(x[0], 0.0, x[2])
    c = wp.vec3(wp.clamp(x[0], -half_x, half_x), 0.0, wp.clamp(x[2], -half_z, half_z))
    delta = x - c
    dist = wp.length(delta)
    if dist < d:
        n = wp.vec3(0.0, side, 0.0)
        if dist > 1.0e-9 * d:
            n = delta / dist
        return d - dist, n, c
    return 0.0, wp.vec3(0.0), x


@wp.func
def mesh_contact(mesh: wp.uint64, x0: wp.vec3, x: wp.vec3, d: float, solid: int):
    """Contact with a wp.Mesh (local frame), thickened by d. Returns (h, n, p).

    Continuous: a ray from x0 along the step (wp.mesh_query_ray) finds the first surface
    crossing; the contact plane is that face, its normal turned toward x0. Otherwise the end
    point's closest surface point is used: inside a face the exact face normal, on an edge or
    a vertex the direction from the closest point (rounded). For ``solid`` meshes (closed,
    outward wound) a point found inside is pushed out through the closest surface."""
    path = x - x0
    path_len = wp.length(path)
    if path_len > 0.0:
        dirn = path / path_len
        hit = wp.mesh_query_ray(mesh, x0, dirn, path_len)
        if hit.result:
            n = hit.normal
            if wp.dot(n, dirn) > 0.0:
                n = -n
            p = x0 + hit.t * dirn
            return d - wp.dot(x - p, n), n, p
    q = wp.mesh_query_point_no_sign(mesh, x, d)
    inside = float(1.0)  # noqa: UP018 (a Warp dynamic variable)
    if solid == 1:
        q = wp.mesh_query_point_sign_normal(mesh, x, 1.0e6)
        inside = q.sign
    if not q.result:
        return 0.0, wp.vec3(0.0), x
    c = wp.mesh_eval_position(mesh, q.face, q.u, q.v)
    fn = wp.mesh_eval_face_normal(mesh, q.face)
    delta = x - c
    dist = wp.length(delta)
    eps = 1.0e-4
    face_interior = q.u > eps and q.v > eps and 1.0 - q.u - q.v > eps
    if inside < 0.0:
        # solid and inside: push out through the closest surface point
        if face_interior or dist <= 1.0e-9 * d:
            return d - wp.dot(delta, fn), fn, c
        return d + dist, -delta / dist, c
    if dist >= d:
        return 0.0, wp.vec3(0.0), x
    if face_interior or dist <= 1.0e-9 * d:
        s = wp.dot(delta, fn)
        if s < 0.0 or (s == 0.0 and wp.dot(x0 - c, fn) < 0.0):
            fn = -fn
        return d - wp.abs(s), fn, c
    return d - dist, delta / dist, c


@wp.func
def surface_velocity(p_local: wp.vec3, pose_prev: wp.transform, pose: wp.transform, dt: float) -> wp.vec3:
    """Velocity [m/s] of the shape's material point p_local over the step."""
    return (wp.transform_point(pose, p_local) - wp.transform_point(pose_prev, p_local)) / dt


@wp.func
def apply_local_contact(
    h: float,
    n_local: wp.vec3,
    p_local: wp.vec3,
    x0_local: wp.vec3,
    x_local: wp.vec3,
    a: wp.vec3,
    x: wp.vec3,
    v: wp.vec3,
    pose_prev: wp.transform,
    pose: wp.transform,
    mode: int,
    restitution: float,
    friction: float,
    stiffness: float,
    damping_ratio: float,
    inv_mass: float,
    dt: float,
):
    """Map a local contact to world space and resolve it (no-op when h <= 0). x0_local and
    x_local: the particle at the start and end of the step in the shape's frames [m] (the start
    distance from the surface along the normal, for reflect mode), a: the step's acceleration."""
    if h <= 0.0:
        return x, v
    n = wp.transform_vector(pose, n_local)
    vs = surface_velocity(p_local, pose_prev, pose, dt)
    d0 = wp.dot(n_local, x0_local - x_local) - h
    return resolve_contact(x, v, n, h, d0, wp.dot(a, n), vs, mode, restitution, friction, stiffness, damping_ratio,
                           inv_mass, dt)


# --------------------------------------------------------------------------------------
# Finite shapes
# --------------------------------------------------------------------------------------
@wp.func
def l1_norm(u: wp.vec3) -> float:
    """|u_x| + |u_y| + |u_z| (>= the length of u, no square root)."""
    return wp.abs(u[0]) + wp.abs(u[1]) + wp.abs(u[2])


@wp.func
def out_of_reach(x: wp.vec3, x0: wp.vec3, center: wp.vec3, half: float, r: float) -> bool:
    """True when every point of the step's path [x0, x] [m] is farther than r [m] (the inflated
    radius) from every point of a segment of half length ``half`` [m] around ``center`` (all
    world, the shape static), by a margin that covers the rounding of the local test
    (``capsule_contact``: the pose transforms, ~1e-7 of the coordinates, and the ray-sphere
    discriminant's cancellation, ~1e-7 |o - c|^2 / r, |o - c|^2 <= 2 (dist^2 + reach^2)): no
    contact then, whatever the mode. Cheap: no transform, no square root (the path's length is
    bounded by its L1 norm). NaN gives False (the full test runs)."""
    e = x - center
    dist2 = wp.dot(e, e)
    reach = l1_norm(x - x0) + half + r
    margin = 1.0e-5 * (l1_norm(x) + l1_norm(center) + reach) + 2.0e-5 * (dist2 + reach * reach) / r
    bound = reach + margin
    return dist2 > bound * bound


@wp.kernel
def collide_capsule(
    inv_mass: wp.array(dtype=float),
    radius: wp.array(dtype=float),
    q_prev: wp.array(dtype=wp.vec3),
    continuous: int,
    a: wp.vec3,
    b: wp.vec3,
    shape_radius: float,
    inside: int,
    pose_prev: wp.transform,
    pose: wp.transform,
    far_center: wp.vec3,
    far_half: float,
    restitution: float,
    friction: float,
    mode: int,
    thickness: float,
    stiffness: float,
    damping_ratio: float,
    dt: float,
    forces: wp.array(dtype=wp.vec3),
    q_io: wp.array(dtype=wp.vec3),
    qd_io: wp.array(dtype=wp.vec3),
):
    """A solid capsule (segment [a, b], local) or sphere (a == b), or a spherical container
    (inside = 1, particles kept within shape_radius of a); continuous = 0 tests the end point
    alone (q_prev still gives reflect mode its start distance). far_half >= 0: the shape did not
    move over the step (pose == pose_prev), is solid, and far_center [m] (world) is the middle of
    its segment, far_half [m] half the segment's length; a particle whose whole step stays out of
    reach (``out_of_reach``) is left as it is without the local test (the same bits)."""
    collide_particle_capsule(wp.tid(), inv_mass, radius, q_prev, continuous, a, b, shape_radius, inside, pose_prev,
                             pose, far_center, far_half, restitution, friction, mode, thickness, stiffness,
                             damping_ratio, dt, forces, q_io, qd_io)


@wp.func
def collide_particle_capsule(
    i: int,
    inv_mass: wp.array(dtype=float),
    radius: wp.array(dtype=float),
    q_prev: wp.array(dtype=wp.vec3),
    continuous: int,
    a: wp.vec3,
    b: wp.vec3,
    shape_radius: float,
    inside: int,
    pose_prev: wp.transform,
    pose: wp.transform,
    far_center: wp.vec3,
    far_half: float,
    restitution: float,
    friction: float,
    mode: int,
    thickness: float,
    stiffness: float,
    damping_ratio: float,
    dt: float,
    forces: wp.array(dtype=wp.vec3),
    q_io: wp.array(dtype=wp.vec3),
    qd_io: wp.array(dtype=wp.vec3),
):
    """Particle i against the capsule (the body of ``collide_capsule``, whose docstring says the
    arguments; ``kernels/collide_lanes.py`` calls it for the lanes its filter keeps)."""
    w = inv_mass[i]
    if w == 0.0:
        return
    x = q_io[i]
    d = radius[i] + thickness
    r = shape_radius + d
    if far_half >= 0.0 and out_of_reach(x, q_prev[i], far_center, far_half, r):
        return
    v = qd_io[i]
    xl = wp.transform_point(wp.transform_inverse(pose), x)
    x0l = wp.transform_point(wp.transform_inverse(pose_prev), q_prev[i])
    if inside == 1:
        r = shape_radius - d
    x_from = x0l
    if continuous == 0:
        x_from = xl
    h, nl, pl = capsule_contact(x_from, xl, a, b, r, inside)
    x, v = apply_local_contact(h, nl, pl, x0l, xl, w * forces[i], x, v, pose_prev, pose, mode, restitution,
                               friction, stiffness, damping_ratio, w, dt)
    q_io[i] = x
    qd_io[i] = v


@wp.kernel
def collide_quad(
    inv_mass: wp.array(dtype=float),
    radius: wp.array(dtype=float),
    q_prev: wp.array(dtype=wp.vec3),
    half_x: float,
    half_z: float,
    pose_prev: wp.transform,
    pose: wp.transform,
    restitution: float,
    friction: float,
    mode: int,
    thickness: float,
    stiffness: float,
    damping_ratio: float,
    dt: float,
    forces: wp.array(dtype=wp.vec3),
    q_io: wp.array(dtype=wp.vec3),
    qd_io: wp.array(dtype=wp.vec3),
):
    """A thin two-sided rectangle (local plane y = 0) with continuous detection."""
    i = wp.tid()
    w = inv_mass[i]
    if w == 0.0:
        return
    x = q_io[i]
    v = qd_io[i]
    xl = wp.transform_point(wp.transform_inverse(pose), x)
    x0l = wp.transform_point(wp.transform_inverse(pose_prev), q_prev[i])
    h, nl, pl = quad_contact(x0l, xl, half_x, half_z, radius[i] + thickness)
    x, v = apply_local_contact(h, nl, pl, x0l, xl, w * forces[i], x, v, pose_prev, pose, mode, restitution,
                               friction, stiffness, damping_ratio, w, dt)
    q_io[i] = x
    qd_io[i] = v


@wp.kernel
def collide_mesh(
    inv_mass: wp.array(dtype=float),
    radius: wp.array(dtype=float),
    q_prev: wp.array(dtype=wp.vec3),
    mesh: wp.uint64,
    solid: int,
    pose_prev: wp.transform,
    pose: wp.transform,
    restitution: float,
    friction: float,
    mode: int,
    thickness: float,
    stiffness: float,
    damping_ratio: float,
    dt: float,
    forces: wp.array(dtype=wp.vec3),
    q_io: wp.array(dtype=wp.vec3),
    qd_io: wp.array(dtype=wp.vec3),
):
    """A triangle mesh (wp.Mesh in its local frame) with continuous detection along the step."""
    i = wp.tid()
    w = inv_mass[i]
    if w == 0.0:
        return
    x = q_io[i]
    v = qd_io[i]
    xl = wp.transform_point(wp.transform_inverse(pose), x)
    x0l = wp.transform_point(wp.transform_inverse(pose_prev), q_prev[i])
    h, nl, pl = mesh_contact(mesh, x0l, xl, radius[i] + thickness, solid)
    x, v = apply_local_contact(h, nl, pl, x0l, xl, w * forces[i], x, v, pose_prev, pose, mode, restitution,
                               friction, stiffness, damping_ratio, w, dt)
    q_io[i] = x
    qd_io[i] = v


# --------------------------------------------------------------------------------------
# Particle-particle collisions
# --------------------------------------------------------------------------------------
@wp.kernel
def count_particle_contacts(
    grid: wp.uint64,
    q: wp.array(dtype=wp.vec3),
    radius: wp.array(dtype=float),
    inv_mass: wp.array(dtype=float),
    max_radius: float,
    particle_world: wp.array(dtype=int),
    world_stride: float,
    world_side: int,
    count_out: wp.array(dtype=int),
):
    """count_out[i] = number of particles overlapping particle i (|x_j - x_i| < r_i + r_j).
    Batched worlds: only particles of i's world count; the grid holds x + world_key(world)."""
    i = wp.tid()
    x = q[i]
    ri = radius[i]
    wi = particle_world[i]
    count = int(0)  # noqa: UP018, RUF046 (a Warp dynamic variable)
    for j in wp.hash_grid_query(grid, x + world_key(wi, world_stride, world_side), ri + max_radius):
        if j != i and particle_world[j] == wi and (inv_mass[i] > 0.0 or inv_mass[j] > 0.0):
            dist = wp.length(q[j] - x)
            if dist < ri + radius[j] and dist > 0.0:
                count += 1
    count_out[i] = count


@wp.kernel
def collide_particle_pairs(
    grid: wp.uint64,
    q: wp.array(dtype=wp.vec3),
    qd: wp.array(dtype=wp.vec3),
    radius: wp.array(dtype=float),
    inv_mass: wp.array(dtype=float),
    contact_count: wp.array(dtype=int),
    max_radius: float,
    restitution: float,
    friction: float,
    separate: int,
    particle_world: wp.array(dtype=int),
    world_stride: float,
    world_side: int,
    q_out: wp.array(dtype=wp.vec3),
    qd_out: wp.array(dtype=wp.vec3),
):
    """Two-body impulses for every overlapping pair (see module docstring).

    Each pair (a, b), a < b, is evaluated with the same operands from both sides, so the
    impulses on a and b are exactly opposite: J = -(1 + c_R) u_n / (w_a + w_b) along
    n = (x_b - x_a)/|x_b - x_a| when approaching (u_n = (v_b - v_a) . n < 0), tangential
    Coulomb friction at most mu J and never reversing the relative slip. With ``separate``
    the overlap is removed, split by inverse mass (centre of mass unchanged). Every pair is
    scaled by 1 / max(contact_count[a], contact_count[b]). Batched worlds: pairs within one
    world only (see ``count_particle_contacts``)."""
    i = wp.tid()
    xi = q[i]
    ri = radius[i]
    world_i = particle_world[i]
    key = xi + world_key(world_i, world_stride, world_side)
    dv = wp.vec3(0.0)
    dx = wp.vec3(0.0)
    # Contacts are summed in ascending partner index, not in the grid's cell order: a world's cell
    # order depends on where its copy of space sits (world_key), so the same contacts of two
    # identical worlds would otherwise be added in different orders (different float rounding).
    # One grid pass per contact (plus one): contacts per particle are few.
    last = int(-1)
    searching = int(1)
    while searching == 1:
        j = int(2147483647)
        for k in wp.hash_grid_query(grid, key, ri + max_radius):
            if k > last and k < j and k != i and particle_world[k] == world_i:
                if wp.length(q[k] - xi) < ri + radius[k] and (inv_mass[i] > 0.0 or inv_mass[k] > 0.0):
                    j = k
        if j == 2147483647:
            searching = 0
            continue
        last = j
        a = wp.min(i, j)
        b = wp.max(i, j)
        wa = inv_mass[a]
        wb = inv_mass[b]
        wsum = wa + wb
        if wsum == 0.0:
            continue
        delta = q[b] - q[a]
        dist = wp.length(delta)
        reach = radius[a] + radius[b]
        if dist >= reach or dist == 0.0:
            continue
        n = delta / dist
        scale = 1.0 / float(wp.max(contact_count[a], contact_count[b]))
        rel = qd[b] - qd[a]
        un = wp.dot(rel, n)
        impulse = wp.vec3(0.0)  # impulse on b [N s]; a receives the opposite
        if un < 0.0:
            jn = -(1.0 + restitution) * un / wsum
            impulse = jn * n
            vt = rel - un * n
            vt_len = wp.length(vt)
            if vt_len > 0.0 and friction > 0.0:
                jt = wp.min(friction * jn, vt_len / wsum)
                impulse = impulse - (jt / vt_len) * vt
        push = wp.vec3(0.0)  # displacement of b per unit inverse mass; a gets the opposite
        if separate == 1:
            push = ((reach - dist) / wsum) * n
        sign = 1.0
        if i == a:
            sign = -1.0
        wi = inv_mass[i]
        dv = dv + (sign * scale * wi) * impulse
        dx = dx + (sign * scale * wi) * push
    q_out[i] = xi + dx
    qd_out[i] = qd[i] + dv
