"""Ray-casting kernels of the preview renderer (``warpsim.render``): one ray per pixel.

Geometry a frame is made of (all in world space, metres):
- opaque triangles in one ``wp.Mesh`` (meshes, colliders, tessellated cubes/cones, instanced
  mesh prototypes) with a colour per face and a shading normal per face corner (smooth meshes
  get vertex normals, flat ones the face normal);
- translucent triangles in a second ``wp.Mesh`` (walls with ``displayOpacity`` < 1) with a colour
  and an opacity per face, composited front to back (at most ``MAX_LAYERS`` layers);
- round primitives in a ``wp.Bvh``: capsules from ``a`` to ``b`` of radius ``r`` (points and
  spheres are capsules with ``a == b``; curves are chains of capsules);
- a density grid (smoke) ray-marched as an emission-free, absorbing and scattering volume with a
  short shadow march towards the light;
- a ground plane ``y = ground_y`` (checkered) below everything.

Shading is Lambert with an ambient term, a directional light and one shadow ray per visible
surface (opaque triangles and round primitives cast shadows). The camera is a pinhole: pixel
``(i, j)`` (row ``i`` from the top) looks along ``forward + (2 (j + 0.5) / width - 1) * tan_x * right
+ (1 - 2 (i + 0.5) / height) * tan_y * up``.

Conventions: colours are linear RGB in [0, 1]; the output is an array of ``vec3`` of shape
(pictures * height * width,), each picture in row-major order (``render_pictures``: one launch
draws many pictures of one camera, a sweep's thumbnails; a lone picture is one of them).
"""

import warp as wp

from .collide import ray_capsule_entry

wp.set_module_options({"enable_backward": False})

MAX_LAYERS = wp.constant(6)
HIT_EPS = wp.constant(1.0e-4)


@wp.struct
class Camera:
    """Pinhole camera: ``eye`` [m], orthonormal ``forward``/``right``/``up`` and the tangents of
    the half field of view across (``tan_x``) and up (``tan_y``)."""

    eye: wp.vec3
    forward: wp.vec3
    right: wp.vec3
    up: wp.vec3
    tan_x: float
    tan_y: float


@wp.struct
class Lighting:
    """Directional light (unit vector towards the light), ambient share, background colours
    (horizon and zenith) and the ground plane (``ground`` 0/1, height [m], checker size [m]; it
    fades into the horizon colour over ``fade`` [m])."""

    light: wp.vec3
    ambient: float
    sky_low: wp.vec3
    sky_high: wp.vec3
    ground: int
    ground_y: float
    checker: float
    fade: float


@wp.struct
class Volume:
    """Density grid (nx, ny, nz) of cell ``dx`` [m] whose cell (0, 0, 0) centre is ``origin + dx/2``;
    ``extinction`` [1/m per unit density], ``color`` the scattering albedo; ``active`` 0/1."""

    density: wp.array3d(dtype=float)
    origin: wp.vec3
    dx: float
    extinction: float
    color: wp.vec3
    active: int


@wp.func
def capsule_normal(p: wp.vec3, a: wp.vec3, b: wp.vec3):
    """Outward unit normal of a capsule (a, b) at surface point p."""
    ba = b - a
    baba = wp.dot(ba, ba)
    s = float(0.0)
    if baba > 1.0e-20:
        s = wp.clamp(wp.dot(p - a, ba) / baba, 0.0, 1.0)
    return wp.normalize(p - (a + s * ba))


@wp.func
def closest_capsule(bvh: wp.uint64, cap_a: wp.array(dtype=wp.vec3), cap_b: wp.array(dtype=wp.vec3),
                    cap_r: wp.array(dtype=float), base: int, o: wp.vec3, d: wp.vec3, t_max: float):
    """(t, index) of the nearest capsule hit before t_max; index -1 if none. The BVH's items are the
    capsules ``base``, ``base + 1``, ... of the arrays (the index returned is the arrays')."""
    best_t = t_max
    best = int(-1)
    query = wp.bvh_query_ray(bvh, o, d)
    k = int(0)
    while wp.bvh_query_next(query, k, best_t):
        t = ray_capsule_entry(o, d, cap_a[base + k], cap_b[base + k], cap_r[base + k])
        if t > 0.0 and t < best_t:
            best_t = t
            best = base + k
    return best_t, best


