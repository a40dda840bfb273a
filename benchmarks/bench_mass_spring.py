"""Mass-spring step: warpsim (Warp kernels) against a plain NumPy implementation of the same step.

The system is an N x N grid of particles joined by structural and shear springs under gravity,
stepped with semi-implicit Euler (forces: gravity + damped springs). Both implementations run
in this process on the same data; the script checks they agree, then prints the time per step
and the ratio NumPy / warpsim. On CUDA the warpsim step is also timed as a captured CUDA graph.

    python benchmarks/bench_mass_spring.py --device cpu --grid 32 64 --steps 50
    python benchmarks/bench_mass_spring.py --device cuda:0 --grid 64 256 512 --steps 200
"""

import argparse
import sys

import numpy as np
import warp as wp
from timing import time_per_call, time_per_graph_launch

import warpsim as ws
from warpsim.cli_common import DefaultsHelpFormatter, device_arg, run_script
from warpsim.verbosity import set_warp_verbosity


def grid_system(n, spacing=0.02, k=2000.0, kd=0.5, mass=0.01):
    b = ws.ModelBuilder()
    for j in range(n):
        for i in range(n):
            b.add_particle((i * spacing, 1.0, j * spacing), mass=0.0 if (j == 0 and i in (0, n - 1)) else mass)
    idx = lambda i, j: j * n + i  # noqa: E731
    for j in range(n):
        for i in range(n):
            if i + 1 < n:
                b.add_spring(idx(i, j), idx(i + 1, j), k, kd)
            if j + 1 < n:
                b.add_spring(idx(i, j), idx(i, j + 1), k, kd)
            if i + 1 < n and j + 1 < n:
                b.add_spring(idx(i, j), idx(i + 1, j + 1), k, kd)
                b.add_spring(idx(i + 1, j), idx(i, j + 1), k, kd)
    return b


class NumpyMassSpring:
    """The same semi-implicit Euler mass-spring step in NumPy (float32, vectorised)."""

    def __init__(self, b, g=(0.0, -9.81, 0.0)):
        self.x = np.array(b.particle_q, dtype=np.float32)
        self.v = np.array(b.particle_qd, dtype=np.float32)
        m = np.array(b.particle_mass, dtype=np.float32)
        self.m = m
        self.w = np.where(m > 0, 1.0 / np.where(m > 0, m, 1), 0).astype(np.float32)
        s = np.array(b.spring_indices)
        self.i, self.j = s[:, 0], s[:, 1]
        self.L = np.array(b.spring_rest_length, dtype=np.float32)
        self.k = np.array(b.spring_stiffness, dtype=np.float32)
        self.kd = np.array(b.spring_damping, dtype=np.float32)
        self.g = np.array(g, dtype=np.float32)

    def step(self, h):
        x, v = self.x, self.v
        u = x[self.i] - x[self.j]
        length = np.linalg.norm(u, axis=1)
        d = u / length[:, None]
        dldt = np.einsum("ij,ij->i", v[self.i] - v[self.j], d)
        fs = -(self.k * (length - self.L) + self.kd * dldt)[:, None] * d
        f = self.m[:, None] * self.g
        np.add.at(f, self.i, fs)
        np.add.at(f, self.j, -fs)
        self.v = v + h * self.w[:, None] * f
        self.x = x + h * self.v


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=DefaultsHelpFormatter)
    parser.add_argument("--device", default=None)
    parser.add_argument("--grid", type=int, nargs="+", default=[32, 64])
    parser.add_argument("--steps", type=int, default=50)
    args = parser.parse_args()
    set_warp_verbosity()  # quiet unless $WARPSIM_VERBOSE=1 (Warp 1.19 ignores config.quiet)
    device = wp.get_device(device_arg(args.device))
    h = 1e-4
    print(f"device: {device} ({device.name})")
    print(f"{'grid':>6} {'particles':>9} {'springs':>8} {'numpy ms':>9} {'warpsim ms':>10} {'ratio':>7}"
          f" {'graph ms':>9} {'ratio':>7}")
    for n in args.grid:
        b = grid_system(n)
        ref = NumpyMassSpring(b)
        sim = ws.Simulator(b.finalize(device), integrator="semi_implicit_euler", forces=[ws.Gravity()],
                           check_every=0)
        # agreement first (a few steps from the same state)
        for _ in range(5):
            ref.step(h)
            sim.step(h)
        err = np.abs(sim.state.positions.numpy() - ref.x).max()
        assert err < 1e-4, f"warpsim and NumPy disagree by {err}"
        t_np = time_per_call(lambda: ref.step(h), args.steps)
        t_ws = time_per_call(lambda: sim.step(h), args.steps, device)
        graph_ms, graph_ratio = "-", "-"
        if device.is_cuda:
            t_graph = time_per_graph_launch(lambda: sim.step(h), args.steps, device)
            graph_ms, graph_ratio = f"{t_graph * 1e3:9.3f}", f"{t_np / t_graph:7.1f}"
        print(f"{n:>6} {b.particle_count:>9} {b.spring_count:>8} {t_np * 1e3:9.3f} {t_ws * 1e3:10.3f} "
              f"{t_np / t_ws:7.2f} {graph_ms:>9} {graph_ratio:>7}")


if __name__ == "__main__":
    sys.exit(run_script(main))
