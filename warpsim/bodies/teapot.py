"""The Utah teapot (Martin Newell, 1975), generated from its public-domain Bezier patch data.

The data below is Newell's classic set as typed in for decades: 306 control points (z up, his
units: the body is 2 wide at its widest, 3.15 tall) and 32 bicubic patches of 16 control-point
indices (1-based, as published): rim 4, body 8, handle 4, spout 4, lid 8 and the 4 bottom
patches added later. ``teapot_mesh`` tessellates every patch into an n x n grid of quads
(two triangles each) and welds coincident vertices, giving three closed, outward-wound,
genus-0 surfaces:

- body: rim + body + lid + bottom. The lid's bottom ring (radius 1.3 at z = 2.4) is moved to
  the rim's inner edge (radius 1.4) so the two weld; that is the only change to the data
  (``fit_lid=False`` keeps the published gap, leaving two open loops).
- handle and spout: open tubes in the data (their ends sit on or inside the body, and the spout
  tip is open); each end loop is closed by a fan of triangles around its centroid.

Degenerate spots: the lid knob (control point 204 repeated four times) and the bottom centre
(270) are poles where a whole patch row collapses to one point; welding merges them to a
single vertex and the zero-area triangles there are dropped. The three surfaces touch or
interpenetrate where the handle and spout meet the body (as in the original), so the mesh is
watertight per component (every edge in two faces, opposite directions) but self-intersecting;
its volume counts the overlap twice. Welding is done per component so they share no vertex.

Coordinates are turned to +Y up ((x, y, z) -> (x, z, -y)) and scaled by ``scale`` [m per unit]:
the default 0.1 gives a teapot 0.65 m long and 0.315 m tall standing on y = 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import meshtools

# fmt: off
PATCHES = (  # 32 patches x 16 indices (1-based)
    # rim
    (1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16),
    (4, 17, 18, 19, 8, 20, 21, 22, 12, 23, 24, 25, 16, 26, 27, 28),
    (19, 29, 30, 31, 22, 32, 33, 34, 25, 35, 36, 37, 28, 38, 39, 40),
    (31, 41, 42, 1, 34, 43, 44, 5, 37, 45, 46, 9, 40, 47, 48, 13),
    # body
    (13, 14, 15, 16, 49, 50, 51, 52, 53, 54, 55, 56, 57, 58, 59, 60),
    (16, 26, 27, 28, 52, 61, 62, 63, 56, 64, 65, 66, 60, 67, 68, 69),
    (28, 38, 39, 40, 63, 70, 71, 72, 66, 73, 74, 75, 69, 76, 77, 78),
    (40, 47, 48, 13, 72, 79, 80, 49, 75, 81, 82, 53, 78, 83, 84, 57),
    (57, 58, 59, 60, 85, 86, 87, 88, 89, 90, 91, 92, 93, 94, 95, 96),
    (60, 67, 68, 69, 88, 97, 98, 99, 92, 100, 101, 102, 96, 103, 104, 105),
    (69, 76, 77, 78, 99, 106, 107, 108, 102, 109, 110, 111, 105, 112, 113, 114),
    (78, 83, 84, 57, 108, 115, 116, 85, 111, 117, 118, 89, 114, 119, 120, 93),
    # handle
    (121, 122, 123, 124, 125, 126, 127, 128, 129, 130, 131, 132, 133, 134, 135, 136),
    (124, 137, 138, 121, 128, 139, 140, 125, 132, 141, 142, 129, 136, 143, 144, 133),
    (133, 134, 135, 136, 145, 146, 147, 148, 149, 150, 151, 152, 69, 153, 154, 155),
    (136, 143, 144, 133, 148, 156, 157, 145, 152, 158, 159, 149, 155, 160, 161, 69),
    # spout
    (162, 163, 164, 165, 166, 167, 168, 169, 170, 171, 172, 173, 174, 175, 176, 177),
    (165, 178, 179, 162, 169, 180, 181, 166, 173, 182, 183, 170, 177, 184, 185, 174),
    (174, 175, 176, 177, 186, 187, 188, 189, 190, 191, 192, 193, 194, 195, 196, 197),
    (177, 184, 185, 174, 189, 198, 199, 186, 193, 200, 201, 190, 197, 202, 203, 194),
    # lid
    (204, 204, 204, 204, 207, 208, 209, 210, 211, 211, 211, 211, 212, 213, 214, 215),
    (204, 204, 204, 204, 210, 217, 218, 219, 211, 211, 211, 211, 215, 220, 221, 222),
    (204, 204, 204, 204, 219, 224, 225, 226, 211, 211, 211, 211, 222, 227, 228, 229),
    (204, 204, 204, 204, 226, 230, 231, 207, 211, 211, 211, 211, 229, 232, 233, 212),
    (212, 213, 214, 215, 234, 235, 236, 237, 238, 239, 240, 241, 242, 243, 244, 245),
    (215, 220, 221, 222, 237, 246, 247, 248, 241, 249, 250, 251, 245, 252, 253, 254),
    (222, 227, 228, 229, 248, 255, 256, 257, 251, 258, 259, 260, 254, 261, 262, 263),
    (229, 232, 233, 212, 257, 264, 265, 234, 260, 266, 267, 238, 263, 268, 269, 242),
    # bottom
    (270, 270, 270, 270, 279, 280, 281, 282, 275, 276, 277, 278, 271, 272, 273, 274),
    (270, 270, 270, 270, 282, 289, 290, 291, 278, 286, 287, 288, 274, 283, 284, 285),
    (270, 270, 270, 270, 291, 298, 299, 300, 288, 295, 296, 297, 285, 292, 293, 294),
    (270, 270, 270, 270, 300, 305, 306, 279, 297, 303, 304, 275, 294, 301, 302, 271),
)

VERTICES = (  # 306 control points (x, y, z), z up
    (1.4, 0.0, 2.4), (1.4, -0.784, 2.4), (0.784, -1.4, 2.4), (0.0, -1.4, 2.4),
    (1.3375, 0.0, 2.53125), (1.3375, -0.749, 2.53125), (0.749, -1.3375, 2.53125), (0.0, -1.3375, 2.53125),
    (1.4375, 0.0, 2.53125), (1.4375, -0.805, 2.53125), (0.805, -1.4375, 2.53125), (0.0, -1.4375, 2.53125),
    (1.5, 0.0, 2.4), (1.5, -0.84, 2.4), (0.84, -1.5, 2.4), (0.0, -1.5, 2.4),
    (-0.784, -1.4, 2.4), (-1.4, -0.784, 2.4), (-1.4, 0.0, 2.4),
    (-0.749, -1.3375, 2.53125), (-1.3375, -0.749, 2.53125), (-1.3375, 0.0, 2.53125),
    (-0.805, -1.4375, 2.53125), (-1.4375, -0.805, 2.53125), (-1.4375, 0.0, 2.53125),
    (-0.84, -1.5, 2.4), (-1.5, -0.84, 2.4), (-1.5, 0.0, 2.4),
    (-1.4, 0.784, 2.4), (-0.784, 1.4, 2.4), (0.0, 1.4, 2.4),
    (-1.3375, 0.749, 2.53125), (-0.749, 1.3375, 2.53125), (0.0, 1.3375, 2.53125),
    (-1.4375, 0.805, 2.53125), (-0.805, 1.4375, 2.53125), (0.0, 1.4375, 2.53125),
    (-1.5, 0.84, 2.4), (-0.84, 1.5, 2.4), (0.0, 1.5, 2.4),
    (0.784, 1.4, 2.4), (1.4, 0.784, 2.4),
    (0.749, 1.3375, 2.53125), (1.3375, 0.749, 2.53125),
    (0.805, 1.4375, 2.53125), (1.4375, 0.805, 2.53125),
    (0.84, 1.5, 2.4), (1.5, 0.84, 2.4),
    (1.75, 0.0, 1.875), (1.75, -0.98, 1.875), (0.98, -1.75, 1.875), (0.0, -1.75, 1.875),
    (2.0, 0.0, 1.35), (2.0, -1.12, 1.35), (1.12, -2.0, 1.35), (0.0, -2.0, 1.35),
    (2.0, 0.0, 0.9), (2.0, -1.12, 0.9), (1.12, -2.0, 0.9), (0.0, -2.0, 0.9),
    (-0.98, -1.75, 1.875), (-1.75, -0.98, 1.875), (-1.75, 0.0, 1.875),
    (-1.12, -2.0, 1.35), (-2.0, -1.12, 1.35), (-2.0, 0.0, 1.35),
    (-1.12, -2.0, 0.9), (-2.0, -1.12, 0.9), (-2.0, 0.0, 0.9),
    (-1.75, 0.98, 1.875), (-0.98, 1.75, 1.875), (0.0, 1.75, 1.875),
    (-2.0, 1.12, 1.35), (-1.12, 2.0, 1.35), (0.0, 2.0, 1.35),
    (-2.0, 1.12, 0.9), (-1.12, 2.0, 0.9), (0.0, 2.0, 0.9),
    (0.98, 1.75, 1.875), (1.75, 0.98, 1.875),
    (1.12, 2.0, 1.35), (2.0, 1.12, 1.35),
    (1.12, 2.0, 0.9), (2.0, 1.12, 0.9),
    (2.0, 0.0, 0.45), (2.0, -1.12, 0.45), (1.12, -2.0, 0.45), (0.0, -2.0, 0.45),
    (1.5, 0.0, 0.225), (1.5, -0.84, 0.225), (0.84, -1.5, 0.225), (0.0, -1.5, 0.225),
    (1.5, 0.0, 0.15), (1.5, -0.84, 0.15), (0.84, -1.5, 0.15), (0.0, -1.5, 0.15),
    (-1.12, -2.0, 0.45), (-2.0, -1.12, 0.45), (-2.0, 0.0, 0.45),
    (-0.84, -1.5, 0.225), (-1.5, -0.84, 0.225), (-1.5, 0.0, 0.225),
    (-0.84, -1.5, 0.15), (-1.5, -0.84, 0.15), (-1.5, 0.0, 0.15),
    (-2.0, 1.12, 0.45), (-1.12, 2.0, 0.45), (0.0, 2.0, 0.45),
    (-1.5, 0.84, 0.225), (-0.84, 1.5, 0.225), (0.0, 1.5, 0.225),
    (-1.5, 0.84, 0.15), (-0.84, 1.5, 0.15), (0.0, 1.5, 0.15),
    (1.12, 2.0, 0.45), (2.0, 1.12, 0.45),
    (0.84, 1.5, 0.225), (1.5, 0.84, 0.225),
    (0.84, 1.5, 0.15), (1.5, 0.84, 0.15),
    (-1.6, 0.0, 2.025), (-1.6, -0.3, 2.025), (-1.5, -0.3, 2.25), (-1.5, 0.0, 2.25),
    (-2.3, 0.0, 2.025), (-2.3, -0.3, 2.025), (-2.5, -0.3, 2.25), (-2.5, 0.0, 2.25),
    (-2.7, 0.0, 2.025), (-2.7, -0.3, 2.025), (-3.0, -0.3, 2.25), (-3.0, 0.0, 2.25),
    (-2.7, 0.0, 1.8), (-2.7, -0.3, 1.8), (-3.0, -0.3, 1.8), (-3.0, 0.0, 1.8),
    (-1.5, 0.3, 2.25), (-1.6, 0.3, 2.025), (-2.5, 0.3, 2.25), (-2.3, 0.3, 2.025),
    (-3.0, 0.3, 2.25), (-2.7, 0.3, 2.025), (-3.0, 0.3, 1.8), (-2.7, 0.3, 1.8),
    (-2.7, 0.0, 1.575), (-2.7, -0.3, 1.575), (-3.0, -0.3, 1.35), (-3.0, 0.0, 1.35),
    (-2.5, 0.0, 1.125), (-2.5, -0.3, 1.125), (-2.65, -0.3, 0.9375), (-2.65, 0.0, 0.9375),
    (-2.0, -0.3, 0.9), (-1.9, -0.3, 0.6), (-1.9, 0.0, 0.6),
    (-3.0, 0.3, 1.35), (-2.7, 0.3, 1.575), (-2.65, 0.3, 0.9375), (-2.5, 0.3, 1.125),
    (-1.9, 0.3, 0.6), (-2.0, 0.3, 0.9),
    (1.7, 0.0, 1.425), (1.7, -0.66, 1.425), (1.7, -0.66, 0.6), (1.7, 0.0, 0.6),
    (2.6, 0.0, 1.425), (2.6, -0.66, 1.425), (3.1, -0.66, 0.825), (3.1, 0.0, 0.825),
    (2.3, 0.0, 2.1), (2.3, -0.25, 2.1), (2.4, -0.25, 2.025), (2.4, 0.0, 2.025),
    (2.7, 0.0, 2.4), (2.7, -0.25, 2.4), (3.3, -0.25, 2.4), (3.3, 0.0, 2.4),
    (1.7, 0.66, 0.6), (1.7, 0.66, 1.425), (3.1, 0.66, 0.825), (2.6, 0.66, 1.425),
    (2.4, 0.25, 2.025), (2.3, 0.25, 2.1), (3.3, 0.25, 2.4), (2.7, 0.25, 2.4),
    (2.8, 0.0, 2.475), (2.8, -0.25, 2.475), (3.525, -0.25, 2.49375), (3.525, 0.0, 2.49375),
    (2.9, 0.0, 2.475), (2.9, -0.15, 2.475), (3.45, -0.15, 2.5125), (3.45, 0.0, 2.5125),
    (2.8, 0.0, 2.4), (2.8, -0.15, 2.4), (3.2, -0.15, 2.4), (3.2, 0.0, 2.4),
    (3.525, 0.25, 2.49375), (2.8, 0.25, 2.475), (3.45, 0.15, 2.5125), (2.9, 0.15, 2.475),
    (3.2, 0.15, 2.4), (2.8, 0.15, 2.4),
    (0.0, 0.0, 3.15), (0.0, -0.002, 3.15), (0.002, 0.0, 3.15),
    (0.8, 0.0, 3.15), (0.8, -0.45, 3.15), (0.45, -0.8, 3.15), (0.0, -0.8, 3.15),
    (0.0, 0.0, 2.85),
    (0.2, 0.0, 2.7), (0.2, -0.112, 2.7), (0.112, -0.2, 2.7), (0.0, -0.2, 2.7),
    (-0.002, 0.0, 3.15), (-0.45, -0.8, 3.15), (-0.8, -0.45, 3.15), (-0.8, 0.0, 3.15),
    (-0.112, -0.2, 2.7), (-0.2, -0.112, 2.7), (-0.2, 0.0, 2.7),
    (0.0, 0.002, 3.15), (-0.8, 0.45, 3.15), (-0.45, 0.8, 3.15), (0.0, 0.8, 3.15),
    (-0.2, 0.112, 2.7), (-0.112, 0.2, 2.7), (0.0, 0.2, 2.7),
    (0.45, 0.8, 3.15), (0.8, 0.45, 3.15),
    (0.112, 0.2, 2.7), (0.2, 0.112, 2.7),
    (0.4, 0.0, 2.55), (0.4, -0.224, 2.55), (0.224, -0.4, 2.55), (0.0, -0.4, 2.55),
    (1.3, 0.0, 2.55), (1.3, -0.728, 2.55), (0.728, -1.3, 2.55), (0.0, -1.3, 2.55),
    (1.3, 0.0, 2.4), (1.3, -0.728, 2.4), (0.728, -1.3, 2.4), (0.0, -1.3, 2.4),
    (-0.224, -0.4, 2.55), (-0.4, -0.224, 2.55), (-0.4, 0.0, 2.55),
    (-0.728, -1.3, 2.55), (-1.3, -0.728, 2.55), (-1.3, 0.0, 2.55),
    (-0.728, -1.3, 2.4), (-1.3, -0.728, 2.4), (-1.3, 0.0, 2.4),
    (-0.4, 0.224, 2.55), (-0.224, 0.4, 2.55), (0.0, 0.4, 2.55),
    (-1.3, 0.728, 2.55), (-0.728, 1.3, 2.55), (0.0, 1.3, 2.55),
    (-1.3, 0.728, 2.4), (-0.728, 1.3, 2.4), (0.0, 1.3, 2.4),
    (0.224, 0.4, 2.55), (0.4, 0.224, 2.55),
    (0.728, 1.3, 2.55), (1.3, 0.728, 2.55),
    (0.728, 1.3, 2.4), (1.3, 0.728, 2.4),
    (0.0, 0.0, 0.0),
    (1.5, 0.0, 0.15), (1.5, 0.84, 0.15), (0.84, 1.5, 0.15), (0.0, 1.5, 0.15),
    (1.5, 0.0, 0.075), (1.5, 0.84, 0.075), (0.84, 1.5, 0.075), (0.0, 1.5, 0.075),
    (1.425, 0.0, 0.0), (1.425, 0.798, 0.0), (0.798, 1.425, 0.0), (0.0, 1.425, 0.0),
    (-0.84, 1.5, 0.15), (-1.5, 0.84, 0.15), (-1.5, 0.0, 0.15),
    (-0.84, 1.5, 0.075), (-1.5, 0.84, 0.075), (-1.5, 0.0, 0.075),
    (-0.798, 1.425, 0.0), (-1.425, 0.798, 0.0), (-1.425, 0.0, 0.0),
    (-1.5, -0.84, 0.15), (-0.84, -1.5, 0.15), (0.0, -1.5, 0.15),
    (-1.5, -0.84, 0.075), (-0.84, -1.5, 0.075), (0.0, -1.5, 0.075),
    (-1.425, -0.798, 0.0), (-0.798, -1.425, 0.0), (0.0, -1.425, 0.0),
    (0.84, -1.5, 0.15), (1.5, -0.84, 0.15),
    (0.84, -1.5, 0.075), (1.5, -0.84, 0.075),
    (0.798, -1.425, 0.0), (1.425, -0.798, 0.0),
)
# fmt: on

PARTS = {"rim": range(4), "body": range(4, 12), "handle": range(12, 16), "spout": range(16, 20),
         "lid": range(20, 28), "bottom": range(28, 32)}
"""Patch numbers (0-based) of each named part of the data."""

COMPONENTS = {"body": ("rim", "body", "lid", "bottom"), "handle": ("handle",), "spout": ("spout",)}
"""The closed surfaces teapot_mesh builds and the parts each is made of."""

RESOLUTIONS = {"low": 4, "high": 12}
"""Named resolutions: segments per patch edge."""


def control_points(fit_lid: bool = True) -> np.ndarray:
    """Control points of the 32 patches, shape (32, 4, 4, 3), Newell's units, z up.

    fit_lid: move the lid's bottom ring onto the rim's inner edge so that they weld."""
    v = np.asarray(VERTICES, dtype=np.float64)
    idx = np.asarray(PATCHES, dtype=np.int64) - 1
    if fit_lid:
        idx = idx.copy()
        for k in range(4):
            idx[24 + k, 12:16] = idx[k, 0:4]
    return v[idx].reshape(32, 4, 4, 3)


def bernstein(t) -> np.ndarray:
    """Cubic Bernstein basis at parameters t, shape t.shape + (4,)."""
    t = np.asarray(t, dtype=np.float64)
    s = 1.0 - t
    return np.stack([s**3, 3.0 * t * s * s, 3.0 * t * t * s, t**3], axis=-1)


def bezier_patch(control, n: int) -> np.ndarray:
    """Points of a bicubic patch (control (4, 4, 3)) on an (n+1) x (n+1) parameter grid,
    shape (n+1, n+1, 3); the first index follows the control rows."""
    b = bernstein(np.linspace(0.0, 1.0, n + 1))
    return np.einsum("ui,vj,ijk->uvk", b, b, np.asarray(control, dtype=np.float64))


def grid_faces(n: int) -> np.ndarray:
    """Triangles of an (n+1) x (n+1) vertex grid, two per quad, shape (2 n^2, 3), wound like the
    patch data (normal along d/dv x d/du, outward for Newell's patches)."""
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    a = (i * (n + 1) + j).reshape(-1)
    b, c = a + 1, a + n + 1
    d = c + 1
    return np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])


