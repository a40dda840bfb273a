"""warpsim: physics-based animation solvers written as NVIDIA Warp kernels.

    import warpsim as ws
    builder = ws.ModelBuilder()
    builder.add_particle((0.0, 0.04, 0.0), mass=1.0)
    sim = ws.Simulator(builder.finalize(), forces=[ws.Gravity()], colliders=[ws.Plane()])
    sim.step(0.04)

The sub-packages are the map: ``core`` (model, builder, forces, integrators, simulator),
``bodies`` (colliders, soft bodies, the teapot, dragging), ``cloth``, ``particle_fluids``,
``grid_fluids``, ``meshing``, ``agents``, ``usd`` (cache writer, prims, validation), ``scenes``
(command-line presets), ``diff`` (differentiable runs: ``Simulator(..., differentiable=True)``);
the Warp kernels live in ``warpsim.kernels``.
"""

from typing import TYPE_CHECKING

from ._version import __version__

if TYPE_CHECKING:  # the same names, seen statically by IDEs, type checkers and autodoc (run time: _HOMES, lazily)
    from .agents import AgentState, BoidParams, Crowd, Flock, FoodSources, Obstacles, Terrain, WalkerParams
    from .bodies import (
        Box, Capsule, Collider, DragSpring, ParticleCollisions, Plane, Planes, Quad, Rectangle, SoftBody,
        Sphere, TriangleMesh, add_soft_body, keyframe_motion, load_mesh, pick_particle, teapot_mesh,
    )
    from .bodies import VBD, SoftContact, VBDContact, torus_mesh
    from .core import BreakReport, SpringFracture, spring_segments
    from .core import StabilityLimit, StabilityWarning
    from .strands import SagFreeReport, StrandForce, StrandRoots, Strands, add_strands, sag_free, strand_stable_dt
    from .cloth import (
        Cloth, ClothImplicitEuler, ClothSemiImplicitEuler, ClothSimulator, add_cloth_grid, add_cloth_mesh,
        cloth_energy,
    )
    from .core import (
        INTEGRATORS, RK2, RK4, ConstantForce, Drag, DynamicSystem, ExplicitEuler, FastMassSpring, Force, ForceField,
        Gravity,
        ImplicitEuler, Integrator, Magnets, Model, ModelBuilder, ParticleSystem, Pendulum, PendulumSystem,
        SemiImplicitEuler, SimulationError, Simulator, Springs, State, Wind, exact_period,
    )
    from .grid_fluids import (
        Advector, FlipLiquid, LevelSet, LevelSetLiquid, MacGrid, PressureSolver, Smoke, Viscosity,
    )
    from .meshing import MarchingCubes, MarchingCubesResult, Metaballs, marching_cubes, topology_changed
    from .particle_fluids import FluidSurface, Nozzle, ParticleFluid, Sink, fluid_block
    from .viewer.server import Viewer
    from .sweeps.rerun import rerun_world


_HOMES = {
    ".agents": ("AgentState", "BoidParams", "Crowd", "Flock", "FoodSources", "Obstacles", "Terrain", "WalkerParams"),
    ".bodies": ("Box", "Capsule", "Collider", "DragSpring", "ParticleCollisions", "Plane", "Planes", "Quad", "Rectangle",
                "SoftBody", "Sphere", "TriangleMesh", "add_soft_body", "keyframe_motion", "load_mesh", "pick_particle",
                "teapot_mesh", "VBD", "SoftContact", "VBDContact", "torus_mesh"),
    ".cloth": ("Cloth", "ClothImplicitEuler", "ClothSemiImplicitEuler", "ClothSimulator", "add_cloth_grid",
               "add_cloth_mesh", "cloth_energy"),
    ".core": ("BreakReport", "SpringFracture", "spring_segments", "StabilityLimit", "StabilityWarning", "INTEGRATORS",
              "RK2", "RK4", "ConstantForce", "Drag", "DynamicSystem", "ExplicitEuler", "FastMassSpring", "Force",
              "ForceField", "Gravity", "ImplicitEuler", "Integrator", "Magnets", "Model", "ModelBuilder",
              "ParticleSystem", "Pendulum", "PendulumSystem", "SemiImplicitEuler", "SimulationError", "Simulator",
              "Springs", "State", "Wind", "exact_period"),
    ".grid_fluids": ("Advector", "FlipLiquid", "LevelSet", "LevelSetLiquid", "MacGrid", "PressureSolver", "Smoke",
                     "Viscosity"),
    ".meshing": ("MarchingCubes", "MarchingCubesResult", "Metaballs", "marching_cubes", "topology_changed"),
    ".particle_fluids": ("FluidSurface", "Nozzle", "ParticleFluid", "Sink", "fluid_block"),
    ".strands": ("SagFreeReport", "StrandForce", "StrandRoots", "Strands", "add_strands", "sag_free", "strand_stable_dt"),
    ".sweeps.rerun": ("rerun_world",),
}
"""Where each public name lives: ``{sub-module: names}``. ``ws.NAME`` imports only its sub-module (a
scene of springs does not import the fluids: ``warpsim run bounce`` and ``warpsim sweep teapot``
start without defining their kernels). Add new public names here, under ``TYPE_CHECKING`` and
to ``__all__``."""

