"""Agent kernels: boids (Reynolds steering) for flyers and swimmers, and ground walkers.

One step of an agent simulation is three launches:

1. ``eval_neighbour_rules`` (one thread per agent, neighbours from a ``wp.HashGrid`` built on the
   positions at the start of the step, candidates filtered by true distance and field of view):
   the separation, alignment, cohesion and drafting steering accelerations [m/s^2], the
   upwash benefit in [0, 1] and a position correction [m] that restores hard minimum distances.
2. ``integrate_flyers`` or ``integrate_walkers``: weights the rules, adds obstacles, food, goals
   and boundaries, limits speed and steering, runs the state machine (flying, landing, resting;
   walking, climbing, fallen) and advances positions and velocities in place.
3. (for output only) ``eval_orientations``: a quaternion per agent from its heading.

Conventions: +Y is up; a steering acceleration is ``limit(desired_velocity - v, max_force)``
(Reynolds 1999) where ``desired_velocity`` has length ``max_speed``; ``max_force`` is the largest
steering acceleration [m/s^2] (unit mass). Periodic axes ("wrap") are handled by querying the
hash grid at the images of the agent, so every pair interacts through its minimum image
(needs query radius < half the box).
"""

import warp as wp

from .worlds import world_key

wp.set_module_options({"enable_backward": False})

FLYING = wp.constant(0)
RESTING = wp.constant(1)
WALKING = wp.constant(2)
CLIMBING = wp.constant(3)
FALLEN = wp.constant(4)
LANDING = wp.constant(5)

BIG = wp.constant(1.0e30)


# --------------------------------------------------------------------------------------
# Parameter and world structs
# --------------------------------------------------------------------------------------
@wp.struct
class RuleParams:
    """Neighbour rules of one agent kind (species). Lengths [m], speeds [m/s], forces [m/s^2]."""

    perception_radius: float  # alignment / cohesion / drafting neighbourhood
    separation_radius: float  # separation from agents of the same group
    separation_radius_other: float  # separation from other groups (species, strangers)
    min_distance: float  # hard minimum distance to the same group (0: off)
    min_distance_other: float  # hard minimum distance to other groups (0: off)
    query_radius: float  # max of the radii above
    fov_cos: float  # cos(field of view / 2); -1 sees all around
    max_speed: float
    max_force: float
    draft: int  # 1: look for upwash positions behind neighbours
    draft_back: float  # best distance behind the neighbour [m]
    draft_side: float  # best lateral offset from the neighbour's track [m]
    draft_width: float  # Gaussian width of the upwash benefit [m]
    draft_time: float  # time to close the gap to the upwash slot [s]


@wp.struct
class FlightParams:
    """Flight behaviour of one kind: weights, energy, resting and food."""

    min_speed: float  # flyers never go slower (stall) [m/s]
    w_separation: float
    w_alignment: float
    w_cohesion: float
    w_draft: float
    w_avoid: float
    w_food: float
    w_goal: float
    w_boundary: float
    avoid_distance: float  # obstacles closer than this are avoided [m]
    body_radius: float  # agents never get closer than this to an obstacle [m]
    min_height: float  # flyers keep this clearance above the ground [m]
    energy_max: float
    drain_rate: float  # energy used per second of flight (0: never tires)
    draft_saving: float  # fraction of drain saved at full upwash benefit
    land_threshold: float  # energy at which a flyer goes down to rest
    rest_time: float  # [s]
    descent_speed: float  # sink rate while landing [m/s]
    takeoff_speed: float  # climb rate at take-off [m/s]
    food_sense_radius: float  # food farther than this is not seen [m]
    food_eat_radius: float  # food closer than this is eaten [m]
    food_energy: float  # energy per bite
    bite_interval: float  # [s] between bites


@wp.struct
class WalkParams:
    """Ground agents: weights, slope rules, falling and recovery."""

    w_separation: float
    w_alignment: float
    w_cohesion: float
    w_avoid: float
    w_goal: float
    w_boundary: float
    avoid_distance: float  # [m]
    body_radius: float  # [m]
    arrive_radius: float  # agents stop this close to their goal [m]
    slow_radius: float  # agents slow down inside this distance of the goal [m]
    max_slope: float  # rise over run above which walking becomes climbing (0.3 = 30 %)
    climb_speed: float  # speed along the surface while climbing [m/s]
    fall_rate: float  # falls per second of climbing [1/s]
    fall_speed: float  # push off the slope when falling [m/s]
    recovery_time: float  # time lying on the ground before getting up [s]
    gravity: wp.vec3  # [m/s^2]


@wp.struct
class Space:
    """Box [lower, upper]; wrapped axes are periodic, the others have soft (steering) walls with
    a hard clamp when ``bounded``."""

    lower: wp.vec3
    upper: wp.vec3
    wrap_x: int
    wrap_y: int
    wrap_z: int
    bounded: int
    margin: float  # soft walls start steering this far inside the box [m]


