"""The package's import directions (docs/architecture.md "Layers"): imports point downwards,
no stage imports another stage, geometry/ is pure maths (numpy, scipy, the standard library)."""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

from helpers import REPOSITORY

PACKAGE = REPOSITORY / "rotonly_cli"

#: what each part of the package may import from rotonly_cli (besides itself); compat, errors
#: and options are leaves (they import nothing of rotonly but each other)
ALLOWED = {
    "geometry": {"compat", "errors", "options"},
    "scene": {"compat", "errors", "options", "geometry"},
    "io": {"compat", "errors", "options", "geometry", "scene"},
    "stages": {"compat", "errors", "geometry", "scene", "io", "options", "runtime"},
}


def _imports(path: Path) -> set[str]:
    """Every module name ``path`` imports (module level and inside functions)."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module)
            names.update(f"{node.module}.{alias.name}" for alias in node.names)
    return names


def _modules(part: str) -> list[Path]:
    return sorted((PACKAGE / part).rglob("*.py"))


@pytest.mark.parametrize("part", sorted(ALLOWED))
def test_imports_point_downwards(part):
    for path in _modules(part):
        for name in _imports(path):
            pieces = name.split(".")
            if pieces[0] != "rotonly_cli" or len(pieces) < 2 or pieces[1] == part:
                continue
            assert pieces[1] in ALLOWED[part], f"{path.relative_to(PACKAGE)} imports {name}"


def test_leaves_import_only_leaves():
    leaves = [PACKAGE / "compat.py", PACKAGE / "errors.py", *sorted((PACKAGE / "options").glob("*.py"))]
    for path in leaves:
        for imported in _imports(path):
            pieces = imported.split(".")
            if pieces[0] == "rotonly_cli":
                assert pieces[1] in {"compat", "errors", "options"}, f"{path.name} imports {imported}"


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