@wp.func
def occluded(mesh: wp.uint64, has_mesh: int, bvh: wp.uint64, has_caps: int, cap_a: wp.array(dtype=wp.vec3),
             cap_b: wp.array(dtype=wp.vec3), cap_r: wp.array(dtype=float), cap_base: int, o: wp.vec3, d: wp.vec3):
    """1.0 when the ray from o along d hits opaque geometry, else 0.0."""
    if has_mesh != 0:
        q = wp.mesh_query_ray(mesh, o, d, 1.0e6)
        if q.result:
            return 1.0
    if has_caps != 0:
        _t, k = closest_capsule(bvh, cap_a, cap_b, cap_r, cap_base, o, d, 1.0e6)
        if k >= 0:
            return 1.0
    return 0.0


@wp.func
def sample_density(vol: Volume, p: wp.vec3):
    """Trilinear density at world point p (0 outside the grid)."""
    g = (p - vol.origin) / vol.dx - wp.vec3(0.5, 0.5, 0.5)
    nx = vol.density.shape[0]
    ny = vol.density.shape[1]
    nz = vol.density.shape[2]
    if g[0] < -0.5 or g[1] < -0.5 or g[2] < -0.5:
        return 0.0
    if g[0] > float(nx) - 0.5 or g[1] > float(ny) - 0.5 or g[2] > float(nz) - 0.5:
        return 0.0
    i0 = int(wp.floor(g[0]))
    j0 = int(wp.floor(g[1]))
    k0 = int(wp.floor(g[2]))
    fx = g[0] - float(i0)
    fy = g[1] - float(j0)
    fz = g[2] - float(k0)
    acc = float(0.0)
    for c in range(8):
        di = c & 1
        dj = (c >> 1) & 1
        dk = (c >> 2) & 1
        i = wp.clamp(i0 + di, 0, nx - 1)
        j = wp.clamp(j0 + dj, 0, ny - 1)
        k = wp.clamp(k0 + dk, 0, nz - 1)
        w = wp.where(di == 1, fx, 1.0 - fx) * wp.where(dj == 1, fy, 1.0 - fy) * wp.where(dk == 1, fz, 1.0 - fz)
        acc += w * vol.density[i, j, k]
    return acc


@wp.func
def slab(o: wp.vec3, d: wp.vec3, lo: wp.vec3, hi: wp.vec3):
    """(t_enter, t_exit) of the ray against the box [lo, hi]; t_enter > t_exit when it misses."""
    t0 = float(0.0)
    t1 = float(1.0e30)
    for a in range(3):
        if wp.abs(d[a]) < 1.0e-12:
            if o[a] < lo[a] or o[a] > hi[a]:
                return 1.0, 0.0
        else:
            inv = 1.0 / d[a]
            ta = (lo[a] - o[a]) * inv
            tb = (hi[a] - o[a]) * inv
            t0 = wp.max(t0, wp.min(ta, tb))
            t1 = wp.min(t1, wp.max(ta, tb))
    return t0, t1


@wp.func
def lambert(color: wp.vec3, n: wp.vec3, light: Lighting, shadow: float):
    diffuse = wp.max(wp.dot(n, light.light), 0.0) * (1.0 - shadow)
    return color * (light.ambient + (1.0 - light.ambient) * diffuse)