@wp.struct
class Obstacles:
    """Spheres (center xyz, radius), planes (unit normal xyz, offset: n.x = offset, free side
    n.x > offset) and triangle meshes (wp.Mesh ids), indexed in that order."""

    spheres: wp.array(dtype=wp.vec4)
    planes: wp.array(dtype=wp.vec4)
    meshes: wp.array(dtype=wp.uint64)
    sphere_count: int
    plane_count: int
    count: int


@wp.struct
class TerrainData:
    """Ground height y = h(x, z): kind 0 flat at ``height``; 1 bilinear height field
    ``heights[i, k]`` at (origin_x + i spacing, origin_z + k spacing), clamped at the borders;
    2 a triangle mesh hit by a ray cast down from ``top`` (the highest surface)."""

    kind: int
    height: float
    origin_x: float
    origin_z: float
    spacing: float
    nx: int
    nz: int
    heights: wp.array2d(dtype=float)
    mesh: wp.uint64
    top: float
    bottom: float


@wp.struct
class Food:
    """Food sources: positions [m] and bites left (int; a step's bites are granted in agent order
    by :func:`grant_bites`, the same on every run and device)."""

    positions: wp.array(dtype=wp.vec3)
    amounts: wp.array(dtype=int)
    count: int


# --------------------------------------------------------------------------------------
# Small functions
# --------------------------------------------------------------------------------------
@wp.func
def limit(v: wp.vec3, max_length: float) -> wp.vec3:
    """v scaled down to length max_length if longer."""
    l = wp.length(v)
    if l > max_length:
        return v * (max_length / l)
    return v


@wp.func
def steer(direction: wp.vec3, v: wp.vec3, max_speed: float, max_force: float) -> wp.vec3:
    """Reynolds steering towards ``direction``: limit(normalize(direction) max_speed - v, max_force);
    zero when direction is zero."""
    l = wp.length(direction)
    if l <= 0.0:
        return wp.vec3(0.0)
    return limit(direction * (max_speed / l) - v, max_force)


@wp.func
def is_mobile(s: int) -> bool:
    return s == FLYING or s == LANDING or s == WALKING or s == CLIMBING


@wp.func
def terrain_sample(t: TerrainData, x: float, z: float) -> wp.vec3:
    """(h, dh/dx, dh/dz) of the ground at (x, z)."""
    if t.kind == 1:
        fx = (x - t.origin_x) / t.spacing
        fz = (z - t.origin_z) / t.spacing
        gx_on = 1.0
        gz_on = 1.0
        if fx < 0.0 or fx > float(t.nx - 1):
            gx_on = 0.0
        if fz < 0.0 or fz > float(t.nz - 1):
            gz_on = 0.0
        fx = wp.clamp(fx, 0.0, float(t.nx - 1))
        fz = wp.clamp(fz, 0.0, float(t.nz - 1))
        i0 = wp.min(int(fx), t.nx - 2)
        k0 = wp.min(int(fz), t.nz - 2)
        u = fx - float(i0)
        w = fz - float(k0)
        h00 = t.heights[i0, k0]
        h10 = t.heights[i0 + 1, k0]
        h01 = t.heights[i0, k0 + 1]
        h11 = t.heights[i0 + 1, k0 + 1]
        h = (1.0 - u) * (1.0 - w) * h00 + u * (1.0 - w) * h10 + (1.0 - u) * w * h01 + u * w * h11
        dhdu = (1.0 - w) * (h10 - h00) + w * (h11 - h01)
        dhdw = (1.0 - u) * (h01 - h00) + u * (h11 - h10)
        return wp.vec3(h, gx_on * dhdu / t.spacing, gz_on * dhdw / t.spacing)
    if t.kind == 2:
        q = wp.mesh_query_ray(t.mesh, wp.vec3(x, t.top, z), wp.vec3(0.0, -1.0, 0.0), t.top - t.bottom)
        if q.result:
            n = wp.normalize(q.normal)
            if n[1] < 0.0:
                n = -n
            if n[1] > 1.0e-6:
                return wp.vec3(t.top - q.t, -n[0] / n[1], -n[2] / n[1])
            return wp.vec3(t.top - q.t, 0.0, 0.0)
        return wp.vec3(t.height, 0.0, 0.0)
    return wp.vec3(t.height, 0.0, 0.0)


@wp.func
def obstacle_distance(obs: Obstacles, k: int, x: wp.vec3, max_dist: float) -> wp.vec4:
    """(outward unit normal xyz, signed distance [m]) from obstacle k to x; meshes farther than
    max_dist report max_dist."""
    if k < obs.sphere_count:
        s = obs.spheres[k]
        d = x - wp.vec3(s[0], s[1], s[2])
        l = wp.length(d)
        n = wp.vec3(0.0, 1.0, 0.0)
        if l > 0.0:
            n = d / l
        return wp.vec4(n[0], n[1], n[2], l - s[3])
    kp = k - obs.sphere_count
    if kp < obs.plane_count:
        p = obs.planes[kp]
        n = wp.vec3(p[0], p[1], p[2])
        return wp.vec4(p[0], p[1], p[2], wp.dot(n, x) - p[3])
    m = obs.meshes[kp - obs.plane_count]
    q = wp.mesh_query_point_sign_normal(m, x, max_dist)
    if q.result:
        cp = wp.mesh_eval_position(m, q.face, q.u, q.v)
        d = x - cp
        l = wp.length(d)
        n = wp.mesh_eval_face_normal(m, q.face)
        if l > 1.0e-6:
            n = d * (q.sign / l)
        return wp.vec4(n[0], n[1], n[2], l * q.sign)
    return wp.vec4(0.0, 1.0, 0.0, max_dist)


