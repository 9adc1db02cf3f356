"""The import graph of the packages: no circles between modules, and layers that import one way only.

Every ``import`` statement of every module counts, those inside functions included (a deferred import is still a
dependency; deferring one is how a circle hides), except those under ``if TYPE_CHECKING:``. Importing a submodule is
an edge to that submodule alone, not to the packages above it.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("vafn_gym", "vafn_media", "vafn_sb3", "vafn_app")
#: Package -> the other packages of :data:`PACKAGES` it may import.
ALLOWED = {
    "vafn_gym": set(),
    "vafn_media": {"vafn_gym"},
    "vafn_sb3": {"vafn_gym"},
    "vafn_app": {"vafn_gym", "vafn_media", "vafn_sb3"},
}


def module_files(root: Path = REPO_ROOT) -> dict[str, Path]:
    """Module name -> file, for every module of :data:`PACKAGES` under ``root``."""
    modules = {}
    for package in PACKAGES:
        for path in sorted((root / package).rglob("*.py")):
            parts = path.relative_to(root).with_suffix("").parts
            modules[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return modules


def _is_type_checking(node: ast.If) -> bool:
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _imports(node: ast.AST) -> Iterator[ast.Import | ast.ImportFrom]:
    """The import statements under ``node``, skipping ``if TYPE_CHECKING:`` bodies."""
    for child in ast.iter_child_nodes(node):
        if isinstance(child, (ast.Import, ast.ImportFrom)):
            yield child
        elif isinstance(child, ast.If) and _is_type_checking(child):
            yield from (item for statement in child.orelse for item in _imports_of(statement))
        else:
            yield from _imports(child)


def _imports_of(statement: ast.stmt) -> Iterator[ast.Import | ast.ImportFrom]:
    if isinstance(statement, (ast.Import, ast.ImportFrom)):
        yield statement
    else:
        yield from _imports(statement)


def imported_names(module: str, path: Path) -> set[str]:
    """Absolute dotted names ``module`` imports: modules, and ``module.name`` for each ``from module import name``."""
    is_package = path.name == "__init__.py"
    names = set()
    for node in _imports(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
            continue
        if node.level:  # relative: from the module's package, one level up per extra dot
            base = module.split(".") if is_package else module.split(".")[:-1]
            base = base[: len(base) - (node.level - 1)]
            target = ".".join([*base, node.module] if node.module else base)
        else:
            target = node.module or ""
        names.add(target)
        names.update(f"{target}.{alias.name}" for alias in node.names)
    return names


def import_graph(root: Path = REPO_ROOT) -> dict[str, set[str]]:
    """Module -> the modules of :data:`PACKAGES` it imports (a ``from package import name`` of a submodule names it)."""
    modules = module_files(root)
    graph = {}
    for module, path in modules.items():
        edges = set()
        for name in imported_names(module, path):
            if name in modules:
                edges.add(name)
            elif name.rpartition(".")[0] in modules:  # from module import attribute
                edges.add(name.rpartition(".")[0])
        graph[module] = edges
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with a circle (two modules or more, or a module importing itself)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []

    def visit(node: str) -> None:  # Tarjan's algorithm (the graph has a few hundred nodes: recursion is fine)
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for successor in graph[node]:
            if successor not in index:
                visit(successor)
                low[node] = min(low[node], low[successor])
            elif successor in on_stack:
                low[node] = min(low[node], index[successor])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1 or node in graph[node]:
                found.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return found


def layer_violations(graph: dict[str, set[str]]) -> list[str]:
    """``module -> imported`` for every import of a package its layer may not import."""
    return sorted(f"{module} -> {target}" for module, targets in graph.items() for target in targets
                  if (top := target.split(".")[0]) != module.split(".")[0]
                  and top not in ALLOWED[module.split(".")[0]])


def test_the_graph_sees_the_imports_it_must():
    graph = import_graph()
    assert "vafn_gym.envs.multi_arm" in graph and "vafn_sb3.registry" in graph
    assert "vafn_sb3.maddpg.maddpg" in graph["vafn_sb3.registry"] or "vafn_sb3.maddpg" in graph["vafn_sb3.registry"]
    assert "vafn_sb3.common.save" in graph["vafn_sb3.sac.sac"]


def test_a_circle_and_a_backward_import_are_found(tmp_path):
    for package in PACKAGES:
        (tmp_path / package).mkdir()
        (tmp_path / package / "__init__.py").write_text("")
    (tmp_path / "vafn_sb3" / "a.py").write_text("def f():\n    from vafn_sb3.b import g\n")
    (tmp_path / "vafn_sb3" / "b.py").write_text("from . import a\nimport vafn_media\n")
    (tmp_path / "vafn_gym" / "c.py").write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n"
                                                "    import vafn_sb3\n")
    graph = import_graph(tmp_path)
    assert cycles(graph) == [["vafn_sb3.a", "vafn_sb3.b"]]
    assert layer_violations(graph) == ["vafn_sb3.b -> vafn_media"]


def test_no_import_circles():
    assert cycles(import_graph()) == []


def test_layers_import_one_way():
    assert layer_violations(import_graph()) == []


@pytest.mark.parametrize("package", ["vafn_gym"])
def test_environments_import_no_torch(package):
    code = f"import sys, {package}; print(sorted(m for m in ('torch', 'stable_baselines3') if m in sys.modules))"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO_ROOT, check=True)
    assert result.stdout.strip() == "[]"
