"""Recover a cloth's structural stiffness and damping from a target cache by differentiating the
simulation.

A square cloth pinned at two corners falls and swings under gravity (``ClothSimulator``,
semi-implicit Euler). First the target: the ordinary simulator runs with hidden structural
stiffness and damping and streams the cloth to a USD cache (``UsdCacheWriter``). Then the fit
reads the cache back and starts from a wrong guess: a differentiable ``ClothSimulator`` records
the same motion on a ``wp.Tape``, the loss is the mean squared distance to the cached frames,
and the gradients with respect to every structural spring (``model.spring_stiffness.grad``,
``model.spring_damping.grad``), summed over those springs, drive SciPy's L-BFGS in
log(stiffness), log(damping). Shear and bend springs keep their known values. The script prints
the iterations, the values found and their errors against the hidden ones.

    python examples/fit_cloth.py --resolution 8 --frames 30 --out usd_out/fit_cloth_target.usdc
"""

import argparse

import numpy as np
import warp as wp

try:
    from scipy.optimize import minimize
except ImportError:  # SciPy is no dependency of warpsim itself
    raise SystemExit("fit_cloth.py needs SciPy (L-BFGS-B): pip install scipy") from None

import warpsim as ws
from warpsim.cli_common import DefaultsHelpFormatter, device_arg, run_script
from warpsim.usd.validate import open_stage
from warpsim.usd.writer import UsdCacheWriter
from warpsim.verbosity import set_warp_verbosity


class Example:
    def __init__(self, resolution=8, frames=30, substeps=10, stiffness=60.0, damping=0.05, differentiable=True,
                 device=None):
        builder = ws.ModelBuilder()
        self.cloth = ws.add_cloth_grid(builder, resolution, 0.5, (0.0, 1.0, 0.0), particle_mass=0.002,
                                       pin=["corner_00", "corner_10"], structural=(stiffness, damping),
                                       shear=(20.0, 0.02), bend=(2.0, 0.005))
        self.sim = ws.ClothSimulator(builder.finalize(device), "semi_implicit_euler", [ws.Gravity()],
                                     differentiable=differentiable)
        self.frames, self.substeps, self.frame_dt = frames, substeps, 1.0 / 60.0
        first, count = self.cloth.springs["structural"]
        self.structural = slice(first, first + count)

    def set_structural(self, stiffness, damping):
        """Give every structural spring ``stiffness`` [N/m] and ``damping`` [N s/m]."""
        m = self.sim.model
        for arr, value in ((m.spring_stiffness, stiffness), (m.spring_damping, damping)):
            values = arr.numpy()
            values[self.structural] = value
            arr.assign(values)

    def declare(self, writer):
        writer.add_mesh("cloth", self.cloth.face_vertex_counts, self.cloth.face_vertex_indices, double_sided=True)

    def frame_data(self):
        return {"cloth": {"points": self.sim.state.positions, "velocities": self.sim.state.velocities}}


def write_target(path, resolution, frames, stiffness, damping, device=None):
    """Run the ordinary simulator with the hidden values and stream it to a USD cache."""
    example = Example(resolution, frames, stiffness=stiffness, damping=damping, differentiable=False, device=device)
    with UsdCacheWriter(path, fps=60.0) as writer:
        example.declare(writer)
        writer.write_frame(0, example.frame_data())
        for frame in range(1, frames + 1):
            example.sim.frame(example.frame_dt, example.substeps)
            writer.write_frame(frame, example.frame_data())


def read_target(path, frames):
    """The cloth points of frames 1..frames from a USD cache, (frames, n, 3) [m]."""
    stage = open_stage(path)
    attr = stage.GetPrimAtPath("/World/cloth").GetAttribute("points")
    return np.array([np.array(attr.Get(frame), dtype=np.float32) for frame in range(1, frames + 1)])


class Fit:
    """Loss and gradient in (log stiffness, log damping) of a differentiable Example."""

    def __init__(self, example, target):
        self.example = example
        r = example.sim.rollout
        self.rollout = r
        self.steps = [f * example.substeps for f in range(1, example.frames + 1)]
        r.reserve(self.steps[-1])
        d = example.sim.device
        self.targets = [wp.array(t, dtype=wp.vec3, device=d) for t in target]
        self.weight = 1.0 / (len(target) * target.shape[1])  # mean over frames and particles [m^2]
        self.loss = wp.zeros(1, dtype=float, device=d, requires_grad=True)
        self.evaluations = 0

    def __call__(self, log_params):
        k, kd = np.exp(log_params)
        ex, r = self.example, self.rollout
        ex.set_structural(k, kd)
        r.reset()
        for _ in range(ex.frames):
            ex.sim.frame(ex.frame_dt, ex.substeps)
        loss = r.trajectory_loss(self.targets, self.weight, self.loss, self.steps)
        r.backward(loss)
        m = ex.sim.model
        grad = np.array([k * m.spring_stiffness.grad.numpy()[ex.structural].sum(dtype=np.float64),
                         kd * m.spring_damping.grad.numpy()[ex.structural].sum(dtype=np.float64)])
        self.evaluations += 1
        scale = 1.0e6  # mm^2: keeps L-BFGS's absolute tolerances meaningful
        return float(loss.numpy()[0]) * scale, grad * scale


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=DefaultsHelpFormatter)
    parser.add_argument("--resolution", type=int, default=8, help="cells per side")
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--hidden", type=float, nargs=2, default=(60.0, 0.05),
                        help="structural stiffness [N/m] and damping [N s/m] of the target")
    parser.add_argument("--guess", type=float, nargs=2, default=(25.0, 0.2))
    parser.add_argument("--quick", action="store_true", help="a smaller cloth and fewer frames (tests)")
    parser.add_argument("--device", default=None)
    parser.add_argument("--out", default="usd_out/fit_cloth_target.usdc", help="the target cache")
    parser.add_argument("--verbose", action="store_true", help="show Warp's banner and module-load lines")
    args = parser.parse_args(argv)
    set_warp_verbosity(args.verbose)
    args.device = device_arg(args.device)  # one line naming the devices there are
    if args.quick:
        args.resolution, args.frames = 5, 12
    write_target(args.out, args.resolution, args.frames, *args.hidden, device=args.device)
    target = read_target(args.out, args.frames)
    example = Example(args.resolution, args.frames, device=args.device)
    fit = Fit(example, target)
    result = minimize(fit, np.log(args.guess), jac=True, method="L-BFGS-B",
                      options={"maxiter": 100, "ftol": 1e-15, "gtol": 1e-10})
    k, kd = np.exp(result.x)
    err = np.abs(np.array([k, kd]) / np.array(args.hidden) - 1.0)
    print(f"target: {args.out}, {args.frames} frames of a {args.resolution}^2-cell cloth")
    print(f"L-BFGS: {result.nit} iterations, {fit.evaluations} rollouts + gradients, "
          f"final mean squared distance {result.fun:.3e} mm^2")
    print(f"structural stiffness {k:.4f} N/m (hidden {args.hidden[0]:g}, error {100 * err[0]:.3f} %)")
    print(f"structural damping   {kd:.5f} N s/m (hidden {args.hidden[1]:g}, error {100 * err[1]:.3f} %)")
    return 0 if np.all(err < 0.01) else 1


if __name__ == "__main__":
    raise SystemExit(run_script(main))
