"""The import rules of ``warpsim/``: every ``import`` / ``from ... import`` (module level and
inside functions alike) is an edge, and

- the graph has no strongly connected component of more than one module (a new circle fails here
  with its members);
- every module imports only its own floor or lower ones (``FLOORS``: the folders of ``warpsim/``
  from the bottom up; command modules are on the top floor); an upward import fails here naming
  both modules, unless ``UPWARD`` lists it with its reason;
- no module imports another module's private (``_name``) names, outside ``PRIVATE_PENDING``.

CONTRIBUTING.md explains the floors."""

import ast
import functools
import pathlib

import warpsim

PACKAGE = pathlib.Path(warpsim.__file__).parent


FLOORS = (
    ("_version", "_lazy", "verbosity", "meshing", "process_pool"),  # 0: no warpsim imports
    ("core",),  # 1: model, builder, forces, integrators, simulator, the solver protocol, shared helpers
    ("bodies", "cloth", "agents", "grid_fluids", "particle_fluids", "usd"),  # 2: domains on core
    ("strands", "diff"),  # 3: domains on domains (hair on the colliders; rollouts of every solver)
    ("__init__",),  # 4: the package face, ``import warpsim as ws``
    ("scenes",),  # 5: presets, one decorator each
    ("cli_common", "extras"),  # 6: shared command-line helpers (option parsing, outputs, devices, extras)
    ("worlds", "render", "viewer"),  # 7: many worlds stepped together, outputs, the live viewer
    ("browse",),  # 8: occupancy records, spacetime queries, the gallery
    ("sweeps", "distributed"),  # 9: sweeps, their tables and manifests, on Ray and several GPUs
    ("cli", "commands", "__main__"),  # 10: the dispatcher and every command (any ``*command`` module)
)
"""The floors of ``warpsim/``, bottom up: a module may import its own floor and the floors below."""

UPWARD: dict = {}
"""Known upward imports and why (none left since Architecture III moved the Rollout into core, the icosphere
into bodies.shapes and the gallery's runs into child processes): this list only shrinks."""

FACE = "warpsim"
"""The package face re-exports every floor (the upper ones lazily, in ``__getattr__``)."""

PRIVATE_PENDING: set = set()
"""(module, name) private imports still allowed (none left since the worlds/ split was reworked):
this list only shrinks."""


def _modules(package=PACKAGE):
    mods = {}
    for path in package.rglob("*.py"):
        rel = path.relative_to(package.parent)
        if rel.parts[1:2] == ("kernels",):  # Warp code only (a symlink in a checkout)
            continue
        parts = list(rel.with_suffix("").parts)
        is_package = parts[-1] == "__init__"
        mods[".".join(parts[:-1] if is_package else parts)] = (path, is_package)
    return mods


def _imports(mod, path, is_package):
    """(node, base module, names) of each ``from ... import`` and (node, name, []) of each ``import``."""
    here = mod.split(".") if is_package else mod.split(".")[:-1]
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            for a in node.names:
                yield node, a.name, []
        elif isinstance(node, ast.ImportFrom):
            base = ".".join(here[: len(here) - node.level + 1] + ([node.module] if node.module else [])) \
                if node.level else (node.module or "")
            yield node, base, [a.name for a in node.names]


def build_graph(package=PACKAGE):
    """{module: set of warpsim modules it imports}; ``from pkg import name`` points at the
    sub-module ``pkg.name`` when one exists, else at ``pkg``."""
    mods = _modules(package)
    graph = {m: set() for m in mods}
    for mod, (path, is_package) in mods.items():
        for _, base, names in _imports(mod, path, is_package):
            targets = [f"{base}.{n}" if f"{base}.{n}" in mods else base for n in names] or [base]
            graph[mod].update(t for t in targets if t in mods and t != mod)
    return graph


@functools.lru_cache(maxsize=1)
def import_graph():
    return build_graph()


def room(module: str) -> str:
    """The folder (or top-level module) of ``warpsim/`` that holds ``module``."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


def floor(module: str) -> int:
    """``module``'s floor (``FLOORS``); KeyError for a folder that has none yet."""
    last = module.split(".")[-1]
    if last == "command" or last.endswith("_command"):
        return len(FLOORS) - 1
    return next(i for i, rooms in enumerate(FLOORS) if room(module) in rooms)


def upward_imports(graph, allowed=UPWARD):
    """[(importer, imported, its floor, their floor)] for every import of a higher floor."""
    return sorted((a, b, floor(a), floor(b)) for a, targets in graph.items() if a != FACE
                  for b in targets if floor(b) > floor(a) and (a, b) not in allowed)