@wp.func
def avoid_obstacles(obs: Obstacles, x: wp.vec3, v: wp.vec3, avoid_distance: float, body_radius: float,
                    max_force: float) -> wp.vec3:
    """Obstacle avoidance [m/s^2]: for each obstacle nearer than body_radius + avoid_distance, a
    push of strength s = max_force (1 - clearance / avoid_distance) along its outward normal n
    and, while approaching (v . n < 0), s along the tangential part of v (a perpendicular of n
    for a head-on approach) so that the agent turns aside instead of stalling."""
    a = wp.vec3(0.0)
    reach = body_radius + avoid_distance
    for k in range(obs.count):
        nd = obstacle_distance(obs, k, x, reach)
        if nd[3] < reach:
            n = wp.vec3(nd[0], nd[1], nd[2])
            s = max_force * (1.0 - wp.max(nd[3] - body_radius, 0.0) / avoid_distance)
            a = a + n * s
            vn = wp.dot(v, n)
            if vn < 0.0:
                t = v - vn * n
                if wp.length(t) < 1.0e-3 * wp.length(v):
                    t = wp.cross(n, wp.vec3(0.0, 1.0, 0.0))
                    if wp.length(t) < 1.0e-6:
                        t = wp.cross(n, wp.vec3(1.0, 0.0, 0.0))
                a = a + wp.normalize(t) * s
    return a


@wp.func
def resolve_obstacles_position(obs: Obstacles, x: wp.vec3, body_radius: float) -> wp.vec3:
    """x moved out of every obstacle to at least body_radius from its surface (one pass)."""
    y = x
    for k in range(obs.count):
        nd = obstacle_distance(obs, k, y, body_radius + 1.0)
        if nd[3] < body_radius:
            y = y + wp.vec3(nd[0], nd[1], nd[2]) * (body_radius - nd[3])
    return y


@wp.func
def resolve_obstacles_velocity(obs: Obstacles, x: wp.vec3, v: wp.vec3, body_radius: float) -> wp.vec3:
    """v without its component into obstacles the agent at x touches."""
    u = v
    for k in range(obs.count):
        nd = obstacle_distance(obs, k, x, body_radius + 1.0)
        if nd[3] < body_radius * 1.001 + 1.0e-5:
            n = wp.vec3(nd[0], nd[1], nd[2])
            vn = wp.dot(u, n)
            if vn < 0.0:
                u = u - vn * n
    return u


@wp.func
def boundary_steer(space: Space, x: wp.vec3, max_force: float) -> wp.vec3:
    """Soft walls on the bounded, non-wrapped axes: max_force times the depth into the margin
    (as a fraction of the margin), pointing into the box."""
    a = wp.vec3(0.0)
    if space.bounded == 0:
        return a
    wraps = wp.vec3i(space.wrap_x, space.wrap_y, space.wrap_z)
    for ax in range(3):
        if wraps[ax] == 0:
            lo = space.lower[ax] + space.margin
            hi = space.upper[ax] - space.margin
            if x[ax] < lo:
                a[ax] = max_force * wp.min((lo - x[ax]) / space.margin, 1.0)
            elif x[ax] > hi:
                a[ax] = -max_force * wp.min((x[ax] - hi) / space.margin, 1.0)
    return a


@wp.func
def wrap_position(space: Space, x: wp.vec3) -> wp.vec3:
    """x mapped into [lower, upper) on wrapped axes and clamped on bounded ones."""
    y = x
    wraps = wp.vec3i(space.wrap_x, space.wrap_y, space.wrap_z)
    for ax in range(3):
        length = space.upper[ax] - space.lower[ax]
        if wraps[ax] != 0:
            r = y[ax] - space.lower[ax]
            y[ax] = space.lower[ax] + r - length * wp.floor(r / length)
        elif space.bounded != 0:
            y[ax] = wp.clamp(y[ax], space.lower[ax], space.upper[ax])
    return y


@wp.func
def clamp_velocity_to_box(space: Space, x: wp.vec3, v: wp.vec3) -> wp.vec3:
    """v without outward components on bounded axes where x sits on a wall."""
    u = v
    if space.bounded == 0:
        return u
    wraps = wp.vec3i(space.wrap_x, space.wrap_y, space.wrap_z)
    for ax in range(3):
        if wraps[ax] == 0:
            if x[ax] <= space.lower[ax] and u[ax] < 0.0:
                u[ax] = 0.0
            if x[ax] >= space.upper[ax] and u[ax] > 0.0:
                u[ax] = 0.0
    return u