def resolve_resolution(resolution) -> int:
    """Segments per patch edge from an int >= 2 or a name in RESOLUTIONS."""
    if isinstance(resolution, str):
        text = resolution.strip().lower()
        if text in RESOLUTIONS:
            return RESOLUTIONS[text]
        try:
            resolution = int(text)
        except ValueError:
            raise ValueError(f"teapot resolution {resolution!r} is not an integer or one of "
                             f"{sorted(RESOLUTIONS)}") from None
    n = int(resolution)
    if n < 2 or n != resolution:
        raise ValueError(f"teapot resolution {resolution!r} must be an integer >= 2 (segments per patch edge)")
    return n


@dataclass
class TeapotMesh:
    """A tessellated teapot: points (V, 3) [m], faces (F, 3) outward-wound triangles,
    ``face_component`` (F,) index into ``component_names``, ``resolution`` n (segments per
    patch edge)."""

    points: np.ndarray
    faces: np.ndarray
    face_component: np.ndarray
    component_names: tuple
    resolution: int

    def component_faces(self, name) -> np.ndarray:
        return self.faces[self.face_component == self.component_names.index(name)]


def teapot_mesh(resolution="low", *, scale: float = 0.1, y_up: bool = True, fit_lid: bool = True) -> TeapotMesh:
    """The welded, capped Utah teapot at ``resolution`` segments per patch edge ("low" = 4:
    518 vertices; "high" = 12: 4614 vertices; or any int >= 2). ``scale`` [m per data unit]; ``y_up`` turns
    the data's z-up into +Y up. See the module docstring for the welding and the caps."""
    n = resolve_resolution(resolution)
    scale = float(scale)
    if not (np.isfinite(scale) and scale > 0.0):
        raise ValueError(f"teapot scale {scale} must be > 0 [m per unit]")
    ctrl = control_points(fit_lid)
    cell = grid_faces(n)
    points, faces, labels = [], [], []
    offset = 0
    names = tuple(COMPONENTS)
    for k, (name, parts) in enumerate(COMPONENTS.items()):
        patches = [p for part in parts for p in PARTS[part]]
        grid = np.concatenate([bezier_patch(ctrl[p], n).reshape(-1, 3) for p in patches])
        f = np.concatenate([cell + m * (n + 1) ** 2 for m in range(len(patches))])
        p, f, _ = meshtools.weld(grid, f, tolerance=1.0e-6)
        loops = meshtools.boundary_loops(f)
        if name != "body" or not fit_lid:
            p, f = meshtools.cap_loops(p, f, loops) if name != "body" else (p, f)
        points.append(p)
        faces.append(f + offset)
        labels.append(np.full(len(f), k))
        offset += len(p)
    merged = np.concatenate(points)
    if y_up:
        merged = np.stack([merged[:, 0], merged[:, 2], -merged[:, 1]], axis=1)
    return TeapotMesh(merged * scale, np.concatenate(faces), np.concatenate(labels), names, n)
