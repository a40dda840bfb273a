"""Analytic scalar fields sampled on grid nodes (inputs for marching cubes).

Grid convention as in ``warpsim.meshing``: ``field[i, j, k]`` is sampled at
``lower + (i, j, k) * spacing`` [m].
"""
import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.func
def node_position(lower: wp.vec3, spacing: wp.vec3, i: int, j: int, k: int):
    return lower + wp.cw_mul(wp.vec3(float(i), float(j), float(k)), spacing)


@wp.kernel
def eval_metaball_density(
    centers: wp.array(dtype=wp.vec3),
    radii: wp.array(dtype=float),
    lower: wp.vec3,
    spacing: wp.vec3,
    field_out: wp.array3d(dtype=float),
):
    """Wyvill metaballs: sum over blobs of (1 - d^2 / R^2)^3 for d < R, else 0 (dimensionless).

    centers [m] and radii [m] have shape (blob_count,); field_out shape (nx, ny, nz). One blob
    alone reaches 1 at its centre and 0 at distance R; its iso-0.5 surface has radius ~0.45 R.
    """
    i, j, k = wp.tid()
    p = node_position(lower, spacing, i, j, k)
    density = float(0.0)
    for b in range(centers.shape[0]):
        r = radii[b]
        q = wp.length_sq(p - centers[b]) / (r * r)
        if q < 1.0:
            s = 1.0 - q
            density += s * s * s
    field_out[i, j, k] = density


def metaball_density(centers, radii, field_out, lower, spacing):
    """Launch :func:`eval_metaball_density` on ``field_out``'s device (no allocation)."""
    wp.launch(
        eval_metaball_density,
        dim=field_out.shape,
        inputs=[centers, radii, wp.vec3(*lower), wp.vec3(*spacing)],
        outputs=[field_out],
        device=field_out.device,
    )


@wp.kernel
def eval_gyroid_ball(
    period: float,
    thickness: float,
    radius: float,
    lower: wp.vec3,
    spacing: wp.vec3,
    field_out: wp.array3d(dtype=float),
):
    """Approximate signed distance [m] of a gyroid sheet clipped to a ball, shape (nx, ny, nz).

    Sheet: |sin x cos y + sin y cos z + sin z cos x| * period / (2 pi) - thickness / 2 <= 0 with
    (x, y, z) = 2 pi p / period [m]; ball: |p| - radius <= 0; their intersection is max(...).
    """
    i, j, k = wp.tid()
    p = node_position(lower, spacing, i, j, k)
    w = 2.0 * wp.pi / period
    x = w * p[0]
    y = w * p[1]
    z = w * p[2]
    g = wp.sin(x) * wp.cos(y) + wp.sin(y) * wp.cos(z) + wp.sin(z) * wp.cos(x)
    sheet = wp.abs(g) / w - 0.5 * thickness
    field_out[i, j, k] = wp.max(sheet, wp.length(p) - radius)


def gyroid_ball(field_out, lower, spacing, period=0.8, thickness=0.08, radius=0.9):
    """Launch :func:`eval_gyroid_ball` on ``field_out``'s device (no allocation)."""
    wp.launch(
        eval_gyroid_ball,
        dim=field_out.shape,
        inputs=[float(period), float(thickness), float(radius), wp.vec3(*lower), wp.vec3(*spacing)],
        outputs=[field_out],
        device=field_out.device,
    )