@wp.func
def nearest_food(food: Food, x: wp.vec3, radius: float, start: int) -> int:
    """Index of the nearest food source with bites left closer than radius, or -1; the sources
    searched are ``start .. start + food.count`` (batched worlds: one block per world)."""
    best = int(-1)  # noqa: RUF046, UP018
    best_d = radius
    for k in range(start, start + food.count):
        if food.amounts[k] > 0:
            d = wp.length(food.positions[k] - x)
            if d < best_d:
                best_d = d
                best = k
    return best


# --------------------------------------------------------------------------------------
# Neighbour rules
# --------------------------------------------------------------------------------------
@wp.kernel
def eval_neighbour_rules(
    grid: wp.uint64,
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    kind: wp.array(dtype=int),
    group: wp.array(dtype=int),
    state: wp.array(dtype=int),
    rules: wp.array(dtype=RuleParams),
    space: Space,
    lookahead: float,
    agent_world: wp.array(dtype=int),
    world_stride: float,
    world_side: int,
    separation_out: wp.array(dtype=wp.vec3),
    alignment_out: wp.array(dtype=wp.vec3),
    cohesion_out: wp.array(dtype=wp.vec3),
    draft_out: wp.array(dtype=wp.vec3),
    benefit_out: wp.array(dtype=float),
    push_out: wp.array(dtype=wp.vec3),
    neighbours_out: wp.array(dtype=int),
):
    """Steering of agent i from its neighbours j != i (minimum image on wrapped axes).

    Visible: |d| < query radius and (no heading or fov_cos = -1 or heading . d >= fov_cos |d|),
    d = x_j - x_i. Separation: limit(max_force sum (1 - |d| / r) (-d / |d|), max_force) over
    visible j (any state) within the separation radius r of j's relation (same group or other):
    graded, full strength at contact. Alignment and cohesion: Reynolds steering towards the mean
    velocity and the mean d of visible mobile same-group j within the perception radius. Drafting (same
    neighbours, those ahead of i along their own heading h_j): benefit = max exp(-((b - b0)^2 +
    (s - s0)^2) / (2 w^2)) with b the distance behind j and s the lateral offset; steering
    limit(v_j + (slot - x_i) / draft_time - v_i, max_force) towards the nearest slot
    x_j - b0 h_j + s0 (side of i). Push (hard minimum distance d_min of the relation, no
    field-of-view filter): with the pair's offset predicted ``lookahead`` [s] ahead,
    p = d + (v_j - v_i) lookahead, the sum of 0.5 (d_min - |p|) (-p / |p|) over j with |p| < d_min.

    Threads take agents in the grid's cell order (``hash_grid_point_id``), so neighbouring threads
    query the same cells and read the same neighbours (coherent gathers; each agent's result is
    unchanged).

    Batched worlds: agents only see agents of their own world ``agent_world``; the grid holds each
    world's agents moved by ``worlds.world_key`` (``world_stride`` [m] apart on a cube of side
    ``world_side``; stride 0: one world), so a query meets its own world's cells."""
    i = wp.hash_grid_point_id(grid, wp.tid())
    p = rules[kind[i]]
    xi = x[i]
    vi = v[i]
    gi = group[i]
    zero = wp.vec3(0.0)
    if not is_mobile(state[i]):
        separation_out[i] = zero
        alignment_out[i] = zero
        cohesion_out[i] = zero
        draft_out[i] = zero
        benefit_out[i] = 0.0
        push_out[i] = zero
        neighbours_out[i] = 0
        return

    speed = wp.length(vi)
    heading = zero
    use_fov = False
    if speed > 1.0e-6 and p.fov_cos > -1.0:
        heading = vi / speed
        use_fov = True
    rq = p.query_radius
    box = space.upper - space.lower

    sep = wp.vec3(0.0)
    ali = wp.vec3(0.0)
    coh = wp.vec3(0.0)
    push = wp.vec3(0.0)
    n_same = int(0)  # noqa: RUF046, UP018 (a dynamic Warp variable)
    benefit = float(0.0)  # noqa: UP018
    best_slot = float(BIG)
    slot_rel = wp.vec3(0.0)
    lead_v = wp.vec3(0.0)
    up = wp.vec3(0.0, 1.0, 0.0)

    for sx in range(-space.wrap_x, space.wrap_x + 1):
        for sy in range(-space.wrap_y, space.wrap_y + 1):
            for sz in range(-space.wrap_z, space.wrap_z + 1):
                q = xi + wp.vec3(float(sx) * box[0], float(sy) * box[1], float(sz) * box[2])
                if sx != 0 or sy != 0 or sz != 0:
                    # skip images whose query ball misses the box
                    if q[0] < space.lower[0] - rq or q[0] > space.upper[0] + rq:
                        continue
                    if q[1] < space.lower[1] - rq or q[1] > space.upper[1] + rq:
                        continue
                    if q[2] < space.lower[2] - rq or q[2] > space.upper[2] + rq:
                        continue
                key = world_key(agent_world[i], world_stride, world_side)
                query = wp.hash_grid_query(grid, q + key, rq)
                j = int(0)  # noqa: RUF046, UP018
                while wp.hash_grid_query_next(query, j):
                    if j == i or agent_world[j] != agent_world[i]:
                        continue
                    d = x[j] - q
                    dist = wp.length(d)
                    if dist >= rq or dist <= 0.0:
                        continue
                    same = group[j] == gi
                    d_min = p.min_distance_other
                    if same:
                        d_min = p.min_distance
                    if d_min > 0.0:
                        dp = d + (v[j] - vi) * lookahead
                        dpl = wp.length(dp)
                        if dpl < d_min and dpl > 0.0:
                            push = push - dp * (0.5 * (d_min - dpl) / dpl)
                    if use_fov and wp.dot(heading, d) < p.fov_cos * dist:
                        continue
                    r_sep = p.separation_radius_other
                    if same:
                        r_sep = p.separation_radius
                    if dist < r_sep:
                        sep = sep - d * ((1.0 - dist / r_sep) / dist)
                    if same and dist < p.perception_radius and is_mobile(state[j]):
                        vj = v[j]
                        ali = ali + vj
                        coh = coh + d
                        n_same += 1
                        sj = wp.length(vj)
                        if p.draft != 0 and sj > 1.0e-6:
                            hj = vj / sj
                            a = -wp.dot(d, hj)  # along hj from x_j to x_i; < 0 behind j
                            back = -a
                            if back > 0.0:
                                lat_v = -d - a * hj
                                lat = wp.length(lat_v)
                                side = wp.vec3(0.0)
                                if lat > 1.0e-6:
                                    side = lat_v / lat
                                else:
                                    side = wp.cross(hj, up)
                                    if wp.length(side) < 1.0e-6:
                                        side = wp.vec3(1.0, 0.0, 0.0)
                                    side = wp.normalize(side)
                                db = back - p.draft_back
                                ds = lat - p.draft_side
                                benefit = wp.max(
                                    benefit, wp.exp(-(db * db + ds * ds) / (2.0 * p.draft_width * p.draft_width))
                                )
                                rel = d - p.draft_back * hj + p.draft_side * side
                                rl = wp.length(rel)
                                if rl < best_slot:
                                    best_slot = rl
                                    slot_rel = rel
                                    lead_v = vj

    separation_out[i] = limit(sep * p.max_force, p.max_force)
    if n_same > 0:
        inv = 1.0 / float(n_same)
        alignment_out[i] = steer(ali * inv, vi, p.max_speed, p.max_force)
        cohesion_out[i] = steer(coh * inv, vi, p.max_speed, p.max_force)
    else:
        alignment_out[i] = zero
        cohesion_out[i] = zero
    if best_slot < BIG:
        draft_out[i] = limit(lead_v + slot_rel / p.draft_time - vi, p.max_force)
    else:
        draft_out[i] = zero
    benefit_out[i] = benefit
    push_out[i] = push
    neighbours_out[i] = n_same


