"""Implicit surface: a gyroid sheet clipped to a ball, sampled by a Warp kernel, meshed, written to USD.

A Warp kernel samples an approximate signed distance on a grid over [-1, 1]^3 m; marching cubes
turns its zero level into a welded, watertight triangle mesh with outward gradient normals. The
script prints the mesh's size, area [m^2], enclosed volume [m^3] and genus (from the Euler
characteristic V - E + F = 2 - 2 genus) and writes one static USD mesh.

    python examples/implicit_surface.py --resolution 128 --out usd_out/implicit_surface.usda
"""

import argparse
import sys

import numpy as np
import warp as wp
from warpsim.kernels.implicit_fields import gyroid_ball

from warpsim.cli_common import DefaultsHelpFormatter, device_arg, run_script
from warpsim.meshing.marching_cubes import marching_cubes
from warpsim.verbosity import set_warp_verbosity


class Example:
    def __init__(self, device=None, resolution=96, period=0.8, thickness=0.08):
        self.device = wp.get_device(device)
        self.lower = (-1.0, -1.0, -1.0)
        h = 2.0 / (resolution - 1)
        self.spacing = (h, h, h)
        self.field = wp.zeros((resolution,) * 3, dtype=wp.float32, device=self.device)
        gyroid_ball(self.field, self.lower, self.spacing, period=period, thickness=thickness)
        self.mesh = marching_cubes(self.field, self.spacing, self.lower, iso=0.0, device=self.device)

    def stats(self):
        v, f, _ = self.mesh.numpy()
        p = v[f].astype(np.float64)
        area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1).sum()
        volume = np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2])).sum() / 6.0
        edges = np.unique(np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1), axis=0)
        return area, volume, len(v) - len(edges) + len(f)

    def write(self, path):
        from warpsim.usd.writer import UsdCacheWriter

        v, f, n = self.mesh.numpy()
        writer = UsdCacheWriter(path)
        writer.add_static_mesh("surface", v, np.full(len(f), 3, np.int32), f.reshape(-1),
                               color=(0.3, 0.6, 0.9), double_sided=False)
        writer.add_primvar("surface", "normals", "normal3f[]", "vertex", value=n)
        return writer.close()


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=DefaultsHelpFormatter)
    parser.add_argument("--device", default=None)
    parser.add_argument("--resolution", type=int, default=96, help="grid nodes per axis")
    parser.add_argument("--out", default="usd_out/implicit_surface.usda")
    parser.add_argument("--verbose", action="store_true", help="show Warp's banner and module-load lines")
    args = parser.parse_args(argv)
    set_warp_verbosity(args.verbose)
    args.device = device_arg(args.device)  # one line naming the devices there are
    example = Example(args.device, args.resolution)
    area, volume, chi = example.stats()
    print(f"{example.mesh.vertex_count} vertices, {example.mesh.face_count} triangles, area {area:.4f} m^2, "
          f"volume {volume:.5f} m^3, Euler characteristic {chi} (genus {(2 - chi) // 2} if connected)")
    print(f"wrote {example.write(args.out)}")


if __name__ == "__main__":
    sys.exit(run_script(main))
