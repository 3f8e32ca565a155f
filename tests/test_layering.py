"""The package's structure (docs/architecture.md "Layers"): every part of the package imports
only the parts below it, no stage imports another stage, geometry/ is pure maths (numpy, scipy,
the standard library), no module is over 600 lines, and no modules import each other in a
cycle.

What counts as an import: every ``import`` statement of a module, at module level, inside a
function or under ``if TYPE_CHECKING:`` alike (a lazy import still ties the two modules).
``from package import name`` imports the module ``package.name`` when there is one, else the
package's ``__init__``; importing ``a.b.c`` does not count as importing ``a`` or ``a.b``.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

from helpers import REPOSITORY

PACKAGE = REPOSITORY / "rotonly_cli"

#: the leaves: they import nothing of rotonly but each other
LEAVES = {"compat", "errors", "options", "version"}

#: what each part of the package (a folder or a module of rotonly_cli/) may import from
#: rotonly_cli besides itself and the leaves, bottom layer first; a part only names parts above
#: it in this table (test_the_layers_have_an_order)
ALLOWED = {
    "geometry": set(),
    "runtime": set(),
    "scene": {"geometry"},
    "io": {"geometry", "scene"},
    "baselines": {"geometry"},
    "simulation": {"geometry", "scene", "io"},
    "twoview": {"geometry", "runtime"},
    "multiview": {"geometry", "twoview"},
    "stages": {"geometry", "scene", "io", "runtime"},
    "calibration": {"geometry", "scene", "io", "runtime"},
    "evaluation": {"geometry", "scene", "io", "stages"},
    "monitor": {"runtime"},
    "chain": {"scene", "io", "runtime", "stages", "calibration"},
    "components": {"scene", "stages", "chain"},
    "pipeline": {"scene", "io", "runtime", "stages", "calibration", "evaluation", "monitor", "chain", "components"},
    "api": {"scene", "io", "runtime", "evaluation", "pipeline"},
    "convert": {"io"},
    "bench": {"geometry", "io", "runtime", "baselines", "simulation", "twoview", "pipeline"},
    "cli": {"geometry", "scene", "io", "runtime", "simulation", "twoview", "evaluation", "pipeline", "convert",
            "bench"},
    "console": {"runtime", "cli"},
    "__init__": {"api"},
}

MAX_LINES = 600


def _import_nodes(path: Path):
    return [node for node in ast.walk(ast.parse(path.read_text(), str(path)))
            if isinstance(node, (ast.Import, ast.ImportFrom))]


def _imports(path: Path) -> set[str]:
    """Every module name ``path`` imports (module level and inside functions)."""
    names = set()
    for node in _import_nodes(path):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif node.level == 0 and node.module:
            names.add(node.module)
            names.update(f"{node.module}.{alias.name}" for alias in node.names)
    return names


def _modules(part: str) -> list[Path]:
    folder = PACKAGE / part
    return sorted(folder.rglob("*.py")) if folder.is_dir() else [PACKAGE / f"{part}.py"]


def _parts() -> set[str]:
    """Every part of the package: its folders (with Python files) and its modules."""
    return {path.relative_to(PACKAGE).parts[0].removesuffix(".py") for path in PACKAGE.rglob("*.py")}


def _module_name(path: Path) -> str:
    parts = path.relative_to(REPOSITORY).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _import_graph() -> dict[str, set[str]]:
    """{module: the package's modules it imports} (the module docstring says what counts)."""
    paths = {_module_name(path): path for path in PACKAGE.rglob("*.py")}
    graph = {}
    for name, path in paths.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        targets = set()
        for node in _import_nodes(path):
            if isinstance(node, ast.Import):
                targets.update(alias.name for alias in node.names)
                continue
            module = node.module or ""
            if node.level:  # relative: from the package, one level up per dot beyond the first
                base = package.split(".")[:len(package.split(".")) - node.level + 1]
                module = ".".join(base + ([module] if module else []))
            for alias in node.names:
                targets.add(f"{module}.{alias.name}" if f"{module}.{alias.name}" in paths else module)
        graph[name] = {target for target in targets if target in paths and target != name}
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan, iterative)."""
    index, low, on_stack, stack, found, counter = {}, {}, set(), [], [], 0
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
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


def test_every_part_of_the_package_has_a_place():
    assert _parts() - LEAVES == set(ALLOWED), "a part of rotonly_cli/ without its row in ALLOWED (or a row too many)"


def test_the_layers_have_an_order():
    order = list(ALLOWED)
    for part, allowed in ALLOWED.items():
        above = allowed - set(order[:order.index(part)])
        assert not above, f"{part} may import {sorted(above)}, which stand above it in ALLOWED"


@pytest.mark.parametrize("part", sorted(ALLOWED))
def test_imports_point_downwards(part):
    for path in _modules(part):
        for name in _imports(path):
            pieces = name.split(".")
            if pieces[0] != "rotonly_cli" or len(pieces) < 2 or pieces[1] == part or pieces[1] not in _parts():
                continue
            assert pieces[1] in ALLOWED[part] | LEAVES, f"{path.relative_to(PACKAGE)} imports {name}"


def test_leaves_import_only_leaves():
    for part in sorted(LEAVES):
        for path in _modules(part):
            for imported in _imports(path):
                pieces = imported.split(".")
                if pieces[0] == "rotonly_cli":
                    assert pieces[1] in LEAVES, f"{path.relative_to(PACKAGE)} imports {imported}"


def test_no_stage_imports_another_stage():
    stages = {path.stem for path in _modules("stages") if path.stem != "__init__"}
    for path in _modules("stages"):
        for name in _imports(path):
            pieces = name.split(".")
            if pieces[:2] == ["rotonly_cli", "stages"] and len(pieces) > 2:
                assert pieces[2] not in stages or pieces[2] == path.stem, \
                    f"stages/{path.name} imports the stage {pieces[2]}"


def test_geometry_imports_only_numpy_scipy_and_the_standard_library():
    for path in _modules("geometry"):
        for name in _imports(path):
            top = name.split(".")[0]
            assert top in {"numpy", "scipy", "rotonly_cli", "__future__"} or top in sys.stdlib_module_names, \
                f"{path.relative_to(PACKAGE)} imports {name}"


def test_no_module_is_over_600_lines():
    long = {str(path.relative_to(PACKAGE)): lines for path in sorted(PACKAGE.rglob("*.py"))
            if (lines := len(path.read_text().splitlines())) > MAX_LINES}
    assert not long, f"modules over {MAX_LINES} lines (split them by concern): {long}"


def test_no_modules_import_each_other_in_a_cycle():
    assert _cycles(_import_graph()) == []


def test_the_cycle_check_sees_a_cycle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": set()}
    assert _cycles(graph) == [["a", "b", "c"]]
    assert _import_graph()["rotonly_cli.chain.stages"] >= {"rotonly_cli.chain.run", "rotonly_cli.chain.reject"}
