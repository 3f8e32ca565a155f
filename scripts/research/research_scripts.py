"""What the research scripts' tests share (test_research.py, test_research_inputs.py): the
repository's paths, a script of this folder loaded as a module, a file's digest."""

from __future__ import annotations

import hashlib
import importlib.util
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
FIXTURES = ROOT / "data_fixtures"


def load_script_at(path: Path, name: str):
    """The script ``path`` imported as the module ``research_<name>``."""
    spec = importlib.util.spec_from_file_location(f"research_{name}", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def load_script(name: str):
    """scripts/research/<name>.py as a module."""
    return load_script_at(Path(__file__).with_name(f"{name}.py"), name)


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()
