"""The package layout of docs/design.md: algorithms are siblings, common/ and envs/ import no algorithm, small modules."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from sb3_pearl import PEARL, PEARLPlus

PACKAGE = Path(__file__).resolve().parent.parent / "sb3_pearl"
ALGORITHMS = {"pearl", "finetune", "maml"}
TOOLS = {"zoo", "reproduce", "experiments", "plots", "demo", "diagnose", "train", "enjoy", "registry"}
MAX_LINES = 550  # "no source file over ~500 lines"


def _runtime_imports(path: Path) -> list[str]:
    """sb3_pearl modules imported by ``path`` outside ``if TYPE_CHECKING:`` blocks (function-level imports included)."""
    tree = ast.parse(path.read_text())
    type_only = {
        id(node)
        for block in ast.walk(tree)
        if isinstance(block, ast.If) and "TYPE_CHECKING" in ast.unparse(block.test)
        for node in ast.walk(block)
    }
    modules = []
    for node in ast.walk(tree):
        if id(node) in type_only:
            continue
        if isinstance(node, ast.ImportFrom) and node.module:
            modules.append(node.module)
        elif isinstance(node, ast.Import):
            modules.extend(alias.name for alias in node.names)
    return [m for m in modules if m.startswith("sb3_pearl.")]


SOURCES = sorted(PACKAGE.rglob("*.py"))


@pytest.mark.parametrize("path", SOURCES, ids=lambda p: str(p.relative_to(PACKAGE)))
def test_dependency_rule(path: Path) -> None:
    parts = path.relative_to(PACKAGE).parts
    home = parts[0] if len(parts) > 1 else Path(parts[0]).stem
    for module in _runtime_imports(path):
        target = module.split(".")[1]
        if home in ALGORITHMS:
            assert target not in (ALGORITHMS - {home}) | TOOLS, f"{path}: an algorithm imports {module}"
        if home == "common":
            assert target not in ALGORITHMS | TOOLS, f"{path}: common/ imports {module}"
        if home == "envs":
            assert target == "envs", f"{path}: envs/ imports {module}"
        if home == "experiments":  # data and declarations: no tool imports them back (no import cycle)
            assert target not in {"zoo", "reproduce", "plots", "demo", "diagnose", "train", "enjoy"}, (
                f"{path} imports {module}"
            )
        if home == "registry":
            assert target not in TOOLS, f"{path}: the registry imports the tool {module}"


@pytest.mark.parametrize("path", SOURCES, ids=lambda p: str(p.relative_to(PACKAGE)))
def test_modules_are_small(path: Path) -> None:
    n_lines = len(path.read_text().splitlines())
    assert n_lines <= MAX_LINES, f"{path} has {n_lines} lines: split it by what it holds (docs/design.md)"


def test_pearlplus_extends_pearl() -> None:
    assert issubclass(PEARLPlus, PEARL)