@wp.func
def shade_pixel(
    cam: Camera,
    light: Lighting,
    width: int,
    height: int,
    tid: int,
    mesh: wp.uint64,
    has_mesh: int,
    face_color: wp.array(dtype=wp.vec3),
    corner_normal: wp.array(dtype=wp.vec3),
    face_base: int,
    glass: wp.uint64,
    has_glass: int,
    glass_color: wp.array(dtype=wp.vec3),
    glass_alpha: wp.array(dtype=float),
    glass_base: int,
    bvh: wp.uint64,
    has_caps: int,
    cap_a: wp.array(dtype=wp.vec3),
    cap_b: wp.array(dtype=wp.vec3),
    cap_r: wp.array(dtype=float),
    cap_color: wp.array(dtype=wp.vec3),
    cap_base: int,
    vol: Volume,
):
    """Linear RGB of pixel ``tid`` (row-major) of one picture: its mesh's faces are the entries
    ``face_base + f`` of ``face_color`` (corners ``3 (face_base + f) + c`` of ``corner_normal``), its
    glass faces ``glass_base + f``, its capsules ``cap_base + k`` (0, 0, 0 for a picture of its own)."""
    i = tid / width
    j = tid - i * width
    sx = (2.0 * (float(j) + 0.5) / float(width) - 1.0) * cam.tan_x
    sy = (1.0 - 2.0 * (float(i) + 0.5) / float(height)) * cam.tan_y
    d = wp.normalize(cam.forward + sx * cam.right + sy * cam.up)
    o = cam.eye

    # nearest opaque surface: triangles, round primitives, ground
    t_best = float(1.0e30)
    kind = int(0)  # 0 sky, 1 triangle, 2 capsule, 3 ground
    n = wp.vec3(0.0, 1.0, 0.0)
    color = wp.vec3(0.0, 0.0, 0.0)
    if has_mesh != 0:
        q = wp.mesh_query_ray(mesh, o, d, t_best)
        if q.result:
            t_best = q.t
            kind = 1
            f = face_base + q.face
            w2 = 1.0 - q.u - q.v
            n = wp.normalize(q.u * corner_normal[3 * f] + q.v * corner_normal[3 * f + 1]
                             + w2 * corner_normal[3 * f + 2])
            if wp.length(n) < 0.5:
                n = q.normal
            color = face_color[f]
    if has_caps != 0:
        t, k = closest_capsule(bvh, cap_a, cap_b, cap_r, cap_base, o, d, t_best)
        if k >= 0:
            t_best = t
            kind = 2
            n = capsule_normal(o + t * d, cap_a[k], cap_b[k])
            color = cap_color[k]

    if light.ground != 0 and d[1] < -1.0e-9 and o[1] > light.ground_y:
        t = (light.ground_y - o[1]) / d[1]
        if t < t_best:
            t_best = t
            kind = 3
            n = wp.vec3(0.0, 1.0, 0.0)
            p = o + t * d
            cell = int(wp.floor(p[0] / light.checker)) + int(wp.floor(p[2] / light.checker))
            color = wp.where(cell % 2 == 0, wp.vec3(0.78, 0.78, 0.76), wp.vec3(0.68, 0.68, 0.66))

    shaded = wp.vec3(0.0, 0.0, 0.0)
    if kind == 0:
        sky = wp.clamp(0.5 + 0.5 * d[1], 0.0, 1.0)
        shaded = (1.0 - sky) * light.sky_low + sky * light.sky_high
    else:
        if wp.dot(n, d) > 0.0:
            n = -n
        p = o + t_best * d
        scale = wp.max(1.0, wp.length(p))
        start = p + n * (HIT_EPS * scale)
        shadow = occluded(mesh, has_mesh, bvh, has_caps, cap_a, cap_b, cap_r, cap_base, start, light.light)
        shaded = lambert(color, n, light, shadow)
        if kind == 3:
            fog = 1.0 - wp.exp(-t_best / light.fade)
            shaded = (1.0 - fog) * shaded + fog * light.sky_low

    # the volume in front of the surface, absorbing and lit through a short shadow march
    transmit = float(1.0)
    acc = wp.vec3(0.0, 0.0, 0.0)
    if vol.active != 0:
        nx = vol.density.shape[0]
        ny = vol.density.shape[1]
        nz = vol.density.shape[2]
        hi = vol.origin + vol.dx * wp.vec3(float(nx), float(ny), float(nz))
        t0, t1 = slab(o, d, vol.origin, hi)
        t1 = wp.min(t1, t_best)
        step = 0.5 * vol.dx
        t = t0 + 0.5 * step
        while t < t1 and transmit > 0.01:
            rho = sample_density(vol, o + t * d)
            if rho > 1.0e-4:
                alpha = 1.0 - wp.exp(-vol.extinction * rho * step)
                # light reaching this sample: march 12 steps of 2 dx towards the light
                tau = float(0.0)
                for m in range(12):
                    tau += sample_density(vol, o + t * d + (float(m) + 0.5) * 2.0 * vol.dx * light.light)
                lit = light.ambient + (1.0 - light.ambient) * wp.exp(-vol.extinction * tau * 2.0 * vol.dx)
                acc += transmit * alpha * lit * vol.color
                transmit *= 1.0 - alpha
            t += step

    # translucent layers in front of the opaque surface, front to back
    glass_acc = wp.vec3(0.0, 0.0, 0.0)
    glass_t = float(1.0)
    if has_glass != 0:
        t_from = float(0.0)
        for layer in range(MAX_LAYERS):
            q = wp.mesh_query_ray(glass, o + t_from * d, d, t_best - t_from)
            if not q.result:
                break
            f = q.face
            gn = q.normal
            if wp.dot(gn, d) > 0.0:
                gn = -gn
            a = glass_alpha[glass_base + f]
            glass_acc += glass_t * a * lambert(glass_color[glass_base + f], gn, light, 0.0)
            glass_t *= 1.0 - a
            t_from = t_from + q.t + HIT_EPS * wp.max(1.0, t_from + q.t)

    return glass_acc + glass_t * (acc + transmit * shaded)


