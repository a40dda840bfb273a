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
