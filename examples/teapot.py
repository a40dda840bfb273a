"""The lecture's jiggly teapot: a mass-spring Utah teapot dropped into a box, grabbed and dragged.

The teapot is generated from Newell's Bezier patches (``warpsim.bodies.teapot``), turned into point
masses joined by edge, bending and interior-lattice springs (``warpsim.bodies.softbody``), dropped into
a box of walls (restitution and friction), and at t = 0.6 s its spout is picked with a ray
(the particle closest to the ray, as a mouse click would) and dragged up and across by a
drag spring until it is let go at t = 1.6 s. Frames stream to a USD cache: the surface as a
Mesh with fixed topology, the springs as curves, the drag as a red line.

Too little mass (or too large a step) makes it explode: try ``--mass 0.02``; the simulator
then stops and names the frame, the particle and the remedy, e.g. ``--integrator implicit_euler``.

    python examples/teapot.py --frames 180 --out usd_out/teapot_example.usda
    python examples/teapot.py --resolution high --stiffness 80 --frames 120
"""

import argparse
import math
import sys

import numpy as np

import warpsim as ws
from warpsim.bodies.drag import DragSpring
from warpsim.bodies.softbody import add_soft_body
from warpsim.bodies.teapot import teapot_mesh
from warpsim.cli_common import DefaultsHelpFormatter, device_arg, run_script
from warpsim.usd.writer import UsdCacheWriter
from warpsim.verbosity import set_warp_verbosity


class Example:
    def __init__(self, resolution="low", mass=1.0, stiffness=40.0, damping=0.05, dt=1.0 / 600,
                 integrator="semi_implicit_euler", device=None):
        mesh = teapot_mesh(resolution, scale=0.1)  # 0.65 m long, 0.315 m tall
        builder = ws.ModelBuilder()
        tilt = math.radians(20.0)
        self.body = add_soft_body(
            builder, mesh.points, mesh.faces, position=(0.0, 0.6, 0.0),
            rotation=(0.0, 0.0, math.sin(tilt / 2), math.cos(tilt / 2)), velocity=(1.0, 0.0, 0.6),
            total_mass=mass, mass_distribution="uniform", stiffness=stiffness, damping=damping, lattice_cells=6)
        self.model = builder.finalize(device)
        self.box = ws.Box((-0.7, 0.0, -0.7), (0.7, 1.4, 0.7), restitution=0.5, friction=0.3)
        self.drag = DragSpring(stiffness=6.0, damping=0.3)
        self.sim = ws.Simulator(self.model, integrator=integrator, forces=[ws.Gravity(), self.drag],
                                colliders=[self.box], max_speed=100.0)
        self.dt = dt
        self.grabbed = -1

    def pick_and_drag(self):
        """Click on the spout: a ray from a camera at the front-right, toward the spout tip."""
        eye = np.array([2.0, 1.0, 2.0])
        x = self.sim.state.positions.numpy()
        spout = x[int(np.argmax(x[: self.body.surface_count, 0]))]
        self.grabbed = self.drag.grab_ray(self.sim.state.positions, eye, spout - eye, max_distance=0.05)
        t0 = self.sim.time
        path = [(t0, x[self.grabbed]), (t0 + 0.5, (0.3, 0.9, 0.0)), (t0 + 1.0, (-0.3, 0.7, 0.3))]
        self.drag.set_path(path, release=t0 + 1.0)

    def step_frame(self, frame_dt=1.0 / 60):
        substeps = max(1, round(frame_dt / self.dt))
        for _ in range(substeps):
            self.sim.step(frame_dt / substeps)

    def declare(self, writer):
        faces = self.body.faces - self.body.particle_start
        writer.add_mesh("teapot", np.full(len(faces), 3), faces.reshape(-1), color=(0.85, 0.85, 0.9))
        writer.add_curves("springs", self.model.spring_indices.numpy(), width=0.001, color=(0.3, 0.3, 0.3))
        writer.add_curves("drag", curve_vertex_counts=[2], width=0.004, color=(0.9, 0.2, 0.1))
        writer.add_box("walls", self.box.lower, self.box.upper)

    def frame_data(self):
        x = self.sim.state.positions.numpy()
        n = self.body.surface_count
        p = max(self.grabbed, 0)
        end = self.drag.target_at(self.sim.time) if self.drag.active_at(self.sim.time) else x[p]
        return {"teapot": {"points": x[:n], "velocities": self.sim.state.velocities.numpy()[:n]},
                "springs": {"points": x}, "drag": {"points": np.array([x[p], end])}}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=DefaultsHelpFormatter)
    parser.add_argument("--frames", type=int, default=180)
    parser.add_argument("--resolution", default="low", help="low, high or segments per patch edge")
    parser.add_argument("--mass", type=float, default=1.0, help="total mass [kg]")
    parser.add_argument("--stiffness", type=float, default=40.0, help="spring stiffness [N/m]")
    parser.add_argument("--damping", type=float, default=0.05, help="spring damping [N s/m]")
    parser.add_argument("--dt", type=float, default=1.0 / 600, help="time step [s]")
    parser.add_argument("--integrator", default="semi_implicit_euler", choices=sorted(ws.INTEGRATORS))
    parser.add_argument("--out", default="usd_out/teapot_example.usda")
    parser.add_argument("--device", default=None)
    parser.add_argument("--verbose", action="store_true", help="show Warp's banner and module-load lines")
    args = parser.parse_args(argv)
    set_warp_verbosity(args.verbose)
    args.device = device_arg(args.device)  # one line naming the devices there are
    example = Example(args.resolution, args.mass, args.stiffness, args.damping, args.dt, args.integrator,
                      args.device)
    print(f"teapot: {example.model.particle_count} particles, {example.model.spring_count} springs")
    failed = None
    with UsdCacheWriter(args.out, fps=60) as writer:
        example.declare(writer)
        writer.write_frame(0, example.frame_data())
        for frame in range(1, args.frames + 1):
            try:
                example.step_frame()
            except ws.SimulationError as err:
                failed = f"frame {frame}: {err}"
                break
            if example.grabbed < 0 and example.sim.time >= 0.6:
                example.pick_and_drag()
                print(f"frame {frame}: picked particle {example.grabbed} (the spout) with a ray and dragged it")
            writer.write_frame(frame, example.frame_data())
            if frame % 30 == 0:
                x = example.sim.state.positions.numpy()
                print(f"frame {frame:4d}  t = {example.sim.time:5.2f} s  lowest y = {x[:, 1].min():.3f} m  "
                      f"centre = ({x[:, 0].mean():+.3f}, {x[:, 1].mean():.3f}, {x[:, 2].mean():+.3f}) m")
    if failed:
        print(f"teapot: the simulation blew up at {failed}\nkept frames 0..{frame - 1} in {args.out}", file=sys.stderr)
        return 1
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(run_script(main))