_HOME_OF = {name: module for module, names in _HOMES.items() for name in names}


def _publish(module_name, names):
    """Import the sub-module ``module_name`` (a key of :data:`_HOMES`) and publish ``names`` of it."""
    import importlib

    module = importlib.import_module(module_name, __name__)
    globals().update({name: getattr(module, name) for name in names})


def _load_all():
    """Import every public name (``import warpsim`` alone stays light, so ``warpsim info`` starts
    without Warp; ``ws.Gravity`` imports only ``warpsim.core``, see :data:`_HOMES`)."""
    for module_name, names in _HOMES.items():
        _publish(module_name, names)


__all__ = [
    "__version__", "ModelBuilder", "Model", "State", "Simulator", "SimulationError",
    "Force", "Gravity", "ConstantForce", "Wind", "Magnets", "Drag", "Springs", "ForceField",
    "Collider", "Planes", "Plane", "Box", "Sphere", "Capsule", "Quad", "Rectangle", "TriangleMesh",
    "ParticleCollisions", "keyframe_motion", "DragSpring", "pick_particle", "SoftBody", "add_soft_body", "load_mesh",
    "teapot_mesh", "Cloth", "add_cloth_grid", "add_cloth_mesh", "cloth_energy", "ClothImplicitEuler",
    "ClothSemiImplicitEuler", "ClothSimulator",
    "Integrator", "ExplicitEuler", "SemiImplicitEuler", "ImplicitEuler", "RK2", "RK4", "INTEGRATORS", "FastMassSpring",
    "MarchingCubes", "MarchingCubesResult", "marching_cubes", "topology_changed", "Metaballs",
    "AgentState", "BoidParams", "Crowd", "Flock", "FoodSources", "Obstacles", "Terrain", "WalkerParams",
    "MacGrid", "PressureSolver", "Advector", "LevelSet", "LevelSetLiquid", "Smoke", "FlipLiquid", "Viscosity",
    "ParticleFluid", "Nozzle", "Sink", "fluid_block", "FluidSurface",
    "Pendulum", "exact_period", "DynamicSystem", "ParticleSystem", "PendulumSystem", "Viewer",
    "SpringFracture", "BreakReport", "spring_segments", "SoftContact", "torus_mesh", "VBD", "VBDContact",
    "StabilityLimit", "StabilityWarning",
    "Strands", "add_strands", "StrandForce", "StrandRoots", "strand_stable_dt", "sag_free", "SagFreeReport",
    "rerun_world",
]


def __getattr__(name):
    """Lazy public names: each is imported on first use with the others of its sub-module (:data:`_HOMES`);
    ``ws.Viewer`` (the browser viewer) imports viser only when first used. The first one applies
    warpsim's quiet default to Warp (``warpsim.verbosity``: ``$WARPSIM_VERBOSE=1`` shows its banner)."""
    if name in __all__ and not name.startswith("__"):
        from .verbosity import set_warp_verbosity

        set_warp_verbosity()
    if name == "Viewer":
        from .viewer.server import Viewer

        return Viewer
    if name in _HOME_OF:
        _publish(_HOME_OF[name], (name,))  # (only it: a sub-package may load its heavier names lazily too)
        return globals()[name]
    raise AttributeError(f"module 'warpsim' has no attribute {name!r}")


def __dir__():
    """The public names (``__all__``) with what is already loaded, so ``dir(ws)`` and tab completion
    show ``ws.Simulator`` and the rest before their first use (they load lazily, see ``__getattr__``)."""
    return sorted(set(__all__) | {k for k in globals() if not k.startswith("_") and k != "TYPE_CHECKING"})