# --------------------------------------------------------------------------------------
# Flyers and swimmers
# --------------------------------------------------------------------------------------
@wp.kernel
def integrate_flyers(
    rules: wp.array(dtype=RuleParams),
    flight: wp.array(dtype=FlightParams),
    space: Space,
    obstacles: Obstacles,
    terrain: TerrainData,
    food: Food,
    kind: wp.array(dtype=int),
    separation: wp.array(dtype=wp.vec3),
    alignment: wp.array(dtype=wp.vec3),
    cohesion: wp.array(dtype=wp.vec3),
    draft: wp.array(dtype=wp.vec3),
    benefit: wp.array(dtype=float),
    push: wp.array(dtype=wp.vec3),
    goals: wp.array(dtype=wp.vec3),
    dt: float,
    agent_world: wp.array(dtype=int),
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    state: wp.array(dtype=int),
    energy: wp.array(dtype=float),
    timer: wp.array(dtype=float),
    bite_timer: wp.array(dtype=float),
    bites: wp.array(dtype=int),
    heading: wp.array(dtype=wp.vec3),
    bite_request_out: wp.array(dtype=int),
):
    """Advance agent i by dt (in place).

    FLYING: a = sum of weighted rules + food (seek the nearest food with bites left within the
    sense radius while energy < energy_max) + goal + obstacles + soft walls, limited to
    max_force; speed kept in [min_speed, max_speed]; energy drains at drain_rate (1 -
    draft_saving benefit); at energy <= land_threshold the agent turns LANDING: it keeps
    separation and obstacles, halves its horizontal speed and sinks at descent_speed; touching
    the ground + min_height it is RESTING for rest_time (energy refills at energy_max /
    rest_time), then takes off along its heading at takeoff_speed with full energy. Eating: one
    bite from the nearest stocked source within the eat radius every bite_interval while
    energy < energy_max, adding food_energy. Food amounts are only read here (a snapshot of the
    step's start): bite_request_out[i] = 2 kf + (1 if the agent turned LANDING this step), or -1,
    asks for a bite of source kf, and :func:`grant_bites` grants them in agent order."""
    i = wp.tid()
    bite_request_out[i] = -1
    k = kind[i]
    p = rules[k]
    f = flight[k]
    s = state[i]
    xi = x[i]
    vi = v[i]

    if s == RESTING:
        g = terrain_sample(terrain, xi[0], xi[2])
        t = timer[i] - dt
        e = wp.min(energy[i] + f.energy_max / f.rest_time * dt, f.energy_max)
        if t < 0.5 * dt:
            h = heading[i]
            hh = wp.vec3(h[0], 0.0, h[2])
            if wp.length(hh) > 1.0e-6:
                hh = wp.normalize(hh)
            state[i] = FLYING
            e = f.energy_max
            t = 0.0
            v[i] = hh * f.min_speed + wp.vec3(0.0, f.takeoff_speed, 0.0)
            x[i] = wp.vec3(xi[0], g[0] + f.min_height, xi[2])
        else:
            v[i] = wp.vec3(0.0)
            x[i] = wp.vec3(xi[0], g[0], xi[2])
        timer[i] = t
        energy[i] = e
        return

    a = wp.vec3(0.0)
    if s == FLYING:
        a = (f.w_separation * separation[i] + f.w_alignment * alignment[i] + f.w_cohesion * cohesion[i]
             + f.w_draft * draft[i])
        if food.count > 0 and f.food_sense_radius > 0.0 and energy[i] < f.energy_max:
            kf = nearest_food(food, xi, f.food_sense_radius, agent_world[i] * food.count)
            if kf >= 0:
                a = a + f.w_food * steer(food.positions[kf] - xi, vi, p.max_speed, p.max_force)
        if f.w_goal > 0.0:
            a = a + f.w_goal * steer(goals[i] - xi, vi, p.max_speed, p.max_force)
    else:  # LANDING
        desired = wp.vec3(0.5 * vi[0], -f.descent_speed, 0.5 * vi[2])
        a = f.w_separation * separation[i] + limit(desired - vi, p.max_force)
    if obstacles.count > 0:
        a = a + f.w_avoid * avoid_obstacles(obstacles, xi, vi, f.avoid_distance, f.body_radius, p.max_force)
    wall = boundary_steer(space, xi, p.max_force)
    if s == LANDING:
        wall[1] = 0.0  # the floor of the box must not hold a landing agent up
    a = a + f.w_boundary * wall
    g0 = terrain_sample(terrain, xi[0], xi[2])
    if s == FLYING and f.avoid_distance > 0.0:
        clearance = xi[1] - g0[0] - f.min_height
        if clearance < f.avoid_distance:
            a[1] = a[1] + f.w_avoid * p.max_force * (1.0 - wp.max(clearance, 0.0) / f.avoid_distance)
    a = limit(a, p.max_force)

    vn = vi + a * dt
    sp = wp.length(vn)
    if sp > p.max_speed:
        vn = vn * (p.max_speed / sp)
    if s == FLYING and sp < f.min_speed:
        if sp > 1.0e-6:
            vn = vn * (f.min_speed / sp)
        else:
            vn = heading[i] * f.min_speed
    xn = xi + vn * dt + push[i]
    if obstacles.count > 0:
        xn = resolve_obstacles_position(obstacles, xn, f.body_radius)
        vn = resolve_obstacles_velocity(obstacles, xn, vn, f.body_radius)
    xn = wrap_position(space, xn)
    vn = clamp_velocity_to_box(space, xn, vn)

    g = terrain_sample(terrain, xn[0], xn[2])
    if s == LANDING and xn[1] <= g[0] + f.min_height:
        xn = wp.vec3(xn[0], g[0], xn[2])
        vn = wp.vec3(0.0)
        s = RESTING
        timer[i] = f.rest_time
    elif xn[1] < g[0] + f.min_height:
        xn[1] = g[0] + f.min_height
        vn[1] = max(vn[1], 0.0)

    e = wp.max(energy[i] - f.drain_rate * (1.0 - f.draft_saving * benefit[i]) * dt, 0.0)
    bt = bite_timer[i] - dt
    kf = int(-1)
    if food.count > 0 and bt <= 0.0 and e < f.energy_max:
        kf = nearest_food(food, xn, f.food_eat_radius, agent_world[i] * food.count)
    bite_timer[i] = wp.max(bt, 0.0)
    landed = int(0)
    if s == FLYING and f.drain_rate > 0.0 and e <= f.land_threshold:
        s = LANDING
        landed = 1
    if kf >= 0:
        bite_request_out[i] = 2 * kf + landed

    if wp.length(vn) > 1.0e-6:
        heading[i] = wp.normalize(vn)
    energy[i] = e
    state[i] = s
    x[i] = xn
    v[i] = vn


