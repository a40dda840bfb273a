"""Particle collisions: the lecture's 1D restitution rule, then a box of colliding balls.

Part 1 collides two balls head on (masses 1 and 3 kg, velocities +2 and -1 m/s) with
coefficients of restitution c_R = 0, 0.5 and 1 and prints the velocities after the impact next
to the analytic two-body result: momentum m_a u_a + m_b u_b is conserved and
c_R = -(v_b - v_a) / (u_b - u_a).

Part 2 throws a few hundred balls into a box of walls with gravity; ``ws.ParticleCollisions``
(a ``wp.HashGrid`` neighbour search) resolves every touching pair with the same rule, a solid
sphere and a capsule sit on the floor as obstacles, and the frames stream to a USD cache.
The total kinetic + potential energy printed per second never increases for c_R < 1.

    python examples/collisions.py --balls 400 --frames 240 --out usd_out/collisions.usda
"""

import argparse
import sys

import numpy as np

import warpsim as ws
from warpsim.bodies.colliders import Capsule, ParticleCollisions, Sphere
from warpsim.cli_common import DefaultsHelpFormatter, device_arg, run_script
from warpsim.usd.writer import UsdCacheWriter
from warpsim.verbosity import set_warp_verbosity


def head_on(c_r, ma=1.0, mb=3.0, ua=2.0, ub=-1.0, device=None):
    """Velocities of two touching balls after one collision step, and the analytic ones."""
    b = ws.ModelBuilder()
    b.add_particle((0.0, 0.0, 0.0), vel=(ua, 0.0, 0.0), mass=ma, radius=0.05)
    b.add_particle((0.0999, 0.0, 0.0), vel=(ub, 0.0, 0.0), mass=mb, radius=0.05)
    sim = ws.Simulator(b.finalize(device), forces=[], colliders=[ParticleCollisions(restitution=c_r)])
    sim.step(1.0e-6)
    v = sim.state.velocities.numpy()[:, 0]
    p = ma * ua + mb * ub
    exact = ((p + mb * c_r * (ub - ua)) / (ma + mb), (p + ma * c_r * (ua - ub)) / (ma + mb))
    return v, exact


class BallBox:
    def __init__(self, balls=400, radius=0.03, restitution=0.6, friction=0.1, seed=0, device=None):
        rng = np.random.default_rng(seed)
        b = ws.ModelBuilder()
        side = int(np.ceil(balls ** (1 / 3)))
        grid = np.stack(np.meshgrid(*[np.arange(side)] * 3, indexing="ij"), -1).reshape(-1, 3)[:balls]
        pos = (grid - 0.5 * (side - 1)) * 2.2 * radius + np.array([0.0, 0.9, 0.0])
        b.add_particles(pos, rng.normal(0.0, 1.0, (balls, 3)), masses=rng.uniform(0.5, 2.0, balls), radii=radius)
        self.model = b.finalize(device)
        self.box = ws.Box((-0.5, 0.0, -0.5), (0.5, 1.5, 0.5), restitution=restitution, friction=friction)
        self.sphere = Sphere((0.2, 0.0, 0.1), 0.2, restitution=restitution, friction=friction)
        self.capsule = Capsule((-0.4, 0.08, -0.3), (0.0, 0.08, 0.35), 0.08, restitution=restitution, friction=friction)
        self.sim = ws.Simulator(self.model, forces=[ws.Gravity()],
                                colliders=[self.box, self.sphere, self.capsule,
                                           ParticleCollisions(restitution=restitution, friction=friction)])
        self.mass = self.model.particle_mass.numpy()

    def energy(self):
        x = self.sim.state.positions.numpy()
        v = self.sim.state.velocities.numpy()
        return float(0.5 * (self.mass[:, None] * v**2).sum() + (self.mass * 9.81 * x[:, 1]).sum())


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=DefaultsHelpFormatter)
    parser.add_argument("--balls", type=int, default=400)
    parser.add_argument("--frames", type=int, default=240)
    parser.add_argument("--substeps", type=int, default=8)
    parser.add_argument("--restitution", type=float, default=0.6)
    parser.add_argument("--out", default="usd_out/collisions.usda")
    parser.add_argument("--device", default=None)
    parser.add_argument("--verbose", action="store_true", help="show Warp's banner and module-load lines")
    args = parser.parse_args(argv)
    set_warp_verbosity(args.verbose)
    args.device = device_arg(args.device)  # one line naming the devices there are

    print("head-on collision, m_a = 1 kg at +2 m/s, m_b = 3 kg at -1 m/s")
    print(f"{'c_R':>5} {'v_a':>9} {'exact':>9} {'v_b':>9} {'exact':>9}")
    for c_r in (0.0, 0.5, 1.0):
        v, exact = head_on(c_r, device=args.device)
        print(f"{c_r:5.2f} {v[0]:9.5f} {exact[0]:9.5f} {v[1]:9.5f} {exact[1]:9.5f}")

    scene = BallBox(args.balls, restitution=args.restitution, device=args.device)
    with UsdCacheWriter(args.out, fps=60) as writer:
        writer.add_points("balls", radius=0.03, color=(0.9, 0.5, 0.1), from_state=True)
        writer.add_box("walls", scene.box.lower, scene.box.upper)
        writer.add_sphere("sphere", tuple(scene.sphere.center), scene.sphere.radius)
        writer.write(0, scene.sim.state)
        print(f"\n{args.balls} balls in a box: energy [J] per second")
        for frame in range(1, args.frames + 1):
            for _ in range(args.substeps):
                scene.sim.step(1.0 / (60 * args.substeps))
            writer.write(frame, scene.sim.state)
            if frame % 60 == 0 or frame == args.frames:
                print(f"  t = {scene.sim.time:5.2f} s  E = {scene.energy():9.4f}")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    sys.exit(run_script(main))
