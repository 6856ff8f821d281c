"""The package's modules import one another in one direction: the import graph is acyclic.

Every import statement counts, at module level or inside a function (a deferred import
still makes two modules depend on each other). The graph is read from the source with
``ast``, so nothing is imported to build it.
"""

from __future__ import annotations

import ast
import pathlib

import mitsuba_shsampling

ROOT = pathlib.Path(mitsuba_shsampling.__file__).parent
PACKAGE = "mitsuba_shsampling"


def module_files() -> dict[str, pathlib.Path]:
    """Dotted module name -> source file, for every module of the package (``__init__`` as the package)."""
    modules = {}
    for path in sorted(ROOT.rglob("*.py")):
        parts = (PACKAGE, *path.relative_to(ROOT).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        modules[".".join(parts)] = path
    return modules


def imported_modules(name: str, path: pathlib.Path, modules: dict[str, pathlib.Path]) -> set[str]:
    """The package's modules that ``name`` imports (``from X import y`` counts ``X.y`` if that is a module)."""
    is_package = path.name == "__init__.py"
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = name.split(".")
                base = base[:len(base) - node.level + (1 if is_package else 0)]
                origin = ".".join(base + ([node.module] if node.module else []))
            else:
                origin = node.module
            targets = [f"{origin}.{alias.name}" if f"{origin}.{alias.name}" in modules else origin
                       for alias in node.names]
        else:
            continue
        out |= {t for t in targets if t in modules and t != name}
    return out


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of ``graph`` as a list of nodes (first == last), or None."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        path.append(node)
        for child in sorted(graph[node]):
            if state.get(child) == 1:
                return path[path.index(child):] + [child]
            if child not in state:
                cycle = visit(child)
                if cycle:
                    return cycle
        path.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state:
            cycle = visit(node)
            if cycle:
                return cycle
    return None


def test_graph_reader_sees_a_deferred_import_and_resolves_relative_names():
    modules = module_files()
    imports = imported_modules(f"{PACKAGE}.sweep.command", modules[f"{PACKAGE}.sweep.command"], modules)
    assert f"{PACKAGE}.sweep.grid" in imports  # imported inside command()
    assert f"{PACKAGE}.command_line" in imports


def test_cycle_finder_finds_a_cycle_and_accepts_a_tree():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b", "c"}, "b": {"c"}, "c": set()}) is None


def test_the_package_has_no_import_cycle():
    modules = module_files()
    graph = {name: imported_modules(name, path, modules) for name, path in modules.items()}
    cycle = find_cycle(graph)
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def test_no_function_of_the_integrators_is_longer_than_80_lines():
    """Long functions there were copies that drifted apart (one path loop serves sh_path and sh_prb)."""
    long = []
    for path in sorted((ROOT / "integrators").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and node.end_lineno - node.lineno >= 80:
                long.append(f"{path.name}:{node.name} ({node.end_lineno - node.lineno + 1} lines)")
    assert long == []


def test_a_lanes_estimators_read_the_per_scene_state_which_never_calls_them():
    """One direction of travel: integrators -> estimators -> environment (state and strategies)."""
    modules = module_files()
    state = f"{PACKAGE}.integrators.environment"
    estimators = f"{PACKAGE}.integrators.estimators"
    assert estimators not in imported_modules(state, modules[state], modules)
    assert state not in imported_modules(f"{PACKAGE}.integrators.strategy", modules[f"{PACKAGE}.integrators.strategy"],
                                         modules)