@wp.kernel
def key_bite_requests(request: wp.array(dtype=int), food_total: int, requests_io: wp.array(dtype=int),
                      keys_out: wp.array(dtype=int), ids_out: wp.array(dtype=int)):
    """Per agent i: key = the requested source (food_total when none, so it sorts last), id = i;
    requests_io[source] += 1 (integer counts: order-free)."""
    i = wp.tid()
    key = food_total
    r = request[i]
    if r >= 0:
        key = r / 2
        wp.atomic_add(requests_io, key, 1)
    keys_out[i] = key
    ids_out[i] = i


@wp.kernel
def grant_bites(
    flight: wp.array(dtype=FlightParams),
    kind: wp.array(dtype=int),
    keys: wp.array(dtype=int),
    ids: wp.array(dtype=int),
    request: wp.array(dtype=int),
    first_request: wp.array(dtype=int),
    amounts: wp.array(dtype=int),
    energy: wp.array(dtype=float),
    bite_timer: wp.array(dtype=float),
    bites: wp.array(dtype=int),
    state: wp.array(dtype=int),
):
    """Requests sorted by source, then agent index (a stable sort of ``key_bite_requests``'s pairs;
    first_request = exclusive prefix sum of the per-source counts): the r-th requester of a source
    gets a bite when r < its bites left, so the lowest-index agents eat first on every device. A
    bite adds food_energy (capped at energy_max), counts in ``bites`` and restarts the bite timer;
    an agent that turned LANDING this step and is above land_threshold after the bite flies on."""
    s = wp.tid()
    kf = keys[s]
    if kf >= amounts.shape[0]:
        return
    if s - first_request[kf] >= amounts[kf]:
        return
    i = ids[s]
    f = flight[kind[i]]
    e = wp.min(energy[i] + f.food_energy, f.energy_max)
    energy[i] = e
    bites[i] = bites[i] + 1
    bite_timer[i] = f.bite_interval
    if request[i] % 2 == 1 and e > f.land_threshold:
        state[i] = FLYING


