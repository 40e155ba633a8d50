"""The dependency rule of docs/design.md, checked on the import graph of every module (function-level imports included).

Two packages: the library ``sb3_pearl`` and, above it, the paper's reproduction ``pearl_paper`` (in the repository,
not in the wheel). Rooms are ranked; a module imports its own room or a lower-ranked one, never a sibling of its rank
(the algorithms never import each other), except the tools on top of each package, which may use one another as long
as no cycle forms. Every room of ``pearl_paper`` ranks above every room of ``sb3_pearl``, so the library never
imports the paper's harness. No import cycle anywhere: neither between modules nor between rooms.
"""

from __future__ import annotations

import ast
import io
import re
import tokenize
from collections.abc import Iterable, Mapping
from pathlib import Path

import pytest

from sb3_pearl import PEARL, PEARLPlus

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = (ROOT / "sb3_pearl", ROOT / "pearl_paper")
LIBRARY_TOOLS = ("zoo", "plots", "diagnose", "tracking", "train", "enjoy")
HARNESS_TOOLS = ("pearl_paper.reproduce", "pearl_paper.demo")
TOOLS = LIBRARY_TOOLS + HARNESS_TOOLS
RANK = {
    "envs": 0,  # a family is usable as a plain Gymnasium env
    "config": 0,  # YAML data
    "common": 1,  # the algorithms' building blocks
    "evaluation": 2,  # meta-test protocol, statistics, callbacks, progress, figures
    "pearl": 3,  # the algorithms: siblings
    "finetune": 3,
    "maml": 3,
    "oracle": 3.5,  # Fine-Tune's soft actor-critic, told the task: above finetune, below the package
    "__init__": 4,  # `import sb3_pearl`: the algorithms and the env registration
    "registry": 4,
    "budgets": 5,  # the budget presets' loader: read by train.py --budget and by the paper's harness
    **dict.fromkeys(LIBRARY_TOOLS, 6),
    # the paper's reproduction, above the whole library
    "pearl_paper": 7,  # the package's docstring only
    "pearl_paper.experiments": 7,  # the paper's experiments: data and declarations
    **dict.fromkeys(HARNESS_TOOLS, 8),
}


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {module_name(path): path for package in PACKAGES for path in sorted(package.rglob("*.py"))}


def room(module: str) -> str:
    """
    The room of a module: its first folder (or file) below ``sb3_pearl``, the package itself being ``__init__``; in
    ``pearl_paper``, the first folder (or file) with the package's name before it, the package itself ``pearl_paper``.
    """
    parts = module.split(".")
    if parts[0] == "pearl_paper":
        return ".".join(parts[:2])
    return parts[1] if len(parts) > 1 else "__init__"


def runtime_imports(module: str, type_only_too: bool = False) -> set[str]:
    """
    The project's modules ``module`` imports outside ``if TYPE_CHECKING:`` blocks (with ``type_only_too``, inside them
    too), function-level imports included.
    """
    path = MODULES[module]
    tree = ast.parse(path.read_text())
    type_only = {
        id(node)
        for block in ast.walk(tree)
        if isinstance(block, ast.If) and "TYPE_CHECKING" in ast.unparse(block.test) and not type_only_too
        for node in ast.walk(block)
    }
    package = module.split(".") if path.name == "__init__.py" else module.split(".")[:-1]
    targets = set()
    for node in ast.walk(tree):
        if id(node) in type_only:
            continue
        if isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative import
                base = ".".join(package[: len(package) - node.level + 1] + ([node.module] if node.module else []))
            for alias in node.names:  # `from pkg import module` imports the module, `from module import name` the module
                targets.add(f"{base}.{alias.name}" if f"{base}.{alias.name}" in MODULES else base)
        elif isinstance(node, ast.Import):
            targets.update(alias.name for alias in node.names)
    return {target for target in targets if target in MODULES and target != module}


GRAPH = {module: runtime_imports(module) for module in MODULES}


def cycles(graph: Mapping[str, Iterable[str]]) -> list[list[str]]:
    """The strongly connected components with more than one node (Tarjan): every import cycle, as its members."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        for successor in graph.get(node, ()):
            if successor not in index:
                visit(successor)
                low[node] = min(low[node], low[successor])
            elif successor in stack:
                low[node] = min(low[node], index[successor])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return found


def test_cycle_finder_on_hand_made_graphs() -> None:
    assert cycles({"a": ["b"], "b": ["c"], "c": []}) == []
    assert cycles({"a": ["b"], "b": ["c"], "c": ["a"], "d": ["a"]}) == [["a", "b", "c"]]
    assert sorted(cycles({"a": ["b"], "b": ["a"], "c": ["d"], "d": ["c"]})) == [["a", "b"], ["c", "d"]]


def test_every_room_is_ranked() -> None:
    assert {room(module) for module in MODULES} <= set(RANK), "a new top-level module or folder: give it a rank here"


@pytest.mark.parametrize("module", sorted(MODULES))
def test_dependency_rule(module: str) -> None:
    home = room(module)
    for target in GRAPH[module]:
        there = room(target)
        if there == home:
            continue
        allowed = (
            RANK[there] < RANK[home]
            or (home in LIBRARY_TOOLS and there in LIBRARY_TOOLS)
            or (home in HARNESS_TOOLS and there in HARNESS_TOOLS)
        )
        assert allowed, f"{module} (room {home}, rank {RANK[home]}) imports {target} (room {there}, rank {RANK[there]})"


def test_the_library_imports_nothing_of_the_paper() -> None:
    """The rank puts the paper's harness above the library; said once more as the rule it is, on the static graph."""
    found = sorted(
        (module, target)
        for module, targets in GRAPH.items()
        if module.startswith("sb3_pearl")
        for target in targets
        if target.startswith("pearl_paper")
    )
    assert found == [], found


