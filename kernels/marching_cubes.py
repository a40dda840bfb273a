"""Marching cubes kernels: block culling, counting, welded-vertex and triangle emission.

Conventions (shared with ``warpsim/meshing.py``):

* The field is sampled at grid nodes ``field[i, j, k]`` = position ``origin + (i, j, k) * spacing``.
  Kernels work on ``g = sign * (field - iso)``: a node is *inside* when ``g < 0`` and *outside*
  when ``g >= 0`` (``sign = -1`` turns a density "inside above iso" into this form). A node
  exactly at iso therefore counts as outside: it is nudged by an infinitesimal toward outside.
* With ``pad = 1`` the grid gets a virtual layer of outside nodes around it, so surfaces cut by
  the domain boundary close (the cap lies ``EDGE_T_MIN * spacing`` outside the domain faces).
* Every grid edge whose end nodes differ in inside/outside yields exactly one vertex, at the
  linear zero crossing ``t = g0 / (g0 - g1)`` clamped to ``[EDGE_T_MIN, 1 - EDGE_T_MIN]``; the
  clamp keeps the vertices of edges meeting at an on-surface node distinct (no zero-area
  triangles). Vertex normals are the normalized gradient of ``g`` (central differences at the
  edge's nodes, one-sided at the domain boundary, interpolated by ``t``): they point outside.
* Triangles are counter-clockwise seen from outside (right-hand normal points toward larger g).
* Work is split into cubic blocks of ``block`` nodes per axis, one thread per block: blocks whose
  nodes all share one side are skipped after a min/max-style pass, the rest count, then emit.
  Block ``b`` owns nodes ``[b*block, (b+1)*block)`` per axis, the +x/+y/+z edges leaving them,
  and the cells whose lowest corner they are. Per node, the counting pass stores the cell's case
  code and the vertex pass the index of the node's first edge vertex (the rest follow in x, y, z
  order), so triangles find their welded vertices without a per-edge map.
"""
import warp as wp

wp.set_module_options({"enable_backward": False})

EDGE_T_MIN = 1.0e-3
"""Smallest distance of an edge vertex from either end node, as a fraction of the edge."""

OUTSIDE_VALUE = 1.0e30
"""Value of ``g`` at the virtual padding nodes (anything >= 0 means outside)."""

MAX_CASE_TRIANGLES = 5
"""Most triangles any of the 256 cases emits."""

# Cube corners: offset (x, y, z) of corner c from the cell's lowest node; bit c of the case code
# is set when corner c is inside (Bourke's numbering).
CORNER_OFFSETS = (
    (0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0),
    (0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1),
)

# The 12 cube edges as corner pairs.
EDGE_CORNERS = (
    (0, 1), (1, 2), (3, 2), (0, 3),
    (4, 5), (5, 6), (7, 6), (4, 7),
    (0, 4), (1, 5), (2, 6), (3, 7),
)

# fmt: off
# EDGE_TABLE[case]: bit e set when cube edge e is crossed (its two corners differ).
EDGE_TABLE = (
    0x000, 0x109, 0x203, 0x30a, 0x406, 0x50f, 0x605, 0x70c,
    0x80c, 0x905, 0xa0f, 0xb06, 0xc0a, 0xd03, 0xe09, 0xf00,
    0x190, 0x099, 0x393, 0x29a, 0x596, 0x49f, 0x795, 0x69c,
    0x99c, 0x895, 0xb9f, 0xa96, 0xd9a, 0xc93, 0xf99, 0xe90,
    0x230, 0x339, 0x033, 0x13a, 0x636, 0x73f, 0x435, 0x53c,
    0xa3c, 0xb35, 0x83f, 0x936, 0xe3a, 0xf33, 0xc39, 0xd30,
    0x3a0, 0x2a9, 0x1a3, 0x0aa, 0x7a6, 0x6af, 0x5a5, 0x4ac,
    0xbac, 0xaa5, 0x9af, 0x8a6, 0xfaa, 0xea3, 0xda9, 0xca0,
    0x460, 0x569, 0x663, 0x76a, 0x066, 0x16f, 0x265, 0x36c,
    0xc6c, 0xd65, 0xe6f, 0xf66, 0x86a, 0x963, 0xa69, 0xb60,
    0x5f0, 0x4f9, 0x7f3, 0x6fa, 0x1f6, 0x0ff, 0x3f5, 0x2fc,
    0xdfc, 0xcf5, 0xfff, 0xef6, 0x9fa, 0x8f3, 0xbf9, 0xaf0,
    0x650, 0x759, 0x453, 0x55a, 0x256, 0x35f, 0x055, 0x15c,
    0xe5c, 0xf55, 0xc5f, 0xd56, 0xa5a, 0xb53, 0x859, 0x950,
    0x7c0, 0x6c9, 0x5c3, 0x4ca, 0x3c6, 0x2cf, 0x1c5, 0x0cc,
    0xfcc, 0xec5, 0xdcf, 0xcc6, 0xbca, 0xac3, 0x9c9, 0x8c0,
    0x8c0, 0x9c9, 0xac3, 0xbca, 0xcc6, 0xdcf, 0xec5, 0xfcc,
    0x0cc, 0x1c5, 0x2cf, 0x3c6, 0x4ca, 0x5c3, 0x6c9, 0x7c0,
    0x950, 0x859, 0xb53, 0xa5a, 0xd56, 0xc5f, 0xf55, 0xe5c,
    0x15c, 0x055, 0x35f, 0x256, 0x55a, 0x453, 0x759, 0x650,
    0xaf0, 0xbf9, 0x8f3, 0x9fa, 0xef6, 0xfff, 0xcf5, 0xdfc,
    0x2fc, 0x3f5, 0x0ff, 0x1f6, 0x6fa, 0x7f3, 0x4f9, 0x5f0,
    0xb60, 0xa69, 0x963, 0x86a, 0xf66, 0xe6f, 0xd65, 0xc6c,
    0x36c, 0x265, 0x16f, 0x066, 0x76a, 0x663, 0x569, 0x460,
    0xca0, 0xda9, 0xea3, 0xfaa, 0x8a6, 0x9af, 0xaa5, 0xbac,
    0x4ac, 0x5a5, 0x6af, 0x7a6, 0x0aa, 0x1a3, 0x2a9, 0x3a0,
    0xd30, 0xc39, 0xf33, 0xe3a, 0x936, 0x83f, 0xb35, 0xa3c,
    0x53c, 0x435, 0x73f, 0x636, 0x13a, 0x033, 0x339, 0x230,
    0xe90, 0xf99, 0xc93, 0xd9a, 0xa96, 0xb9f, 0x895, 0x99c,
    0x69c, 0x795, 0x49f, 0x596, 0x29a, 0x393, 0x099, 0x190,
    0xf00, 0xe09, 0xd03, 0xc0a, 0xb06, 0xa0f, 0x905, 0x80c,
    0x70c, 0x605, 0x50f, 0x406, 0x30a, 0x203, 0x109, 0x000,
)

