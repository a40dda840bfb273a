"""Cloth "lanes" step: eight particles a thread, their spring sums in SIMD lanes.

A block is eight particles whose CSR spring rows have the same neighbour pattern: entry k of
each row joins particle p to p + delta_k. Thread b handles block b: for every entry k it loads
the eight neighbours' positions and velocities into ``lane8`` vectors (consecutive particles
from the planar copies ``px .. pvz`` as contiguous loads, other blocks per lane), evaluates the
eight springs with vector arithmetic and adds them to eight running sums, in row order. Each
lane does ``damped_spring_force``'s operations on its own particle's entry (the force on end i
of a spring is bit-exactly minus the one on end j), and the rows are summed in the model's CSR
order, so the step gives the "scatter" and "owner" modes' bits. Padding lanes repeat a real
particle of the block and write the same values.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})

LANES = 8
ROW_MAX = 12  # longest CSR row a block handles (the entry loop is unrolled this many times)

lane8 = wp.types.vector(length=LANES, dtype=wp.float32)
lane8i = wp.types.vector(length=LANES, dtype=wp.int32)


@wp.func
def load_run(a: wp.array(dtype=float), base: int) -> lane8:
    """a[base .. base + 7] (base >= 0: the index needs no wrap-around test, so the loads merge)."""
    r = lane8()
    for c in range(LANES):
        r[c] = a[base + c]
    return r


@wp.func
def load_lanes(a: wp.array(dtype=float), pp: lane8i, delta: int) -> lane8:
    """a[pp[c] + delta] for the eight lanes c."""
    r = lane8()
    for c in range(LANES):
        r[c] = a[wp.max(pp[c] + delta, 0)]
    return r


@wp.func
def lane_spring_forces(ux: lane8, uy: lane8, uz: lane8, wx: lane8, wy: lane8, wz: lane8,
                       rest: lane8, k: lane8, kd: lane8):
    """Eight springs' forces on their end i [N] from u = x_i - x_j, w = v_i - v_j: the operations
    of ``damped_spring_force`` lane by lane (zero where |u| < 1e-12)."""
    l2 = wp.cw_mul(ux, ux) + wp.cw_mul(uy, uy) + wp.cw_mul(uz, uz)
    l = lane8()
    for c in range(LANES):
        l[c] = wp.sqrt(l2[c])
    dx = wp.cw_div(ux, l)
    dy = wp.cw_div(uy, l)
    dz = wp.cw_div(uz, l)
    dldt = wp.cw_mul(wx, dx) + wp.cw_mul(wy, dy) + wp.cw_mul(wz, dz)
    m = -(wp.cw_mul(k, l - rest) + wp.cw_mul(kd, dldt))
    gx = wp.cw_mul(m, dx)
    gy = wp.cw_mul(m, dy)
    gz = wp.cw_mul(m, dz)
    for c in range(LANES):
        small = l[c] < 1.0e-12
        gx[c] = wp.where(small, 0.0, gx[c])
        gy[c] = wp.where(small, 0.0, gy[c])
        gz[c] = wp.where(small, 0.0, gz[c])
    return gx, gy, gz


@wp.kernel
def pack_planar(q: wp.array(dtype=wp.vec3), qd: wp.array(dtype=wp.vec3), count: int,
                px: wp.array(dtype=lane8), py: wp.array(dtype=lane8), pz: wp.array(dtype=lane8),
                pvx: wp.array(dtype=lane8), pvy: wp.array(dtype=lane8), pvz: wp.array(dtype=lane8)):
    """Planar copies of positions and velocities (per component, eight particles an entry) of
    particles 8t .. 8t + 7 (the last of ``count`` repeated past the end)."""
    t = wp.tid()
    x = lane8()
    y = lane8()
    z = lane8()
    vx = lane8()
    vy = lane8()
    vz = lane8()
    for c in range(LANES):
        i = wp.min(LANES * wp.max(t, 0) + c, count - 1)
        a = q[i]
        v = qd[i]
        x[c] = a[0]
        y[c] = a[1]
        z[c] = a[2]
        vx[c] = v[0]
        vy[c] = v[1]
        vz[c] = v[2]
    px[t] = x
    py[t] = y
    pz[t] = z
    pvx[t] = vx
    pvy[t] = vy
    pvz[t] = vz


@wp.kernel
def pack_lane_params(slot_springs: wp.array(dtype=lane8i), rest: wp.array(dtype=float),
                     stiffness: wp.array(dtype=float), damping: wp.array(dtype=float),
                     slot_params: wp.array(dtype=lane8)):
    """Slot a's eight springs' (rest [m], k [N/m], kd [N s/m]) from the model's arrays into
    slot_params[3a .. 3a + 2] (refreshed each frame, so changes in place take effect)."""
    a = wp.tid()
    ss = slot_springs[a]
    r = lane8()
    k = lane8()
    kd = lane8()
    for c in range(LANES):
        s = ss[c]
        r[c] = rest[s]
        k[c] = stiffness[s]
        kd[c] = damping[s]
    slot_params[3 * a] = r
    slot_params[3 * a + 1] = k
    slot_params[3 * a + 2] = kd


@wp.func
def step_lane(i: int, x: wp.vec3, v: wp.vec3, f: wp.vec3, f_ext: wp.array(dtype=wp.vec3), use_f_ext: int,
              inv_mass: wp.array(dtype=float), gravity: wp.vec3, h: float,
              q_out: wp.array(dtype=wp.vec3), qd_out: wp.array(dtype=wp.vec3)):
    """Particle i's update from its spring sum f [N], the operations of ``step_cloth_owned``
    (f_ext added first where used; a pinned particle keeps its velocity)."""
    w = inv_mass[i]
    if w > 0.0:
        if use_f_ext != 0:
            f = f_ext[i] + f
        v = v + h * (w * f + gravity)
    qd_out[i] = v
    q_out[i] = x + h * v


@wp.func
def load_state_run(px: wp.array(dtype=float), py: wp.array(dtype=float), pz: wp.array(dtype=float),
                   pvx: wp.array(dtype=float), pvy: wp.array(dtype=float), pvz: wp.array(dtype=float),
                   pp: lane8i, delta: int):
    """Planar positions and velocities of particles pp[0] + delta + c, c = 0 .. 7 (contiguous)."""
    base = wp.max(pp[0] + delta, 0)
    return (load_run(px, base), load_run(py, base), load_run(pz, base), load_run(pvx, base), load_run(pvy, base),
            load_run(pvz, base))


@wp.func
def load_state_lanes(px: wp.array(dtype=float), py: wp.array(dtype=float), pz: wp.array(dtype=float),
                     pvx: wp.array(dtype=float), pvy: wp.array(dtype=float), pvz: wp.array(dtype=float),
                     pp: lane8i, delta: int):
    """Planar positions and velocities of particles pp[c] + delta, c = 0 .. 7."""
    return (load_lanes(px, pp, delta), load_lanes(py, pp, delta), load_lanes(pz, pp, delta),
            load_lanes(pvx, pp, delta), load_lanes(pvy, pp, delta), load_lanes(pvz, pp, delta))


def _step_kernel(run: bool):
    """The lanes step over blocks of consecutive particles (``run``: contiguous loads) or of any
    eight particles (per-lane loads); the loads are chosen at code generation."""
    load_state = load_state_run if run else load_state_lanes

    def step_cloth_lanes(
        px: wp.array(dtype=float), py: wp.array(dtype=float), pz: wp.array(dtype=float),
        pvx: wp.array(dtype=float), pvy: wp.array(dtype=float), pvz: wp.array(dtype=float),
        f_ext: wp.array(dtype=wp.vec3),
        use_f_ext: int,
        first_block: int,
        block_particles: wp.array(dtype=lane8i),
        block_info: wp.array(dtype=wp.vec4i),
        pattern_deltas: wp.array(dtype=int),
        slot_params: wp.array(dtype=lane8),
        inv_mass: wp.array(dtype=float),
        gravity: wp.vec3,
        h: float,
        q_out: wp.array(dtype=wp.vec3),
        qd_out: wp.array(dtype=wp.vec3),
    ):
        """One semi-implicit Euler step of block b = first_block + tid's eight particles
        ``block_particles[b]``; block_info[b] = (first pattern entry, row length <= ROW_MAX,
        first slot, 1 when the particles are consecutive). Reads the planar state, writes
        q_out / qd_out."""
        b = first_block + wp.tid()
        pp = block_particles[b]
        info = block_info[b]
        ox, oy, oz, ovx, ovy, ovz = wp.static(load_state)(px, py, pz, pvx, pvy, pvz, pp, 0)
        fx = lane8()
        fy = lane8()
        fz = lane8()
        for k in range(ROW_MAX):
            if k < info[1]:
                dk = pattern_deltas[info[0] + k]
                a3 = 3 * (info[2] + k)
                xx, xy, xz, vx, vy, vz = wp.static(load_state)(px, py, pz, pvx, pvy, pvz, pp, dk)
                gx, gy, gz = lane_spring_forces(ox - xx, oy - xy, oz - xz, ovx - vx, ovy - vy, ovz - vz,
                                                slot_params[a3], slot_params[a3 + 1], slot_params[a3 + 2])
                fx = fx + gx
                fy = fy + gy
                fz = fz + gz
        for c in range(LANES):
            step_lane(wp.max(pp[c], 0), wp.vec3(ox[c], oy[c], oz[c]), wp.vec3(ovx[c], ovy[c], ovz[c]),
                      wp.vec3(fx[c], fy[c], fz[c]), f_ext, use_f_ext, inv_mass, gravity, h, q_out, qd_out)

    step_cloth_lanes.__name__ = step_cloth_lanes.__qualname__ = "step_cloth_lanes_" + ("run" if run else "any")
    return wp.kernel(step_cloth_lanes)


step_cloth_lanes_run = _step_kernel(True)
step_cloth_lanes_any = _step_kernel(False)
