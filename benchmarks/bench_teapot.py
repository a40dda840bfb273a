"""Jiggly-teapot step: warpsim (Warp kernels) against a plain NumPy mass-spring step of the same model.

The model is the ``teapot`` scene's soft body (edge, bending and interior-lattice springs, equal
point masses) in a box of six walls (reflect mode, restitution 0.5, friction 0.3), stepped with
semi-implicit Euler under gravity at dt = 1/600 s for the low-resolution teapot (n = 4 segments
per patch edge), and dt = (1/600) (4/n)^3 at n segments: the masses (1 kg in all) shrink like
1/n^2 while the lid-knob and bottom poles gain 4n springs (and dampers) each, so the stable
explicit step shrinks like n^-3 (the damping bound sum(c) dt / m < 2 is the tighter one). The
teapot starts just above the floor so that the agreement check covers wall contacts. The NumPy
reference implements the same step
(float32, vectorised: springs with np.add.at, then the six walls in order). Both run in this
process from the same state; the script checks that they agree after a few steps, then prints
steps per second and the ratio warpsim / NumPy at each resolution. On CUDA the warpsim step is
also timed as a captured CUDA graph.

    python benchmarks/bench_teapot.py --device cpu --resolution low high
    python benchmarks/bench_teapot.py --device cuda:0 --resolution low high 24 --steps 500
"""

import argparse
import math
import sys

import numpy as np
import warp as wp
from bench_mass_spring import NumpyMassSpring
from timing import time_per_call, time_per_graph_launch

import warpsim as ws
from warpsim.bodies.softbody import add_soft_body
from warpsim.bodies.teapot import teapot_mesh
from warpsim.cli_common import DefaultsHelpFormatter, device_arg, run_script
from warpsim.verbosity import set_warp_verbosity

DT_LOW = 1.0 / 600.0


def teapot_builder(resolution, height=0.02):
    mesh = teapot_mesh(resolution)
    b = ws.ModelBuilder()
    tilt = math.radians(20.0)
    add_soft_body(b, mesh.points, mesh.faces, position=(0.0, height, 0.0),
                  rotation=(0.0, 0.0, math.sin(tilt / 2), math.cos(tilt / 2)), velocity=(1.0, 0.0, 0.6),
                  total_mass=1.0, mass_distribution="uniform", stiffness=40.0, damping=0.05, lattice_cells=6)
    return b


class NumpyTeapot(NumpyMassSpring):
    """The same step in NumPy: gravity + damped springs, semi-implicit Euler (the mass-spring
    benchmark's NumPy step), then the box walls (reflect: h' = e h, v_n' = -e v_n, Coulomb
    friction mu (1 + e) |v_n|), wall by wall."""

    def __init__(self, b, box, g=(0.0, -9.81, 0.0)):
        super().__init__(b, g)
        self.r = np.array(b.particle_radius, dtype=np.float32)
        self.normals = box.normals.astype(np.float32)
        self.offsets = box.offsets.astype(np.float32)
        self.e, self.mu = np.float32(box.restitution), np.float32(box.friction)

    def step(self, h):
        super().step(h)
        x, v = self.x, self.v
        for n, off in zip(self.normals, self.offsets):
            depth = self.r - (x @ n - off)
            hit = depth > 0.0
            if not hit.any():
                continue
            x[hit] += ((1.0 + self.e) * depth[hit])[:, None] * n
            vh = v[hit]
            vn = vh @ n
            approach = vn < 0.0
            vt = vh - vn[:, None] * n
            vt_len = np.linalg.norm(vt, axis=1)
            scale = np.where(vt_len > 0, np.maximum(0.0, 1.0 - self.mu * (1.0 + self.e) * (-vn) / np.where(
                vt_len > 0, vt_len, 1.0)), 1.0)
            new = vt * scale[:, None] - self.e * vn[:, None] * n
            v[hit] = np.where(approach[:, None], new, vh)
        self.x, self.v = x, v


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=DefaultsHelpFormatter)
    parser.add_argument("--device", default=None)
    parser.add_argument("--resolution", nargs="+", default=["low", "high"])
    parser.add_argument("--steps", type=int, default=200)
    args = parser.parse_args()
    set_warp_verbosity()  # quiet unless $WARPSIM_VERBOSE=1 (Warp 1.19 ignores config.quiet)
    device = wp.get_device(device_arg(args.device))
    print(f"device: {device} ({device.name})")
    print(f"{'res':>5} {'particles':>9} {'springs':>8} {'numpy st/s':>11} {'warpsim st/s':>13} {'ratio':>7}"
          f" {'graph st/s':>11} {'ratio':>7}")
    for res in args.resolution:
        b = teapot_builder(res)
        box = ws.Box((-0.7, 0.0, -0.7), (0.7, 1.4, 0.7), restitution=0.5, friction=0.3)
        ref = NumpyTeapot(b, box)
        sim = ws.Simulator(b.finalize(device), forces=[ws.Gravity()], colliders=[box], check_every=0)
        dt = DT_LOW * (4.0 / teapot_mesh(res).resolution) ** 3
        for _ in range(100):  # agreement first (it lands on the floor)
            ref.step(dt)
            sim.step(dt)
        err = np.abs(sim.state.positions.numpy() - ref.x).max()
        assert err < 1e-3, f"warpsim and NumPy disagree by {err} m"
        t_np = time_per_call(lambda ref=ref, dt=dt: ref.step(dt), max(20, args.steps // 10))
        t_ws = time_per_call(lambda sim=sim, dt=dt: sim.step(dt), args.steps, device)
        graph_rate, graph_ratio = "-", "-"
        if device.is_cuda:
            t_graph = time_per_graph_launch(lambda: sim.step(dt), args.steps, device)
            graph_rate, graph_ratio = f"{1 / t_graph:11.0f}", f"{t_np / t_graph:7.1f}"
        print(f"{res:>5} {b.particle_count:>9} {b.spring_count:>8} {1 / t_np:11.0f} {1 / t_ws:13.0f} "
              f"{t_np / t_ws:7.1f} {graph_rate:>11} {graph_ratio:>7}")


if __name__ == "__main__":
    sys.exit(run_script(main))