@wp.kernel
def consume_food(requests: wp.array(dtype=int), amounts_io: wp.array(dtype=int)):
    """Bites left -= the bites granted (min(requests, bites left))."""
    k = wp.tid()
    amounts_io[k] = amounts_io[k] - wp.min(requests[k], amounts_io[k])


# --------------------------------------------------------------------------------------
# Ground agents
# --------------------------------------------------------------------------------------
@wp.kernel
def integrate_walkers(
    rules: wp.array(dtype=RuleParams),
    walk: WalkParams,
    space: Space,
    obstacles: Obstacles,
    terrain: TerrainData,
    kind: wp.array(dtype=int),
    separation: wp.array(dtype=wp.vec3),
    alignment: wp.array(dtype=wp.vec3),
    cohesion: wp.array(dtype=wp.vec3),
    push: wp.array(dtype=wp.vec3),
    goals: wp.array(dtype=wp.vec3),
    seed: int,
    step: wp.array(dtype=int),
    dt: float,
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    state: wp.array(dtype=int),
    timer: wp.array(dtype=float),
    heading: wp.array(dtype=wp.vec3),
):
    """Advance ground agent i by dt (in place); every quantity below is horizontal (xz).

    WALKING/CLIMBING: a = weighted rules + goal (arrive: desired speed max_speed min(1, dist /
    slow_radius), zero inside arrive_radius) + obstacles + soft walls, limited to max_force;
    speed <= max_speed. The move (velocity dt + push) is tested against the terrain: if its rise
    over run exceeds max_slope the agent CLIMBS: the move is shortened so that the speed along
    the surface is at most climb_speed, and it falls with probability 1 - exp(-fall_rate dt)
    (random stream (seed, step, i)). Otherwise it WALKS. y follows the ground.
    FALLEN: a particle under gravity; on the ground it slides (normal velocity removed) where
    the slope exceeds max_slope, else stops and lies for recovery_time, then walks again."""
    i = wp.tid()
    p = rules[kind[i]]
    s = state[i]
    xi = x[i]
    vi = v[i]
    zero = wp.vec3(0.0)

    if s == FALLEN:
        t = timer[i]
        if t >= 0.0:  # lying on the ground
            t = t - dt
            if t < 0.5 * dt:
                state[i] = WALKING
                t = 0.0
            timer[i] = t
            v[i] = zero
            return
        vn = vi + walk.gravity * dt
        xn = xi + vn * dt
        if obstacles.count > 0:
            xn = resolve_obstacles_position(obstacles, xn, walk.body_radius)
            vn = resolve_obstacles_velocity(obstacles, xn, vn, walk.body_radius)
        xn = wrap_position(space, xn)
        vn = clamp_velocity_to_box(space, xn, vn)
        g = terrain_sample(terrain, xn[0], xn[2])
        if xn[1] <= g[0]:
            xn[1] = g[0]
            if g[1] * g[1] + g[2] * g[2] > walk.max_slope * walk.max_slope:
                n = wp.normalize(wp.vec3(-g[1], 1.0, -g[2]))
                vd = wp.dot(vn, n)
                if vd < 0.0:
                    vn = vn - vd * n
            else:
                vn = zero
                timer[i] = walk.recovery_time
        x[i] = xn
        v[i] = vn
        return

    vh = wp.vec3(vi[0], 0.0, vi[2])
    a = (walk.w_separation * separation[i] + walk.w_alignment * alignment[i]
         + walk.w_cohesion * cohesion[i])
    to_goal = goals[i] - xi
    to_goal[1] = 0.0
    dist = wp.length(to_goal)
    desired = zero
    if dist > walk.arrive_radius:
        desired = to_goal * (p.max_speed * wp.min(1.0, dist / walk.slow_radius) / dist)
    a = a + walk.w_goal * limit(desired - vh, p.max_force)
    if obstacles.count > 0:
        a = a + walk.w_avoid * avoid_obstacles(obstacles, xi, vh, walk.avoid_distance, walk.body_radius, p.max_force)
    a = a + walk.w_boundary * boundary_steer(space, xi, p.max_force)
    a[1] = 0.0
    vh = limit(vh + limit(a, p.max_force) * dt, p.max_speed)

    ph = push[i]
    ph[1] = 0.0
    move = vh * dt + ph
    g0 = terrain_sample(terrain, xi[0], xi[2])
    new_state = WALKING
    run = wp.length(move)
    if run > 1.0e-7:
        g1 = terrain_sample(terrain, xi[0] + move[0], xi[2] + move[2])
        slope = (g1[0] - g0[0]) / run
        if wp.abs(slope) > walk.max_slope:
            new_state = CLIMBING
            # shorten the move until its length along the surface is at most climb_speed dt
            along = wp.sqrt(run * run + (g1[0] - g0[0]) * (g1[0] - g0[0]))
            for _it in range(4):
                if along > walk.climb_speed * dt:
                    scale = walk.climb_speed * dt / along
                    move = move * scale
                    vh = vh * scale
                    g1 = terrain_sample(terrain, xi[0] + move[0], xi[2] + move[2])
                    rl = wp.length(move)
                    along = wp.sqrt(rl * rl + (g1[0] - g0[0]) * (g1[0] - g0[0]))
            rng = wp.rand_init(seed, step[0] * x.shape[0] + i)
            if wp.randf(rng) < 1.0 - wp.exp(-walk.fall_rate * dt):
                down = wp.vec3(-g0[1], 0.0, -g0[2])
                if wp.length(down) > 1.0e-6:
                    down = wp.normalize(down)
                state[i] = FALLEN
                timer[i] = -1.0
                v[i] = down * walk.fall_speed
                x[i] = wp.vec3(xi[0], g0[0] + 1.0e-3, xi[2])
                return
    xn = xi + move
    if obstacles.count > 0:
        xn = resolve_obstacles_position(obstacles, xn, walk.body_radius)
    xn = wrap_position(space, xn)
    g = terrain_sample(terrain, xn[0], xn[2])
    xn[1] = g[0]
    if wp.length(vh) > 1.0e-6:
        heading[i] = wp.normalize(vh)
    v[i] = wp.vec3(vh[0], (xn[1] - xi[1]) / dt, vh[2])
    x[i] = xn
    state[i] = new_state