def _private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def private_imports(package=PACKAGE):
    """[(module, line, imported module, name)] of every ``from <warpsim module> import _name`` and
    every ``module._name`` read through a warpsim module imported under a name (``from . import
    stability as stab``: ``stab._reason``) that names another module's private name (dunder names
    aside)."""
    mods, found = _modules(package), []
    for mod, (path, is_package) in mods.items():
        aliases = {}
        for node, base, names in _imports(mod, path, is_package):
            if base.split(".")[0] != package.name or base == mod:
                continue
            found += [(mod, node.lineno, base, n) for n in names if _private(n)]
            for a in node.names:
                full = f"{base}.{a.name}" if isinstance(node, ast.ImportFrom) else a.name
                if full in mods and full != mod and (a.asname or isinstance(node, ast.ImportFrom)):
                    aliases[a.asname or a.name] = full
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and \
                    node.value.id in aliases and _private(node.attr):
                found.append((mod, node.lineno, aliases[node.value.id], node.attr))
    return sorted(found)


def circles(graph):
    """Strongly connected components with more than one module (Tarjan, iterative)."""
    index, low, stack, on_stack, found = {}, {}, [], set(), []
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return found


def test_the_finder_sees_a_circle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert circles(graph) == [["a", "b", "c"]]
    assert circles({"a": {"b"}, "b": set()}) == []


def test_the_graph_has_the_known_edges():
    graph = import_graph()
    assert "warpsim.core.model" in graph["warpsim.core.simulator"]
    assert "warpsim.bodies.mesh_io" in graph["warpsim.bodies.colliders"]
    assert "warpsim.core.rollout" in graph["warpsim.core.simulator"]  # imported inside Simulator.__init__: counts too
    assert "warpsim.cli_common" in graph["warpsim.render.command"]


def test_no_import_circles_among_warpsim_modules():
    found = circles({k: set(v) for k, v in import_graph().items()})
    assert not found, "import circles (move the shared helper one floor down): " + "; ".join(
        " <-> ".join(c) for c in found)


def test_moved_names_still_agree():
    from warpsim import cli, cli_common
    from warpsim.bodies import softbody
    from warpsim.cloth.solver import ClothSemiImplicitEuler
    from warpsim.core.rollout import CLOTH_SEMI_IMPLICIT

    assert CLOTH_SEMI_IMPLICIT == ClothSemiImplicitEuler.name
    assert cli.UsageError is cli_common.UsageError
    assert softbody.load_mesh is warpsim.bodies.mesh_io.load_mesh


def test_every_folder_has_a_floor():
    rooms = {room(m) for m in import_graph()}
    missing = sorted(r for r in rooms if not any(r in f for f in FLOORS))
    assert not missing, f"give these folders a floor in FLOORS (and CONTRIBUTING.md): {missing}"


def test_no_module_imports_a_higher_floor():
    found = upward_imports(import_graph())
    assert not found, "upward imports (move the shared piece down a floor): " + "; ".join(
        f"{a} (floor {fa}) imports {b} (floor {fb})" for a, b, fa, fb in found)


def _write_package(root, files):
    for rel, text in files.items():
        path = root / "warpsim" / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    return root / "warpsim"


def test_the_floors_check_reports_an_upward_import(tmp_path):
    package = _write_package(tmp_path, {
        "__init__.py": "", "core/__init__.py": "", "scenes/__init__.py": "", "scenes/basic.py": "X = 1\n",
        "core/model.py": "def f():\n    from ..scenes import basic  # inside a function: counts too\n",
        "scenes/teapot.py": "from ..core import model\n",  # downward: fine
    })
    graph = build_graph(package)
    assert upward_imports(graph) == [("warpsim.core.model", "warpsim.scenes.basic", 1, 5)]
    assert upward_imports(graph, allowed={("warpsim.core.model", "warpsim.scenes.basic"): "why"}) == []
    assert ("warpsim.core.model", "warpsim.scenes.basic", 1, 5) in upward_imports(
        {**import_graph(), "warpsim.core.model": {"warpsim.scenes.basic"}})


def test_no_module_imports_another_modules_private_names():
    found = [f for f in private_imports() if (f[0], f[3]) not in PRIVATE_PENDING]
    assert not found, "private names imported from another module (make them public): " + "; ".join(
        f"{m}:{line} imports {name} from {base}" for m, line, base, name in found)


def test_the_private_import_check_reports_one(tmp_path):
    package = _write_package(tmp_path, {
        "__init__.py": "", "core/__init__.py": "", "core/builder.py": "def _vec3():\n    pass\n",
        "core/forces.py": "from .builder import _vec3\nfrom .builder import __doc__\n",
        "bodies/__init__.py": "", "bodies/drag.py": "def f():\n    from ..core.builder import _vec3\n",
        "bodies/mesh.py": "from ..core import builder as b\n\nX = b._vec3, b.public, b.__name__\n",
    })
    assert private_imports(package) == [("warpsim.bodies.drag", 2, "warpsim.core.builder", "_vec3"),
                                        ("warpsim.bodies.mesh", 3, "warpsim.core.builder", "_vec3"),
                                        ("warpsim.core.forces", 1, "warpsim.core.builder", "_vec3")]