@wp.kernel
def render_pictures(
    cam: Camera,
    lights: wp.array(dtype=Lighting),
    width: int,
    height: int,
    meshes: wp.array(dtype=wp.uint64),
    face_base: wp.array(dtype=int),
    face_color: wp.array(dtype=wp.vec3),
    corner_normal: wp.array(dtype=wp.vec3),
    glasses: wp.array(dtype=wp.uint64),
    glass_base: wp.array(dtype=int),
    glass_color: wp.array(dtype=wp.vec3),
    glass_alpha: wp.array(dtype=float),
    bvhs: wp.array(dtype=wp.uint64),
    cap_base: wp.array(dtype=int),
    cap_a: wp.array(dtype=wp.vec3),
    cap_b: wp.array(dtype=wp.vec3),
    cap_r: wp.array(dtype=float),
    cap_color: wp.array(dtype=wp.vec3),
    vol: Volume,
    image_out: wp.array(dtype=wp.vec3),
):
    """Pictures of one camera, launched over (pictures, height * width): picture ``w`` draws its
    own mesh, glass and capsules (id 0: none; its entries from ``face_base[w]``, ``glass_base[w]``,
    ``cap_base[w]`` of the joined arrays) lit by ``lights[w]`` into ``image_out[w * height * width ..]``
    (row-major, linear RGB); the volume ``vol`` (if ``vol.active``) is in every picture."""
    w, tid = wp.tid()
    mesh = meshes[w]
    glass = glasses[w]
    bvh = bvhs[w]
    image_out[w * width * height + tid] = shade_pixel(
        cam, lights[w], width, height, tid, mesh, wp.where(mesh != wp.uint64(0), 1, 0), face_color, corner_normal,
        face_base[w], glass, wp.where(glass != wp.uint64(0), 1, 0), glass_color, glass_alpha, glass_base[w], bvh,
        wp.where(bvh != wp.uint64(0), 1, 0), cap_a, cap_b, cap_r, cap_color, cap_base[w], vol)


@wp.func
def srgb8(c: float) -> wp.uint8:
    """The 8-bit sRGB code of a linear value (clamped to [0, 1]; IEC 61966-2-1's curve, rounded)."""
    x = wp.clamp(c, 0.0, 1.0)
    s = float(0.0)
    if x <= 0.0031308:
        s = 12.92 * x
    else:
        s = 1.055 * wp.pow(x, 1.0 / 2.4) - 0.055
    return wp.uint8(int(s * 255.0 + 0.5))


@wp.kernel
def encode_srgb8(linear: wp.array(dtype=wp.vec3), rgb_out: wp.array(dtype=wp.uint8)):
    """``rgb_out[3 i + k]`` (uint8) = sRGB code of channel k of ``linear[i]`` (the pictures' pixels)."""
    i = wp.tid()
    c = linear[i]
    rgb_out[3 * i] = srgb8(c[0])
    rgb_out[3 * i + 1] = srgb8(c[1])
    rgb_out[3 * i + 2] = srgb8(c[2])


@wp.kernel
def capsule_boxes(a: wp.array(dtype=wp.vec3), b: wp.array(dtype=wp.vec3), r: wp.array(dtype=float),
                  lowers: wp.array(dtype=wp.vec3), uppers: wp.array(dtype=wp.vec3)):
    """Bounding box [m] of capsule i (ends ``a[i]``, ``b[i]``, radius ``r[i]``): the BVH items of the pictures'
    capsules (the bits of NumPy's ``np.minimum(a, b) - r`` and ``np.maximum(a, b) + r`` in float32)."""
    i = wp.tid()
    pad = wp.vec3(r[i], r[i], r[i])
    lowers[i] = wp.min(a[i], b[i]) - pad
    uppers[i] = wp.max(a[i], b[i]) + pad