def test_the_harness_ranks_above_the_library() -> None:
    library = [RANK[r] for r in {room(m) for m in MODULES if m.startswith("sb3_pearl")}]
    harness = [RANK[r] for r in {room(m) for m in MODULES if m.startswith("pearl_paper")}]
    assert harness and min(harness) > max(library)


def test_no_import_cycle_between_modules() -> None:
    assert cycles(GRAPH) == []


@pytest.mark.parametrize("home", ["pearl", "finetune", "oracle", "maml"])
def test_no_import_cycle_inside_an_algorithm_room_type_only_imports_included(home: str) -> None:
    """An algorithm is one class with its own methods: no module of its room imports back the module that imports it,
    not even for type annotations (PEARL's collection and returns are its methods, not functions of the model)."""
    graph = {
        module: {target for target in runtime_imports(module, type_only_too=True) if room(target) == home}
        for module in MODULES
        if room(module) == home
    }
    assert cycles(graph) == []


def test_no_import_cycle_between_rooms() -> None:
    rooms: dict[str, set[str]] = {}
    for module, targets in GRAPH.items():
        rooms.setdefault(room(module), set()).update(room(target) for target in targets if room(target) != room(module))
    assert cycles(rooms) == []


def test_the_graph_sees_function_level_imports() -> None:
    """The rule would be toothless if lazy imports were invisible: write_meta_test imports the figures inside itself."""
    assert "sb3_pearl.evaluation.figures" in GRAPH["sb3_pearl.evaluation.held_out"]


def test_pearlplus_extends_pearl() -> None:
    assert issubclass(PEARLPlus, PEARL)


@pytest.mark.parametrize("package", ["sb3_pearl.pearl", "sb3_pearl.finetune", "sb3_pearl.maml"])
def test_an_algorithm_imports_only_algorithm_code(package: str) -> None:
    """Importing an algorithm (in a fresh interpreter) loads none of its observers: no module of the diagnostics, the
    evaluation layer, the reproduction harness or the zoo CLI."""
    import subprocess
    import sys

    code = (
        f"import sys, {package}\n"
        "print(' '.join(m for m in sys.modules if m.startswith('pearl_paper') or m.startswith('sb3_pearl.') and any("
        "part in m.split('.') for part in ('diagnostics', 'evaluation', 'zoo'))))"
    )
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert loaded == [], f"importing {package} loads {loaded}"


OBSERVERS = ("evaluation", "zoo", "pearl_paper.reproduce", "pearl_paper.demo")


@pytest.mark.parametrize("module", sorted(m for m in MODULES if room(m) in ("pearl", "finetune", "maml")))
def test_algorithm_modules_import_no_observer(module: str) -> None:
    """The same on the static graph (function-level imports included): an algorithm module imports no module of the
    evaluation layer, the harness, the zoo or the diagnostics; the diagnostics themselves (``pearl.diagnostics``) are
    the observer that lives beside PEARL and may use the evaluation layer."""
    if ".diagnostics" in module:
        return
    observers = sorted(t for t in GRAPH[module] if room(t) in OBSERVERS or ".diagnostics" in t)
    assert observers == [], f"{module} imports {observers}: observe it from above (a callback, the logger)"


def test_the_observer_rule_sees_a_function_level_import() -> None:
    """The graph the rule reads holds imports made inside functions (the report's figures and sections are imported in
    ``build_report``), which the import-time test above cannot see."""
    assert "pearl_paper.reproduce.remeasured_tables" in GRAPH["pearl_paper.reproduce.report"]
    assert "sb3_pearl.evaluation.meta_test" in GRAPH["sb3_pearl.pearl.diagnostics.rollouts"]


SPEED_FIGURE = re.compile(
    r"\d+(\.\d+)?(-\d+(\.\d+)?)?(x|%) \*?(faster|slower)|\d+(-\d+)? fps\b"  # ratios and rates
    r"|\d+(\.\d+)? (core|CPU)-hours?\b|\d+(\.\d+)? ?(ms|s)/(step|update)\b"  # a measured cost
)


def docstrings_and_comments(path: Path) -> Iterable[tuple[int, str]]:
    """The docstrings (with their first line) and the comments of a module."""
    source = path.read_text()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            docstring = ast.get_docstring(node, clean=False)
            if docstring is not None:
                yield node.body[0].lineno, docstring
    for token in tokenize.generate_tokens(io.StringIO(source).readline):
        if token.type == tokenize.COMMENT:
            yield token.start[0], token.string


def test_the_speed_figure_pattern_on_hand_made_lines() -> None:
    for figure in ("3.6x faster", "18% slower", "560-833 fps", "~8.5 core-hours a seed", "1 CPU-hour", "27.6 ms/step"):
        assert SPEED_FIGURE.search(figure), figure
    for prose in ("2x128 networks", "the step is compute-bound", "one thread per core", "5 s of collection"):
        assert not SPEED_FIGURE.search(prose), prose


def test_docstrings_carry_no_speed_figures() -> None:
    """Measured speed ratios belong in docs/ (speed.md, pearl.md, ...) with their command, not in code."""
    found = [
        f"{path.relative_to(ROOT)}:{line}: {match.group(0)}"
        for path in MODULES.values()
        for line, text in docstrings_and_comments(path)
        for match in SPEED_FIGURE.finditer(text)
    ]
    assert not found, found
