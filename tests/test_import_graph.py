"""No import circles among warpsim's modules: every ``import`` / ``from ... import`` in
``warpsim/`` (module level and inside functions alike) is an edge, and the graph must have no
strongly connected component of more than one module. A new circle fails here with its members."""

import ast
import functools
import pathlib

import warpsim

PACKAGE = pathlib.Path(warpsim.__file__).parent


def _modules():
    mods = {}
    for path in PACKAGE.rglob("*.py"):
        rel = path.relative_to(PACKAGE.parent)
        if rel.parts[1:2] == ("kernels",):  # Warp code only (a symlink in a checkout)
            continue
        parts = list(rel.with_suffix("").parts)
        is_package = parts[-1] == "__init__"
        mods[".".join(parts[:-1] if is_package else parts)] = (path, is_package)
    return mods


@functools.lru_cache(maxsize=1)
def import_graph():
    """{module: set of warpsim modules it imports}; ``from pkg import name`` points at the
    sub-module ``pkg.name`` when one exists, else at ``pkg``."""
    mods = _modules()
    graph = {m: set() for m in mods}
    for mod, (path, is_package) in mods.items():
        here = mod.split(".") if is_package else mod.split(".")[:-1]
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            targets = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = ".".join(here[: len(here) - node.level + 1] + ([node.module] if node.module else [])) \
                    if node.level else (node.module or "")
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in mods else base for a in node.names]
            graph[mod].update(t for t in targets if t in mods and t != mod)
    return graph


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
    assert "warpsim.diff" in graph["warpsim.core.simulator"]  # imported inside Simulator.__init__: counts too
    assert "warpsim.cli_common" in graph["warpsim.render.command"]


def test_no_import_circles_among_warpsim_modules():
    found = circles({k: set(v) for k, v in import_graph().items()})
    assert not found, "import circles (move the shared helper one floor down): " + "; ".join(
        " <-> ".join(c) for c in found)


def test_moved_names_still_agree():
    from warpsim import cli, cli_common
    from warpsim.bodies import softbody
    from warpsim.cloth.solver import ClothSemiImplicitEuler
    from warpsim.diff.rollout import CLOTH_SEMI_IMPLICIT

    assert CLOTH_SEMI_IMPLICIT == ClothSemiImplicitEuler.name
    assert cli.UsageError is cli_common.UsageError
    assert softbody.load_mesh is warpsim.bodies.mesh_io.load_mesh