@wp.kernel
def advance_counter(counter: wp.array(dtype=int)):
    counter[0] = counter[0] + 1


# --------------------------------------------------------------------------------------
# Output and queries
# --------------------------------------------------------------------------------------
@wp.kernel
def eval_orientations(heading: wp.array(dtype=wp.vec3), state: wp.array(dtype=int), upright: int,
                      q_out: wp.array(dtype=wp.quat)):
    """Quaternion (x, y, z, w) turning the prototype's +Z axis to the heading with +Y kept up.
    upright = 1 (walkers): yaw only; FALLEN agents are tipped 90 degrees to lie along the heading."""
    i = wp.tid()
    f = heading[i]
    if upright != 0:
        f = wp.vec3(f[0], 0.0, f[2])
    if wp.length(f) < 1.0e-6:
        f = wp.vec3(0.0, 0.0, 1.0)
    f = wp.normalize(f)
    up = wp.vec3(0.0, 1.0, 0.0)
    r = wp.cross(up, f)
    if wp.length(r) < 1.0e-6:
        r = wp.vec3(1.0, 0.0, 0.0)
    r = wp.normalize(r)
    u = wp.cross(f, r)
    q = wp.quat_from_matrix(wp.matrix_from_cols(r, u, f))
    if upright != 0 and state[i] == FALLEN:
        # lie down: the body's +Y goes to the heading, its +Z to -up
        q = wp.quat_from_matrix(wp.matrix_from_cols(r, f, -up))
    q_out[i] = q


@wp.kernel
def sample_terrain(terrain: TerrainData, points: wp.array(dtype=wp.vec3), out: wp.array(dtype=wp.vec3)):
    """out[i] = (h, dh/dx, dh/dz) at points[i] (x, z)."""
    i = wp.tid()
    pt = points[i]
    out[i] = terrain_sample(terrain, pt[0], pt[2])


@wp.kernel
def eval_obstacle_distance(obstacles: Obstacles, points: wp.array(dtype=wp.vec3), max_dist: float,
                           out: wp.array(dtype=float)):
    """out[i] = smallest signed distance [m] from points[i] to any obstacle (max_dist if none nearer)."""
    i = wp.tid()
    best = max_dist
    for k in range(obstacles.count):
        nd = obstacle_distance(obstacles, k, points[i], max_dist)
        best = wp.min(best, nd[3])
    out[i] = best
