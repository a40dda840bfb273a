"""The public API as IDEs and type checkers see it: every ``ws.*`` name that the lazy loader
publishes (``warpsim._HOMES``) is also imported under ``if TYPE_CHECKING:`` (so static tools see the
same names) from the same sub-module, ``__all__`` lists exactly those names, each resolves at run
time to an object with a docstring, and a name imports only its own sub-module."""

import ast
import pathlib

import warpsim

INIT = pathlib.Path(warpsim.__file__)


def _imported_names(nodes):
    names = set()
    for node in nodes:
        for sub in ast.walk(node):
            if isinstance(sub, ast.ImportFrom):
                names.update(alias.asname or alias.name for alias in sub.names)
    return names


def _sections():
    tree = ast.parse(INIT.read_text())
    static = None
    for node in tree.body:
        if isinstance(node, ast.If) and getattr(node.test, "id", None) == "TYPE_CHECKING":
            static = _imported_names(node.body)
    lazy = {name for names in warpsim._HOMES.values() for name in names}
    assert static is not None, "warpsim/__init__.py lost its TYPE_CHECKING block"
    return static, lazy


def test_static_names_mirror_the_lazy_loader_and_all():
    static, lazy = _sections()
    # Viewer loads through __getattr__ alone (viser stays unimported until it is used)
    assert static - {"Viewer"} == lazy, f"TYPE_CHECKING vs _HOMES: {sorted(static ^ (lazy | {'Viewer'}))}"
    public = set(warpsim.__all__) - {"__version__"}
    assert public == static, f"__all__ vs TYPE_CHECKING imports differ: {sorted(public ^ static)}"


def test_each_name_is_imported_from_its_home_in_both_sections():
    tree = ast.parse(INIT.read_text())
    block = next(n for n in tree.body if isinstance(n, ast.If) and getattr(n.test, "id", None) == "TYPE_CHECKING")
    static_home = {alias.asname or alias.name: "." * node.level + (node.module or "")
                   for node in ast.walk(block) if isinstance(node, ast.ImportFrom) for alias in node.names}
    wrong = {name: (static_home[name], warpsim._HOME_OF[name]) for name in warpsim._HOME_OF
             if static_home.get(name) != warpsim._HOME_OF[name]}
    assert not wrong, f"TYPE_CHECKING imports these from another module than _HOMES: {wrong}"


def test_a_name_imports_only_its_own_sub_package():
    """``ws.Gravity`` (what a scene of springs uses) defines none of the fluids' or crowds' kernels."""
    import subprocess
    import sys

    code = ("import sys, warpsim as ws; ws.Gravity; ws.Plane; ws.INTEGRATORS; "
            "print(sorted(m for m in ('warpsim.grid_fluids', 'warpsim.particle_fluids', 'warpsim.agents', "
            "'warpsim.meshing', 'warpsim.cloth', 'warpsim.strands') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]", f"ws.Gravity, ws.Plane and ws.INTEGRATORS also imported {out.strip()}"
    code = "import sys, warpsim as ws; ws.FlipLiquid; print('warpsim.grid_fluids' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip() == "True"


def test_every_public_name_resolves_with_a_docstring():
    static, _ = _sections()
    missing = []
    for name in sorted(static - {"Viewer"}):
        obj = getattr(warpsim, name)
        if isinstance(obj, dict):  # INTEGRATORS: name -> class table
            continue
        if not (getattr(obj, "__doc__", None) or "").strip():
            missing.append(name)
    assert not missing, f"public names without a docstring: {missing}"


def test_py_typed_ships_with_the_package():
    assert (INIT.parent / "py.typed").is_file()
    text = (INIT.parents[1] / "pyproject.toml").read_text()
    assert 'warpsim = ["py.typed"]' in text


# public functions still without a return annotation (files other branches own this turn);
# the set may only shrink: a new public function without one fails below
RETURN_PENDING = {
    "ClothImplicitEuler.assemble", "ClothImplicitEuler.step", "ClothSemiImplicitEuler.step", "ClothSimulator.run",
    "ExplicitEuler.step", "SemiImplicitEuler.step", "SemiImplicitEuler.fused_step", "ImplicitEuler.assemble",
    "ImplicitEuler.step", "RK2.step", "RK4.step", "Simulator.run",
    "BoidParams.validate", "WalkerParams.validate", "Obstacles.bind", "Terrain.bind", "Terrain.bounds",
    "keyframe_motion", "FlipLiquid.add_box", "FlipLiquid.add_sdf", "FlipLiquid.add_cells", "FlipLiquid.measure_density",
    "FlipLiquid.surface", "MacGrid.add_collider", "PressureSolver.precondition", "PressureSolver.apply",
    "PressureSolver.project", "Advector.advect", "Viscosity.apply", "Metaballs.mesh", "FluidSurface.mesh",
    "Pendulum.stability", "StrandForce.bind", "StrandForce.eval", "StrandRoots.apply", "StrandRoots.bind",
    "Strands.bind", "Strands.strand_of",
}


def test_public_functions_annotate_their_return():
    import inspect

    missing = set()
    for name in warpsim.__all__:
        if name in ("__version__", "Viewer", "INTEGRATORS"):
            continue
        obj = getattr(warpsim, name)
        if inspect.isclass(obj):
            funcs = [(f"{name}.{k}", v) for k, v in vars(obj).items()
                     if not k.startswith("_") and inspect.isfunction(v)]
        else:
            funcs = [(name, obj)] if inspect.isfunction(obj) else []
        missing.update(q for q, f in funcs if inspect.signature(f).return_annotation is inspect.Signature.empty)
    new = missing - RETURN_PENDING
    assert not new, f"public functions without a return annotation: {sorted(new)}"


def test_the_built_in_scene_index_names_the_module_that_registers_each_scene():
    """``scenes.BUILT_IN`` (what ``get_scene`` imports alone) agrees with the registry after every module
    is imported, and a scene looked up by name in a fresh process imports no other scene's module."""
    import subprocess
    import sys

    from warpsim import scenes

    shipped = {name: cls.__module__ for name, cls in scenes.scenes().items() if cls.__module__.startswith("warpsim.")}
    assert shipped == {name: f"warpsim.scenes.{module}" for name, module in scenes.BUILT_IN.items()}
    code = ("import sys; from warpsim.scenes import get_scene; c = get_scene('teapot'); "
            "print(c.__module__, sorted(m for m in sys.modules if m.startswith('warpsim.scenes.') and m != c.__module__"
            " and m != 'warpsim.scenes.live' and m != 'warpsim.scenes.timing'), "
            "'warpsim.grid_fluids' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out == ["warpsim.scenes.teapot", "[]", "False"], out


def test_a_built_in_scene_name_cannot_be_taken():
    import pytest

    from warpsim.scenes import SimulatorScene, register_scene

    with pytest.raises(ValueError, match="'bounce' is taken by a built-in scene .*basic.py"):
        @register_scene("bounce", "not the ball")
        class NotTheBall(SimulatorScene):
            pass


def test_lazy_names_stay_the_objects_after_their_modules_are_imported():
    """A name loaded on first use is the function or class even where its sub-module (same name, or
    imported directly first) was imported before (``hair`` once got the module ``sag_free``)."""
    import subprocess
    import sys

    code = ("import warpsim.strands.sag_free, warpsim.bodies.vbd, warpsim.strands.builder; "
            "from warpsim.strands import sag_free, Strands; from warpsim.bodies import VBD; "
            "import warpsim as ws; "
            "print(callable(sag_free), isinstance(Strands, type), isinstance(VBD, type), callable(ws.sag_free))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out == ["True"] * 4, out
