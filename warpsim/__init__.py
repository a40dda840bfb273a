"""warpsim: physics-based animation solvers written as NVIDIA Warp kernels.

    import warpsim as ws
    builder = ws.ModelBuilder()
    builder.add_particle((0.0, 0.04, 0.0), mass=1.0)
    sim = ws.Simulator(builder.finalize(), forces=[ws.Gravity()], colliders=[ws.Plane()])
    sim.step(0.04)
"""

from ._version import __version__
from .agents import AgentState, BoidParams, Crowd, Flock, FoodSources, Obstacles, Terrain, WalkerParams
from .builder import ModelBuilder
from .cloth import Cloth, add_cloth_grid, add_cloth_mesh
from .cloth_solver import ClothImplicitEuler, ClothSemiImplicitEuler, ClothSimulator, cloth_energy
from .colliders import (
    Box, Capsule, Collider, ParticleCollisions, Plane, Planes, Quad, Rectangle, Sphere, TriangleMesh, keyframe_motion,
)
from .drag import DragSpring, pick_particle
from .softbody import SoftBody, add_soft_body, load_mesh
from .teapot import teapot_mesh
from .errors import SimulationError
from .forces import ConstantForce, Drag, Force, ForceField, Gravity, Magnets, Springs, Wind
from .meshing import MarchingCubes, MarchingCubesResult, marching_cubes, topology_changed
from .metaballs import Metaballs
from .integrators import INTEGRATORS, RK2, RK4, ExplicitEuler, ImplicitEuler, Integrator, SemiImplicitEuler
from .model import Model, State
from .pendulum import Pendulum, exact_period
from .simulator import Simulator
from .flip import FlipLiquid
from .fluid_surface import FluidSurface
from .grid_advection import Advector
from .grid_pressure import PressureSolver
from .levelset import LevelSet
from .levelset_liquid import LevelSetLiquid
from .mac_grid import MacGrid
from .smoke import Smoke
from .viscosity import Viscosity
from .sph import Nozzle, ParticleFluid, Sink, fluid_block
from .system import DynamicSystem, ParticleSystem, PendulumSystem

__all__ = [
    "__version__", "ModelBuilder", "Model", "State", "Simulator", "SimulationError",
    "Force", "Gravity", "ConstantForce", "Wind", "Magnets", "Drag", "Springs", "ForceField",
    "Collider", "Planes", "Plane", "Box", "Sphere", "Capsule", "Quad", "Rectangle", "TriangleMesh",
    "ParticleCollisions", "keyframe_motion", "DragSpring", "pick_particle", "SoftBody", "add_soft_body", "load_mesh",
    "teapot_mesh", "Cloth", "add_cloth_grid", "add_cloth_mesh", "cloth_energy", "ClothImplicitEuler",
    "ClothSemiImplicitEuler", "ClothSimulator",
    "Integrator", "ExplicitEuler", "SemiImplicitEuler", "ImplicitEuler", "RK2", "RK4", "INTEGRATORS",
    "MarchingCubes", "MarchingCubesResult", "marching_cubes", "topology_changed", "Metaballs",
    "AgentState", "BoidParams", "Crowd", "Flock", "FoodSources", "Obstacles", "Terrain", "WalkerParams",
    "MacGrid", "PressureSolver", "Advector", "LevelSet", "LevelSetLiquid", "Smoke", "FlipLiquid", "Viscosity",
    "ParticleFluid", "Nozzle", "Sink", "fluid_block", "FluidSurface",
    "Pendulum", "exact_period", "DynamicSystem", "ParticleSystem", "PendulumSystem",
]
