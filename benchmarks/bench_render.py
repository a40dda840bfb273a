"""Preview renderer speed: one frame of a cache, from the USD file to the image, in one process.

Two cases (the issue's goals: each under 1 s):
- ``teapot``: a frame of the ``teapot`` scene (soft-body mesh, springs as capsules, guide walls)
  at 480x360 on the CPU;
- ``liquid``: a particle-liquid frame of ``--points`` spheres (a collapsing column's shape: a
  block with a sloped front, jittered) at 480x360, meant for a GPU at 1,000,000 points.

For each it reports the whole frame (reading the prims from USD, building the ``wp.Mesh`` and
``wp.Bvh``, casting the rays, copying the image back), the gather and render parts, and as a
reference in the same process Warp's own ``example_raycast`` kernel (one bare ray per pixel
against the same triangles, normals as colours, no shading, shadows or spheres) where the frame
has triangles; the ratio says what shading, shadows and the sphere BVH cost on top.

    python benchmarks/bench_render.py --device cpu --case teapot
    python benchmarks/bench_render.py --device cuda:0 --case liquid --points 1000000
    python benchmarks/bench_render.py --device cpu --case liquid --points 20000      # a CPU check
"""
import argparse
import os
import sys
import tempfile
import time

import numpy as np
import warp as wp

from warpsim.cli_common import DefaultsHelpFormatter, device_arg, run_script
from warpsim.render import Renderer, frame_bounds
from warpsim.render.usd_scene import CacheScene
from warpsim.verbosity import set_warp_verbosity


def best_of(fn, device, repeats):
    fn()  # warm-up: compile, allocate
    wp.synchronize_device(device)
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        wp.synchronize_device(device)
        best = min(best, time.perf_counter() - t0)
    return best


def teapot_cache(folder, frames):
    from warpsim.cli import main

    path = os.path.join(folder, "teapot.usda")
    with open(os.devnull, "w") as quiet:
        code = main(["run", "teapot", "--frames", str(frames), "--out", path, "--device", "cpu", "--no-progress"],
                    quiet, quiet)
    if code != 0:
        raise SystemExit("could not write the teapot cache")
    return path, frames


def liquid_cache(folder, count, seed=0):
    """One frame of ``count`` particles: a block 2a wide, 1a tall, a/2 deep with its front sloping
    down along +x (the shape of a collapsing column), spacing from the count, inside a guide box."""
    from warpsim.usd.writer import UsdCacheWriter

    rng = np.random.default_rng(seed)
    a = 0.5
    volume = 0.75 * (2 * a) * a * (0.5 * a)  # the sloped block keeps 3/4 of the box
    s = (volume / count) ** (1.0 / 3.0)
    nx, ny, nz = (int(np.ceil(v / s)) + 1 for v in (2 * a, a, 0.5 * a))
    g = np.stack(np.meshgrid(*(np.arange(n) * s for n in (nx, ny, nz)), indexing="ij"), -1).reshape(-1, 3)
    keep = g[:, 1] <= a * (1.0 - 0.5 * g[:, 0] / (2 * a))
    p = g[keep][:count] + rng.normal(0.0, 0.05 * s, (min(count, keep.sum()), 3))
    path = os.path.join(folder, "liquid.usdc")
    with UsdCacheWriter(path, fps=60) as w:
        w.add_points("particles", radius=0.5 * s, color=(0.15, 0.45, 0.9), velocities=False)
        w.add_box("container", (-s, -s, -s), (2 * a + s, 1.2 * a, 0.5 * a + s), opacity=0.2, purpose="guide")
        w.write_frame(0, {"particles": {"points": p.astype(np.float32)}})
    return path, 0


def reference_raycast(geom, camera, width, height, device):
    """Warp's example_raycast kernel on the frame's triangles (None when it has none)."""
    if not len(geom.triangles):
        return None
    from warp.examples.core.example_raycast import draw

    mesh = wp.Mesh(wp.array(geom.points, dtype=wp.vec3, device=device),
                   wp.array(geom.triangles.reshape(-1), dtype=wp.int32, device=device))
    pixels = wp.zeros(width * height, dtype=wp.vec3, device=device)
    eye = wp.vec3(*camera.eye)

    def run():
        wp.launch(draw, dim=width * height, inputs=[mesh.id, eye, width, height, pixels], device=device)
        pixels.numpy()

    return best_of(run, device, 5)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=DefaultsHelpFormatter)
    parser.add_argument("--device", default=None, help="Warp device (default: preferred)")
    parser.add_argument("--case", choices=["teapot", "liquid"], default="teapot")
    parser.add_argument("--points", type=int, default=1_000_000, help="particles of the liquid case")
    parser.add_argument("--size", default="480x360")
    parser.add_argument("--frames", type=int, default=30, help="teapot frames to simulate (the last is drawn)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--keep", default=None, help="also write the picture here (.png)")
    args = parser.parse_args()
    set_warp_verbosity()  # quiet unless $WARPSIM_VERBOSE=1 (Warp 1.19 ignores config.quiet)
    wp.init()
    device = wp.get_device(device_arg(args.device))
    width, height = (int(v) for v in args.size.split("x"))
    with tempfile.TemporaryDirectory() as folder:
        t0 = time.perf_counter()
        path, frame = teapot_cache(folder, args.frames) if args.case == "teapot" else liquid_cache(folder, args.points)
        made = time.perf_counter() - t0
        scene = CacheScene(path)
        camera = frame_bounds(scene.bounds([frame]), width, height)
        renderer = Renderer(width, height, device=device)
        holder = {}

        def whole():
            holder["image"] = renderer.render(scene.geometry(frame), camera)

        geom = scene.geometry(frame)
        t_whole = best_of(whole, device, args.repeats)
        t_gather = best_of(lambda: scene.geometry(frame), device, args.repeats)
        t_render = best_of(lambda: renderer.render(geom, camera), device, args.repeats)
        t_ref = reference_raycast(geom, camera, width, height, device)
        if args.keep:
            from PIL import Image

            Image.fromarray(holder["image"]).save(args.keep)
    spheres, tris = len(geom.cap_r), len(geom.triangles)
    print(f"case {args.case} on {device}: {width}x{height}, {tris} triangles, {spheres} spheres/capsules "
          f"(cache made in {made:.1f} s)")
    print(f"  whole frame (USD read + BVH build + rays + copy back): {t_whole * 1e3:9.1f} ms   "
          f"({'under' if t_whole < 1.0 else 'OVER'} the 1 s goal)")
    print(f"  gather from USD:                                       {t_gather * 1e3:9.1f} ms")
    print(f"  render (BVH build + rays + copy back):                 {t_render * 1e3:9.1f} ms")
    if t_ref is not None:
        print(f"  reference: Warp example_raycast, bare rays, same triangles: {t_ref * 1e3:6.1f} ms   "
              f"render / reference = {t_render / t_ref:.2f}x")


if __name__ == "__main__":
    sys.exit(run_script(main))