# TRI_TABLE[case]: up to 5 triangles as cube-edge triples, -1 padded (Paul Bourke / Cory Bloyd's
# public-domain table). Read with "bit set = inside" it resolves every ambiguous face the same way
# from both cells sharing it (crack-free), but lists triangles clockwise seen from outside:
# emit_triangles writes them as (e0, e2, e1).
TRI_TABLE = (
    (-1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 0,  8,  3, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 0,  1,  9, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 1,  8,  3,  9,  8,  1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 1,  2, 10, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 0,  8,  3,  1,  2, 10, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 9,  2, 10,  0,  2,  9, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 2,  8,  3,  2, 10,  8, 10,  9,  8, -1, -1, -1, -1, -1, -1, -1),
    ( 3, 11,  2, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 0, 11,  2,  8, 11,  0, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 1,  9,  0,  2,  3, 11, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 1, 11,  2,  1,  9, 11,  9,  8, 11, -1, -1, -1, -1, -1, -1, -1),
    ( 3, 10,  1, 11, 10,  3, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 0, 10,  1,  0,  8, 10,  8, 11, 10, -1, -1, -1, -1, -1, -1, -1),
    ( 3,  9,  0,  3, 11,  9, 11, 10,  9, -1, -1, -1, -1, -1, -1, -1),
    ( 9,  8, 10, 10,  8, 11, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 4,  7,  8, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 4,  3,  0,  7,  3,  4, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 0,  1,  9,  8,  4,  7, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 4,  1,  9,  4,  7,  1,  7,  3,  1, -1, -1, -1, -1, -1, -1, -1),
    ( 1,  2, 10,  8,  4,  7, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 3,  4,  7,  3,  0,  4,  1,  2, 10, -1, -1, -1, -1, -1, -1, -1),
    ( 9,  2, 10,  9,  0,  2,  8,  4,  7, -1, -1, -1, -1, -1, -1, -1),
    ( 2, 10,  9,  2,  9,  7,  2,  7,  3,  7,  9,  4, -1, -1, -1, -1),
    ( 8,  4,  7,  3, 11,  2, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    (11,  4,  7, 11,  2,  4,  2,  0,  4, -1, -1, -1, -1, -1, -1, -1),
    ( 9,  0,  1,  8,  4,  7,  2,  3, 11, -1, -1, -1, -1, -1, -1, -1),
    ( 4,  7, 11,  9,  4, 11,  9, 11,  2,  9,  2,  1, -1, -1, -1, -1),
    ( 3, 10,  1,  3, 11, 10,  7,  8,  4, -1, -1, -1, -1, -1, -1, -1),
    ( 1, 11, 10,  1,  4, 11,  1,  0,  4,  7, 11,  4, -1, -1, -1, -1),
    ( 4,  7,  8,  9,  0, 11,  9, 11, 10, 11,  0,  3, -1, -1, -1, -1),
    ( 4,  7, 11,  4, 11,  9,  9, 11, 10, -1, -1, -1, -1, -1, -1, -1),
    ( 9,  5,  4, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 9,  5,  4,  0,  8,  3, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 0,  5,  4,  1,  5,  0, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 8,  5,  4,  8,  3,  5,  3,  1,  5, -1, -1, -1, -1, -1, -1, -1),
    ( 1,  2, 10,  9,  5,  4, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 3,  0,  8,  1,  2, 10,  4,  9,  5, -1, -1, -1, -1, -1, -1, -1),
    ( 5,  2, 10,  5,  4,  2,  4,  0,  2, -1, -1, -1, -1, -1, -1, -1),
    ( 2, 10,  5,  3,  2,  5,  3,  5,  4,  3,  4,  8, -1, -1, -1, -1),
    ( 9,  5,  4,  2,  3, 11, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 0, 11,  2,  0,  8, 11,  4,  9,  5, -1, -1, -1, -1, -1, -1, -1),
    ( 0,  5,  4,  0,  1,  5,  2,  3, 11, -1, -1, -1, -1, -1, -1, -1),
    ( 2,  1,  5,  2,  5,  8,  2,  8, 11,  4,  8,  5, -1, -1, -1, -1),
    (10,  3, 11, 10,  1,  3,  9,  5,  4, -1, -1, -1, -1, -1, -1, -1),
    ( 4,  9,  5,  0,  8,  1,  8, 10,  1,  8, 11, 10, -1, -1, -1, -1),
    ( 5,  4,  0,  5,  0, 11,  5, 11, 10, 11,  0,  3, -1, -1, -1, -1),
    ( 5,  4,  8,  5,  8, 10, 10,  8, 11, -1, -1, -1, -1, -1, -1, -1),
    ( 9,  7,  8,  5,  7,  9, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 9,  3,  0,  9,  5,  3,  5,  7,  3, -1, -1, -1, -1, -1, -1, -1),
    ( 0,  7,  8,  0,  1,  7,  1,  5,  7, -1, -1, -1, -1, -1, -1, -1),
    ( 1,  5,  3,  3,  5,  7, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 9,  7,  8,  9,  5,  7, 10,  1,  2, -1, -1, -1, -1, -1, -1, -1),
    (10,  1,  2,  9,  5,  0,  5,  3,  0,  5,  7,  3, -1, -1, -1, -1),
    ( 8,  0,  2,  8,  2,  5,  8,  5,  7, 10,  5,  2, -1, -1, -1, -1),
    ( 2, 10,  5,  2,  5,  3,  3,  5,  7, -1, -1, -1, -1, -1, -1, -1),
    ( 7,  9,  5,  7,  8,  9,  3, 11,  2, -1, -1, -1, -1, -1, -1, -1),
    ( 9,  5,  7,  9,  7,  2,  9,  2,  0,  2,  7, 11, -1, -1, -1, -1),
    ( 2,  3, 11,  0,  1,  8,  1,  7,  8,  1,  5,  7, -1, -1, -1, -1),
    (11,  2,  1, 11,  1,  7,  7,  1,  5, -1, -1, -1, -1, -1, -1, -1),
    ( 9,  5,  8,  8,  5,  7, 10,  1,  3, 10,  3, 11, -1, -1, -1, -1),
    ( 5,  7,  0,  5,  0,  9,  7, 11,  0,  1,  0, 10, 11, 10,  0, -1),
    (11, 10,  0, 11,  0,  3, 10,  5,  0,  8,  0,  7,  5,  7,  0, -1),
    (11, 10,  5,  7, 11,  5, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    (10,  6,  5, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 0,  8,  3,  5, 10,  6, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 9,  0,  1,  5, 10,  6, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 1,  8,  3,  1,  9,  8,  5, 10,  6, -1, -1, -1, -1, -1, -1, -1),
    ( 1,  6,  5,  2,  6,  1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 1,  6,  5,  1,  2,  6,  3,  0,  8, -1, -1, -1, -1, -1, -1, -1),
    ( 9,  6,  5,  9,  0,  6,  0,  2,  6, -1, -1, -1, -1, -1, -1, -1),
    ( 5,  9,  8,  5,  8,  2,  5,  2,  6,  3,  2,  8, -1, -1, -1, -1),
    ( 2,  3, 11, 10,  6,  5, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    (11,  0,  8, 11,  2,  0, 10,  6,  5, -1, -1, -1, -1, -1, -1, -1),
    ( 0,  1,  9,  2,  3, 11,  5, 10,  6, -1, -1, -1, -1, -1, -1, -1),
    ( 5, 10,  6,  1,  9,  2,  9, 11,  2,  9,  8, 11, -1, -1, -1, -1),
    ( 6,  3, 11,  6,  5,  3,  5,  1,  3, -1, -1, -1, -1, -1, -1, -1),
    ( 0,  8, 11,  0, 11,  5,  0,  5,  1,  5, 11,  6, -1, -1, -1, -1),
    ( 3, 11,  6,  0,  3,  6,  0,  6,  5,  0,  5,  9, -1, -1, -1, -1),
    ( 6,  5,  9,  6,  9, 11, 11,  9,  8, -1, -1, -1, -1, -1, -1, -1),
    ( 5, 10,  6,  4,  7,  8, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 4,  3,  0,  4,  7,  3,  6,  5, 10, -1, -1, -1, -1, -1, -1, -1),
    ( 1,  9,  0,  5, 10,  6,  8,  4,  7, -1, -1, -1, -1, -1, -1, -1),
    (10,  6,  5,  1,  9,  7,  1,  7,  3,  7,  9,  4, -1, -1, -1, -1),
    ( 6,  1,  2,  6,  5,  1,  4,  7,  8, -1, -1, -1, -1, -1, -1, -1),
    ( 1,  2,  5,  5,  2,  6,  3,  0,  4,  3,  4,  7, -1, -1, -1, -1),
    ( 8,  4,  7,  9,  0,  5,  0,  6,  5,  0,  2,  6, -1, -1, -1, -1),
    ( 7,  3,  9,  7,  9,  4,  3,  2,  9,  5,  9,  6,  2,  6,  9, -1),
    ( 3, 11,  2,  7,  8,  4, 10,  6,  5, -1, -1, -1, -1, -1, -1, -1),
    ( 5, 10,  6,  4,  7,  2,  4,  2,  0,  2,  7, 11, -1, -1, -1, -1),
    ( 0,  1,  9,  4,  7,  8,  2,  3, 11,  5, 10,  6, -1, -1, -1, -1),
    ( 9,  2,  1,  9, 11,  2,  9,  4, 11,  7, 11,  4,  5, 10,  6, -1),
    ( 8,  4,  7,  3, 11,  5,  3,  5,  1,  5, 11,  6, -1, -1, -1, -1),
    ( 5,  1, 11,  5, 11,  6,  1,  0, 11,  7, 11,  4,  0,  4, 11, -1),
    ( 0,  5,  9,  0,  6,  5,  0,  3,  6, 11,  6,  3,  8,  4,  7, -1),
    ( 6,  5,  9,  6,  9, 11,  4,  7,  9,  7, 11,  9, -1, -1, -1, -1),
    (10,  4,  9,  6,  4, 10, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 4, 10,  6,  4,  9, 10,  0,  8,  3, -1, -1, -1, -1, -1, -1, -1),
    (10,  0,  1, 10,  6,  0,  6,  4,  0, -1, -1, -1, -1, -1, -1, -1),
    ( 8,  3,  1,  8,  1,  6,  8,  6,  4,  6,  1, 10, -1, -1, -1, -1),
    ( 1,  4,  9,  1,  2,  4,  2,  6,  4, -1, -1, -1, -1, -1, -1, -1),
    ( 3,  0,  8,  1,  2,  9,  2,  4,  9,  2,  6,  4, -1, -1, -1, -1),
    ( 0,  2,  4,  4,  2,  6, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 8,  3,  2,  8,  2,  4,  4,  2,  6, -1, -1, -1, -1, -1, -1, -1),
    (10,  4,  9, 10,  6,  4, 11,  2,  3, -1, -1, -1, -1, -1, -1, -1),
    ( 0,  8,  2,  2,  8, 11,  4,  9, 10,  4, 10,  6, -1, -1, -1, -1),
    ( 3, 11,  2,  0,  1,  6,  0,  6,  4,  6,  1, 10, -1, -1, -1, -1),
    ( 6,  4,  1,  6,  1, 10,  4,  8,  1,  2,  1, 11,  8, 11,  1, -1),
    ( 9,  6,  4,  9,  3,  6,  9,  1,  3, 11,  6,  3, -1, -1, -1, -1),
    ( 8, 11,  1,  8,  1,  0, 11,  6,  1,  9,  1,  4,  6,  4,  1, -1),
    ( 3, 11,  6,  3,  6,  0,  0,  6,  4, -1, -1, -1, -1, -1, -1, -1),
    ( 6,  4,  8, 11,  6,  8, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 7, 10,  6,  7,  8, 10,  8,  9, 10, -1, -1, -1, -1, -1, -1, -1),
    ( 0,  7,  3,  0, 10,  7,  0,  9, 10,  6,  7, 10, -1, -1, -1, -1),
    (10,  6,  7,  1, 10,  7,  1,  7,  8,  1,  8,  0, -1, -1, -1, -1),
    (10,  6,  7, 10,  7,  1,  1,  7,  3, -1, -1, -1, -1, -1, -1, -1),
    ( 1,  2,  6,  1,  6,  8,  1,  8,  9,  8,  6,  7, -1, -1, -1, -1),
    ( 2,  6,  9,  2,  9,  1,  6,  7,  9,  0,  9,  3,  7,  3,  9, -1),
    ( 7,  8,  0,  7,  0,  6,  6,  0,  2, -1, -1, -1, -1, -1, -1, -1),
    ( 7,  3,  2,  6,  7,  2, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 2,  3, 11, 10,  6,  8, 10,  8,  9,  8,  6,  7, -1, -1, -1, -1),
    ( 2,  0,  7,  2,  7, 11,  0,  9,  7,  6,  7, 10,  9, 10,  7, -1),
    ( 1,  8,  0,  1,  7,  8,  1, 10,  7,  6,  7, 10,  2,  3, 11, -1),
    (11,  2,  1, 11,  1,  7, 10,  6,  1,  6,  7,  1, -1, -1, -1, -1),
    ( 8,  9,  6,  8,  6,  7,  9,  1,  6, 11,  6,  3,  1,  3,  6, -1),
    ( 0,  9,  1, 11,  6,  7, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 7,  8,  0,  7,  0,  6,  3, 11,  0, 11,  6,  0, -1, -1, -1, -1),
    ( 7, 11,  6, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 7,  6, 11, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 3,  0,  8, 11,  7,  6, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 0,  1,  9, 11,  7,  6, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 8,  1,  9,  8,  3,  1, 11,  7,  6, -1, -1, -1, -1, -1, -1, -1),
    (10,  1,  2,  6, 11,  7, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 1,  2, 10,  3,  0,  8,  6, 11,  7, -1, -1, -1, -1, -1, -1, -1),
    ( 2,  9,  0,  2, 10,  9,  6, 11,  7, -1, -1, -1, -1, -1, -1, -1),
    ( 6, 11,  7,  2, 10,  3, 10,  8,  3, 10,  9,  8, -1, -1, -1, -1),
    ( 7,  2,  3,  6,  2,  7, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 7,  0,  8,  7,  6,  0,  6,  2,  0, -1, -1, -1, -1, -1, -1, -1),
    ( 2,  7,  6,  2,  3,  7,  0,  1,  9, -1, -1, -1, -1, -1, -1, -1),
    ( 1,  6,  2,  1,  8,  6,  1,  9,  8,  8,  7,  6, -1, -1, -1, -1),
    (10,  7,  6, 10,  1,  7,  1,  3,  7, -1, -1, -1, -1, -1, -1, -1),
    (10,  7,  6,  1,  7, 10,  1,  8,  7,  1,  0,  8, -1, -1, -1, -1),
    ( 0,  3,  7,  0,  7, 10,  0, 10,  9,  6, 10,  7, -1, -1, -1, -1),
    ( 7,  6, 10,  7, 10,  8,  8, 10,  9, -1, -1, -1, -1, -1, -1, -1),
    ( 6,  8,  4, 11,  8,  6, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 3,  6, 11,  3,  0,  6,  0,  4,  6, -1, -1, -1, -1, -1, -1, -1),
    ( 8,  6, 11,  8,  4,  6,  9,  0,  1, -1, -1, -1, -1, -1, -1, -1),
    ( 9,  4,  6,  9,  6,  3,  9,  3,  1, 11,  3,  6, -1, -1, -1, -1),
    ( 6,  8,  4,  6, 11,  8,  2, 10,  1, -1, -1, -1, -1, -1, -1, -1),
    ( 1,  2, 10,  3,  0, 11,  0,  6, 11,  0,  4,  6, -1, -1, -1, -1),
    ( 4, 11,  8,  4,  6, 11,  0,  2,  9,  2, 10,  9, -1, -1, -1, -1),
    (10,  9,  3, 10,  3,  2,  9,  4,  3, 11,  3,  6,  4,  6,  3, -1),
    ( 8,  2,  3,  8,  4,  2,  4,  6,  2, -1, -1, -1, -1, -1, -1, -1),
    ( 0,  4,  2,  4,  6,  2, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 1,  9,  0,  2,  3,  4,  2,  4,  6,  4,  3,  8, -1, -1, -1, -1),
    ( 1,  9,  4,  1,  4,  2,  2,  4,  6, -1, -1, -1, -1, -1, -1, -1),
    ( 8,  1,  3,  8,  6,  1,  8,  4,  6,  6, 10,  1, -1, -1, -1, -1),
    (10,  1,  0, 10,  0,  6,  6,  0,  4, -1, -1, -1, -1, -1, -1, -1),
    ( 4,  6,  3,  4,  3,  8,  6, 10,  3,  0,  3,  9, 10,  9,  3, -1),
    (10,  9,  4,  6, 10,  4, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 4,  9,  5,  7,  6, 11, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 0,  8,  3,  4,  9,  5, 11,  7,  6, -1, -1, -1, -1, -1, -1, -1),
    ( 5,  0,  1,  5,  4,  0,  7,  6, 11, -1, -1, -1, -1, -1, -1, -1),
    (11,  7,  6,  8,  3,  4,  3,  5,  4,  3,  1,  5, -1, -1, -1, -1),
    ( 9,  5,  4, 10,  1,  2,  7,  6, 11, -1, -1, -1, -1, -1, -1, -1),
    ( 6, 11,  7,  1,  2, 10,  0,  8,  3,  4,  9,  5, -1, -1, -1, -1),
    ( 7,  6, 11,  5,  4, 10,  4,  2, 10,  4,  0,  2, -1, -1, -1, -1),
    ( 3,  4,  8,  3,  5,  4,  3,  2,  5, 10,  5,  2, 11,  7,  6, -1),
    ( 7,  2,  3,  7,  6,  2,  5,  4,  9, -1, -1, -1, -1, -1, -1, -1),
    ( 9,  5,  4,  0,  8,  6,  0,  6,  2,  6,  8,  7, -1, -1, -1, -1),
    ( 3,  6,  2,  3,  7,  6,  1,  5,  0,  5,  4,  0, -1, -1, -1, -1),
    ( 6,  2,  8,  6,  8,  7,  2,  1,  8,  4,  8,  5,  1,  5,  8, -1),
    ( 9,  5,  4, 10,  1,  6,  1,  7,  6,  1,  3,  7, -1, -1, -1, -1),
    ( 1,  6, 10,  1,  7,  6,  1,  0,  7,  8,  7,  0,  9,  5,  4, -1),
    ( 4,  0, 10,  4, 10,  5,  0,  3, 10,  6, 10,  7,  3,  7, 10, -1),
    ( 7,  6, 10,  7, 10,  8,  5,  4, 10,  4,  8, 10, -1, -1, -1, -1),
    ( 6,  9,  5,  6, 11,  9, 11,  8,  9, -1, -1, -1, -1, -1, -1, -1),
    ( 3,  6, 11,  0,  6,  3,  0,  5,  6,  0,  9,  5, -1, -1, -1, -1),
    ( 0, 11,  8,  0,  5, 11,  0,  1,  5,  5,  6, 11, -1, -1, -1, -1),
    ( 6, 11,  3,  6,  3,  5,  5,  3,  1, -1, -1, -1, -1, -1, -1, -1),
    ( 1,  2, 10,  9,  5, 11,  9, 11,  8, 11,  5,  6, -1, -1, -1, -1),
    ( 0, 11,  3,  0,  6, 11,  0,  9,  6,  5,  6,  9,  1,  2, 10, -1),
    (11,  8,  5, 11,  5,  6,  8,  0,  5, 10,  5,  2,  0,  2,  5, -1),
    ( 6, 11,  3,  6,  3,  5,  2, 10,  3, 10,  5,  3, -1, -1, -1, -1),
    ( 5,  8,  9,  5,  2,  8,  5,  6,  2,  3,  8,  2, -1, -1, -1, -1),
    ( 9,  5,  6,  9,  6,  0,  0,  6,  2, -1, -1, -1, -1, -1, -1, -1),
    ( 1,  5,  8,  1,  8,  0,  5,  6,  8,  3,  8,  2,  6,  2,  8, -1),
    ( 1,  5,  6,  2,  1,  6, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 1,  3,  6,  1,  6, 10,  3,  8,  6,  5,  6,  9,  8,  9,  6, -1),
    (10,  1,  0, 10,  0,  6,  9,  5,  0,  5,  6,  0, -1, -1, -1, -1),
    ( 0,  3,  8,  5,  6, 10, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    (10,  5,  6, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    (11,  5, 10,  7,  5, 11, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    (11,  5, 10, 11,  7,  5,  8,  3,  0, -1, -1, -1, -1, -1, -1, -1),
    ( 5, 11,  7,  5, 10, 11,  1,  9,  0, -1, -1, -1, -1, -1, -1, -1),
    (10,  7,  5, 10, 11,  7,  9,  8,  1,  8,  3,  1, -1, -1, -1, -1),
    (11,  1,  2, 11,  7,  1,  7,  5,  1, -1, -1, -1, -1, -1, -1, -1),
    ( 0,  8,  3,  1,  2,  7,  1,  7,  5,  7,  2, 11, -1, -1, -1, -1),
    ( 9,  7,  5,  9,  2,  7,  9,  0,  2,  2, 11,  7, -1, -1, -1, -1),
    ( 7,  5,  2,  7,  2, 11,  5,  9,  2,  3,  2,  8,  9,  8,  2, -1),
    ( 2,  5, 10,  2,  3,  5,  3,  7,  5, -1, -1, -1, -1, -1, -1, -1),
    ( 8,  2,  0,  8,  5,  2,  8,  7,  5, 10,  2,  5, -1, -1, -1, -1),
    ( 9,  0,  1,  5, 10,  3,  5,  3,  7,  3, 10,  2, -1, -1, -1, -1),
    ( 9,  8,  2,  9,  2,  1,  8,  7,  2, 10,  2,  5,  7,  5,  2, -1),
    ( 1,  3,  5,  3,  7,  5, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 0,  8,  7,  0,  7,  1,  1,  7,  5, -1, -1, -1, -1, -1, -1, -1),
    ( 9,  0,  3,  9,  3,  5,  5,  3,  7, -1, -1, -1, -1, -1, -1, -1),
    ( 9,  8,  7,  5,  9,  7, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 5,  8,  4,  5, 10,  8, 10, 11,  8, -1, -1, -1, -1, -1, -1, -1),
    ( 5,  0,  4,  5, 11,  0,  5, 10, 11, 11,  3,  0, -1, -1, -1, -1),
    ( 0,  1,  9,  8,  4, 10,  8, 10, 11, 10,  4,  5, -1, -1, -1, -1),
    (10, 11,  4, 10,  4,  5, 11,  3,  4,  9,  4,  1,  3,  1,  4, -1),
    ( 2,  5,  1,  2,  8,  5,  2, 11,  8,  4,  5,  8, -1, -1, -1, -1),
    ( 0,  4, 11,  0, 11,  3,  4,  5, 11,  2, 11,  1,  5,  1, 11, -1),
    ( 0,  2,  5,  0,  5,  9,  2, 11,  5,  4,  5,  8, 11,  8,  5, -1),
    ( 9,  4,  5,  2, 11,  3, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 2,  5, 10,  3,  5,  2,  3,  4,  5,  3,  8,  4, -1, -1, -1, -1),
    ( 5, 10,  2,  5,  2,  4,  4,  2,  0, -1, -1, -1, -1, -1, -1, -1),
    ( 3, 10,  2,  3,  5, 10,  3,  8,  5,  4,  5,  8,  0,  1,  9, -1),
    ( 5, 10,  2,  5,  2,  4,  1,  9,  2,  9,  4,  2, -1, -1, -1, -1),
    ( 8,  4,  5,  8,  5,  3,  3,  5,  1, -1, -1, -1, -1, -1, -1, -1),
    ( 0,  4,  5,  1,  0,  5, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 8,  4,  5,  8,  5,  3,  9,  0,  5,  0,  3,  5, -1, -1, -1, -1),
    ( 9,  4,  5, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 4, 11,  7,  4,  9, 11,  9, 10, 11, -1, -1, -1, -1, -1, -1, -1),
    ( 0,  8,  3,  4,  9,  7,  9, 11,  7,  9, 10, 11, -1, -1, -1, -1),
    ( 1, 10, 11,  1, 11,  4,  1,  4,  0,  7,  4, 11, -1, -1, -1, -1),
    ( 3,  1,  4,  3,  4,  8,  1, 10,  4,  7,  4, 11, 10, 11,  4, -1),
    ( 4, 11,  7,  9, 11,  4,  9,  2, 11,  9,  1,  2, -1, -1, -1, -1),
    ( 9,  7,  4,  9, 11,  7,  9,  1, 11,  2, 11,  1,  0,  8,  3, -1),
    (11,  7,  4, 11,  4,  2,  2,  4,  0, -1, -1, -1, -1, -1, -1, -1),
    (11,  7,  4, 11,  4,  2,  8,  3,  4,  3,  2,  4, -1, -1, -1, -1),
    ( 2,  9, 10,  2,  7,  9,  2,  3,  7,  7,  4,  9, -1, -1, -1, -1),
    ( 9, 10,  7,  9,  7,  4, 10,  2,  7,  8,  7,  0,  2,  0,  7, -1),
    ( 3,  7, 10,  3, 10,  2,  7,  4, 10,  1, 10,  0,  4,  0, 10, -1),
    ( 1, 10,  2,  8,  7,  4, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 4,  9,  1,  4,  1,  7,  7,  1,  3, -1, -1, -1, -1, -1, -1, -1),
    ( 4,  9,  1,  4,  1,  7,  0,  8,  1,  8,  7,  1, -1, -1, -1, -1),
    ( 4,  0,  3,  7,  4,  3, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 4,  8,  7, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 9, 10,  8, 10, 11,  8, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 3,  0,  9,  3,  9, 11, 11,  9, 10, -1, -1, -1, -1, -1, -1, -1),
    ( 0,  1, 10,  0, 10,  8,  8, 10, 11, -1, -1, -1, -1, -1, -1, -1),
    ( 3,  1, 10, 11,  3, 10, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 1,  2, 11,  1, 11,  9,  9, 11,  8, -1, -1, -1, -1, -1, -1, -1),
    ( 3,  0,  9,  3,  9, 11,  1,  2,  9,  2, 11,  9, -1, -1, -1, -1),
    ( 0,  2, 11,  8,  0, 11, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 3,  2, 11, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 2,  3,  8,  2,  8, 10, 10,  8,  9, -1, -1, -1, -1, -1, -1, -1),
    ( 9, 10,  2,  0,  9,  2, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 2,  3,  8,  2,  8, 10,  0,  1,  8,  1, 10,  8, -1, -1, -1, -1),
    ( 1, 10,  2, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 1,  3,  8,  9,  1,  8, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 0,  9,  1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    ( 0,  3,  8, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
    (-1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1),
)
# fmt: on


def _case_edge_entries():
    """Per case, 15 entries (dx, dy, dz, axis): the lower node offset and axis of each table edge."""
    entries = []
    for case in range(256):
        row = TRI_TABLE[case]
        for s in range(3 * MAX_CASE_TRIANGLES):
            e = row[s]
            if e < 0:
                entries.append((0, 0, 0, 0))
                continue
            a, b = (CORNER_OFFSETS[c] for c in EDGE_CORNERS[e])
            lower = tuple(min(a[d], b[d]) for d in range(3))
            axis = next(d for d in range(3) if a[d] != b[d])
            entries.append((*lower, axis))
    return entries


_table_cache = {}


def case_tables(device):
    """Triangle tables on ``device``, built once per device.

    Returns ``(case_tri_count, case_edges)``: int32 shape (256,) and vec4i shape (256 * 15,).
    """
    device = wp.get_device(device)
    key = device.alias
    if key not in _table_cache:
        counts = [sum(1 for e in TRI_TABLE[c] if e >= 0) // 3 for c in range(256)]
        _table_cache[key] = (
            wp.array(counts, dtype=wp.int32, device=device),
            wp.array(_case_edge_entries(), dtype=wp.vec4i, device=device),
        )
    return _table_cache[key]


@wp.struct
class GridSpec:
    """A scalar field on a regular grid, as the kernels see it."""

    field: wp.array3d(dtype=wp.float32)  # node values, shape (nx, ny, nz)
    iso: float  # iso value
    sign: float  # +1: inside below iso; -1: inside above iso
    pad: int  # 1: virtual outside layer around the grid; 0: none
    node_count: wp.vec3i  # padded node counts (nx + 2 pad, ...)
    lower: wp.vec3  # position of padded node (0, 0, 0) [m]
    spacing: wp.vec3  # node spacing [m]
    block: int  # nodes per block and axis
    block_count: wp.vec3i  # blocks per axis


@wp.func
def node_value(grid: GridSpec, i: int, j: int, k: int):
    """g at padded node (i, j, k); OUTSIDE_VALUE off the field (padding or past the last node)."""
    x = i - grid.pad
    y = j - grid.pad
    z = k - grid.pad
    shape = grid.field.shape
    if x < 0 or y < 0 or z < 0 or x >= shape[0] or y >= shape[1] or z >= shape[2]:
        return OUTSIDE_VALUE
    return grid.sign * (grid.field[x, y, z] - grid.iso)


@wp.func
def node_in_field(grid: GridSpec, n: wp.vec3i):
    shape = grid.field.shape
    x = n[0] - grid.pad
    y = n[1] - grid.pad
    z = n[2] - grid.pad
    return x >= 0 and y >= 0 and z >= 0 and x < shape[0] and y < shape[1] and z < shape[2]


@wp.func
def node_gradient(grid: GridSpec, n: wp.vec3i):
    """Gradient of g at an in-field node [1/m]: central differences, one-sided at the boundary."""
    shape = grid.field.shape
    x = n[0] - grid.pad
    y = n[1] - grid.pad
    z = n[2] - grid.pad
    x0 = wp.max(x - 1, 0)
    x1 = wp.min(x + 1, shape[0] - 1)
    y0 = wp.max(y - 1, 0)
    y1 = wp.min(y + 1, shape[1] - 1)
    z0 = wp.max(z - 1, 0)
    z1 = wp.min(z + 1, shape[2] - 1)
    f = grid.field
    gx = (f[x1, y, z] - f[x0, y, z]) / (float(x1 - x0) * grid.spacing[0])
    gy = (f[x, y1, z] - f[x, y0, z]) / (float(y1 - y0) * grid.spacing[1])
    gz = (f[x, y, z1] - f[x, y, z0]) / (float(z1 - z0) * grid.spacing[2])
    return grid.sign * wp.vec3(gx, gy, gz)


@wp.func
def face_nibble(grid: GridSpec, i: int, j: int, k: int):
    """Inside bits of the z = k face of cell (i, j, .): corners 0-3 (as bits 0-3)."""
    code = int(0)
    for c in range(4):
        g = node_value(
            grid,
            i + wp.static(CORNER_OFFSETS[c][0]),
            j + wp.static(CORNER_OFFSETS[c][1]),
            k,
        )
        if g < 0.0:
            code = code | wp.static(1 << c)
    return code


@wp.func
def block_origin(grid: GridSpec, b: int):
    """Lowest padded node of block b."""
    bc = grid.block_count
    bz = b % bc[2]
    by = (b // bc[2]) % bc[1]
    bx = b // (bc[1] * bc[2])
    return wp.vec3i(bx * grid.block, by * grid.block, bz * grid.block)


@wp.func
def block_is_mixed(grid: GridSpec, lo: wp.vec3i):
    """True when the nodes of the block's cells and edges ([lo, lo + block]) are not all on one side."""
    n = grid.node_count
    shape = grid.field.shape
    pad = grid.pad
    # Field-index range of the nodes; padding nodes in the range are outside.
    x0 = lo[0] - pad
    y0 = lo[1] - pad
    z0 = lo[2] - pad
    x1 = wp.min(lo[0] + grid.block, n[0] - 1) - pad
    y1 = wp.min(lo[1] + grid.block, n[1] - 1) - pad
    z1 = wp.min(lo[2] + grid.block, n[2] - 1) - pad
    has_outside = x0 < 0 or y0 < 0 or z0 < 0 or x1 >= shape[0] or y1 >= shape[1] or z1 >= shape[2]
    x0 = wp.max(x0, 0)
    y0 = wp.max(y0, 0)
    z0 = wp.max(z0, 0)
    x1 = wp.min(x1, shape[0] - 1)
    y1 = wp.min(y1, shape[1] - 1)
    z1 = wp.min(z1, shape[2] - 1)
    inside = int(0)
    seen = int(0)
    for x in range(x0, x1 + 1):
        for y in range(y0, y1 + 1):
            row = int(0)
            for z in range(z0, z1 + 1):
                row += wp.where(grid.sign * (grid.field[x, y, z] - grid.iso) < 0.0, 1, 0)
            inside += row
            seen += z1 + 1 - z0
            if inside > 0 and (has_outside or inside < seen):
                return True
    return False


@wp.func
def owned_end(grid: GridSpec, lo: wp.vec3i):
    """One past the last padded node the block owns, per axis."""
    n = grid.node_count
    return wp.vec3i(
        wp.min(lo[0] + grid.block, n[0]),
        wp.min(lo[1] + grid.block, n[1]),
        wp.min(lo[2] + grid.block, n[2]),
    )


@wp.func
def node_index(grid: GridSpec, i: int, j: int, k: int):
    """Flat index of padded node (i, j, k)."""
    n = grid.node_count
    return (i * n[1] + j) * n[2] + k


@wp.func
def edge_crossings(grid: GridSpec, code: int, i: int, j: int, k: int):
    """Which of the +x, +y, +z edges leaving node (i, j, k) (corner 0 of `code`) the surface crosses."""
    n = grid.node_count
    inside0 = code & 1
    cx = i + 1 < n[0] and ((code >> 1) & 1) != inside0
    cy = j + 1 < n[1] and ((code >> 3) & 1) != inside0
    cz = k + 1 < n[2] and ((code >> 4) & 1) != inside0
    return wp.vec3i(wp.where(cx, 1, 0), wp.where(cy, 1, 0), wp.where(cz, 1, 0))


@wp.kernel
def count_block_elements(
    grid: GridSpec,
    case_tri_count: wp.array(dtype=wp.int32),
    block_counts_out: wp.array(dtype=wp.vec2i),
    node_case_out: wp.array(dtype=wp.uint8),
):
    """Per block: (crossed edges it owns, triangles of the cells it owns), shape (block_total,).

    Also stores the case code of every owned node's cell (corners past the grid count as
    outside) in node_case_out, shape (padded node count,), for the emission kernels.
    """
    b = wp.tid()
    lo = block_origin(grid, b)
    if not block_is_mixed(grid, lo):
        block_counts_out[b] = wp.vec2i(0, 0)
        return
    n = grid.node_count
    hi = owned_end(grid, lo)
    vertex_count = int(0)
    tri_count = int(0)
    for i in range(lo[0], hi[0]):
        for j in range(lo[1], hi[1]):
            low = face_nibble(grid, i, j, lo[2])
            for k in range(lo[2], hi[2]):
                high = face_nibble(grid, i, j, k + 1)
                code = low | (high << 4)
                low = high
                node_case_out[node_index(grid, i, j, k)] = wp.uint8(code)
                c = edge_crossings(grid, code, i, j, k)
                vertex_count += c[0] + c[1] + c[2]
                if i + 1 < n[0] and j + 1 < n[1] and k + 1 < n[2]:
                    tri_count += case_tri_count[code]
    block_counts_out[b] = wp.vec2i(vertex_count, tri_count)


@wp.func
def emit_edge_vertex(
    grid: GridSpec,
    node: wp.vec3i,
    axis: int,
    vertex: int,
    vertices_out: wp.array(dtype=wp.vec3),
    normals_out: wp.array(dtype=wp.vec3),
):
    """Write the welded vertex of the crossed edge from `node` along `axis` and its unit normal."""
    e = wp.vec3i(0, 0, 0)
    e[axis] = 1
    other = node + e
    g0 = node_value(grid, node[0], node[1], node[2])
    g1 = node_value(grid, other[0], other[1], other[2])
    t = g0 / (g0 - g1)
    if wp.isnan(t):  # NaN field value on this edge
        t = 0.5
    t = wp.clamp(t, EDGE_T_MIN, 1.0 - EDGE_T_MIN)
    direction = wp.vec3(float(e[0]), float(e[1]), float(e[2]))
    p = wp.vec3(float(node[0]), float(node[1]), float(node[2])) + t * direction
    vertices_out[vertex] = grid.lower + wp.cw_mul(p, grid.spacing)

    # Fallback normal: along the edge, toward its outside end.
    normal = wp.where(g0 < 0.0, direction, -direction)
    if node_in_field(grid, node) and node_in_field(grid, other):
        gradient = wp.lerp(node_gradient(grid, node), node_gradient(grid, other), t)
        length = wp.length(gradient)
        if length > 0.0 and length < 1.0e30:
            normal = gradient / length
    normals_out[vertex] = normal


@wp.kernel
def emit_block_vertices(
    grid: GridSpec,
    block_counts: wp.array(dtype=wp.vec2i),
    block_offsets: wp.array(dtype=wp.vec2i),
    node_case: wp.array(dtype=wp.uint8),
    node_vertex_out: wp.array(dtype=wp.int32),
    vertices_out: wp.array(dtype=wp.vec3),
    normals_out: wp.array(dtype=wp.vec3),
):
    """Emit the vertices of a block's crossed edges, in node order then x, y, z.

    block_offsets is the inclusive scan of block_counts. node_vertex_out[node] (shape: padded
    node count) receives the index of the node's first vertex; its other edges follow it.
    """
    b = wp.tid()
    counts = block_counts[b]
    if counts[0] == 0:
        return
    vertex = block_offsets[b][0] - counts[0]
    lo = block_origin(grid, b)
    hi = owned_end(grid, lo)
    for i in range(lo[0], hi[0]):
        for j in range(lo[1], hi[1]):
            for k in range(lo[2], hi[2]):
                node = node_index(grid, i, j, k)
                code = int(node_case[node])
                c = edge_crossings(grid, code, i, j, k)
                if c[0] + c[1] + c[2] > 0:
                    node_vertex_out[node] = vertex
                    for axis in range(3):
                        if c[axis] != 0:
                            emit_edge_vertex(grid, wp.vec3i(i, j, k), axis, vertex, vertices_out, normals_out)
                            vertex += 1


@wp.func
def edge_vertex_index(
    grid: GridSpec,
    node: wp.vec3i,
    axis: int,
    node_case: wp.array(dtype=wp.uint8),
    node_vertex: wp.array(dtype=wp.int32),
):
    """Vertex index of the crossed edge leaving `node` along `axis`."""
    index = node_index(grid, node[0], node[1], node[2])
    c = edge_crossings(grid, int(node_case[index]), node[0], node[1], node[2])
    vertex = node_vertex[index]
    if axis > 0:
        vertex += c[0]
    if axis > 1:
        vertex += c[1]
    return vertex


@wp.kernel
def emit_block_triangles(
    grid: GridSpec,
    case_tri_count: wp.array(dtype=wp.int32),
    case_edges: wp.array(dtype=wp.vec4i),
    block_counts: wp.array(dtype=wp.vec2i),
    block_offsets: wp.array(dtype=wp.vec2i),
    node_case: wp.array(dtype=wp.uint8),
    node_vertex: wp.array(dtype=wp.int32),
    faces_out: wp.array2d(dtype=wp.int32),
):
    """Emit the triangles of a block's cells, counter-clockwise seen from outside, shape (F, 3)."""
    b = wp.tid()
    counts = block_counts[b]
    if counts[1] == 0:
        return
    face = block_offsets[b][1] - counts[1]
    n = grid.node_count
    lo = block_origin(grid, b)
    hi = owned_end(grid, lo)
    for i in range(lo[0], wp.min(hi[0], n[0] - 1)):
        for j in range(lo[1], wp.min(hi[1], n[1] - 1)):
            for k in range(lo[2], wp.min(hi[2], n[2] - 1)):
                code = int(node_case[node_index(grid, i, j, k)])
                tri_count = case_tri_count[code]
                for q in range(tri_count):
                    ids = wp.vec3i(0, 0, 0)
                    for s in range(3):
                        entry = case_edges[code * 15 + q * 3 + s]
                        node = wp.vec3i(i + entry[0], j + entry[1], k + entry[2])
                        ids[s] = edge_vertex_index(grid, node, entry[3], node_case, node_vertex)
                    faces_out[face, 0] = ids[0]
                    faces_out[face, 1] = ids[2]
                    faces_out[face, 2] = ids[1]
                    face += 1


@wp.kernel
def find_non_finite_node(field: wp.array3d(dtype=float), first_out: wp.array(dtype=int)):
    """``first_out[0] = min`` linear index ``(i ny + j) nz + k`` of the nodes holding NaN or
    infinity (the caller fills it with the node count beforehand)."""
    i, j, k = wp.tid()
    v = field[i, j, k]
    if not wp.isfinite(v):
        wp.atomic_min(first_out, 0, (i * field.shape[1] + j) * field.shape[2] + k)
