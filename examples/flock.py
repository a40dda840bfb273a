"""Flocking: two species of birds that follow each other, keep their distance, look for low air
resistance, rest every so often and go for food.

Builds a ``ws.Flock`` by hand: small birds (species 0) and geese (species 1, which
seek the upwash behind and beside each other and save 30 % of their flight energy there) fly
over a hilly height field that wraps around in x and z, avoid a tree crown (a sphere), eat at
two food sources and land to rest when their energy runs low. Every ``--print-every`` frames it
prints the polarization of each species (1 = all fly the same way), how many are resting, the
geese's mean upwash benefit and the food left; with ``--out`` it streams a USD cache (agents as
a PointInstancer oriented along their velocity, coloured by state).

    python examples/flock.py --frames 240 --out usd_out/flock.usda
"""

import argparse
import sys

import numpy as np

from warpsim.agents import AgentState, BoidParams, Flock, FoodSources, Obstacles, Terrain, polarization
from warpsim.cli_common import DefaultsHelpFormatter, device_arg, run_script
from warpsim.verbosity import set_warp_verbosity

SIZE = 40.0  # side of the periodic world [m]


class Example:
    def __init__(self, birds=200, geese=30, seed=0, device=None):
        rng = np.random.default_rng(seed)
        half = 0.5 * SIZE
        self.terrain = Terrain.from_function(lambda x, z: 1.0 + np.sin(x / 6.0) * np.cos(z / 8.0),
                                             (-half, -half), (half, half), spacing=1.0)
        self.obstacles = Obstacles(spheres=[((8.0, 7.0, -6.0), 2.5)])  # a tree crown
        food_xz = np.array([[-10.0, 5.0], [12.0, 10.0]])
        food_y = self.terrain.height(food_xz, device) + 0.5
        self.food = FoodSources(np.c_[food_xz[:, 0], food_y, food_xz[:, 1]], amounts=100)

        small = BoidParams(max_speed=9.0, min_speed=5.0, perception_radius=4.0, separation_radius=1.0,
                           separation_radius_other=2.0, min_height=0.5, drain_rate=1 / 30, land_threshold=0.15,
                           rest_time=6.0, food_sense_radius=10.0, food_eat_radius=1.0, food_energy=0.05)
        goose = BoidParams(max_speed=8.0, min_speed=5.0, max_force=6.0, perception_radius=6.0, separation_radius=0.8,
                           separation_radius_other=2.0, fov_deg=220.0, cohesion_weight=0.3, min_height=1.0,
                           draft_weight=1.5, draft_saving=0.3, draft_back=1.2, draft_side=1.0, draft_width=0.5,
                           drain_rate=1 / 45, land_threshold=0.15, rest_time=8.0, body_radius=0.3)
        n = birds + geese
        self.species = np.r_[np.zeros(birds, int), np.ones(geese, int)]
        x = np.c_[rng.uniform(-half, half, n), rng.uniform(5.0, 15.0, n), rng.uniform(-half, half, n)]
        x[birds:] = [-10.0, 10.0, 0.0] + rng.normal(0.0, 2.0, (geese, 3))
        v = rng.normal(0.0, 1.0, (n, 3)) * [1.0, 0.1, 1.0]
        v[birds:] = [1.0, 0.0, 0.2]
        v = 6.0 * v / np.linalg.norm(v, axis=1, keepdims=True)
        self.flock = Flock(x, v, self.species, [small, goose], bounds=((-half, -5.0, -half), (half, 20.0, half)),
                           wrap=(True, False, True), margin=3.0, terrain=self.terrain, obstacles=self.obstacles,
                           food=self.food, energy=rng.uniform(0.3, 1.0, n), device=device)

    def step(self, dt):
        self.flock.step(dt)

    def report(self):
        f = self.flock
        v, state = f.velocities.numpy(), f.state.numpy()
        flying = state == AgentState.FLYING
        phis = [polarization(v[flying & (self.species == s)]) for s in (0, 1)]
        geese = self.species == 1
        return phis, int((state == AgentState.RESTING).sum()), float(f.benefit.numpy()[geese].mean()), \
            f.food_amounts.numpy().tolist()

    def declare(self, writer):
        writer.add_instancer("birds", [("cone", {"radius": 0.15, "height": 0.5, "axis": "Z"}),
                                       ("cone", {"radius": 0.35, "height": 1.2, "axis": "Z"})],
                             count_changes=False, primvars={"state": "int[]"})
        pts, tri = self.terrain.mesh()
        writer.add_static_mesh("terrain", pts, np.full(len(tri), 3), tri.reshape(-1), color=(0.45, 0.4, 0.3))
        (center, radius), = self.obstacles.spheres
        writer.add_sphere("tree", tuple(center), radius, color=(0.2, 0.5, 0.2))

    def write(self, writer, frame):
        f = self.flock
        writer.write_frame(frame, {"birds": {
            "positions": f.positions, "orientations": f.orientations(), "velocities": f.velocities,
            "protoIndices": f.species, "state": f.state}})


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=DefaultsHelpFormatter)
    parser.add_argument("--frames", type=int, default=240)
    parser.add_argument("--fps", type=float, default=24.0)
    parser.add_argument("--substeps", type=int, default=2)
    parser.add_argument("--birds", type=int, default=200)
    parser.add_argument("--geese", type=int, default=30)
    parser.add_argument("--print-every", type=int, default=48)
    parser.add_argument("--device", default=None)
    parser.add_argument("--out", default=None, help="USD cache to write, e.g. usd_out/flock.usda")
    parser.add_argument("--verbose", action="store_true", help="show Warp's banner and module-load lines")
    args = parser.parse_args(argv)
    set_warp_verbosity(args.verbose)
    args.device = device_arg(args.device)  # one line naming the devices there are
    example = Example(args.birds, args.geese, device=args.device)
    writer = None
    if args.out:
        from warpsim.usd.writer import UsdCacheWriter

        writer = UsdCacheWriter(args.out, fps=args.fps)
        example.declare(writer)
        example.write(writer, 0)
    print(f"{'frame':>5} {'phi birds':>9} {'phi geese':>9} {'resting':>7} {'upwash':>6}  food left")
    dt = 1.0 / (args.fps * args.substeps)
    for frame in range(1, args.frames + 1):
        for _ in range(args.substeps):
            example.step(dt)
        if writer is not None:
            example.write(writer, frame)
        if frame % args.print_every == 0 or frame == args.frames:
            (p0, p1), resting, benefit, food = example.report()
            print(f"{frame:>5} {p0:>9.3f} {p1:>9.3f} {resting:>7d} {benefit:>6.2f}  {food}")
    if writer is not None:
        print("wrote", writer.close())


if __name__ == "__main__":
    sys.exit(run_script(main))
