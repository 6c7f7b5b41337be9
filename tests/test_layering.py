"""The import graph keeps its layers: the CLI over the application layer, over formats and the core.

Every ``import`` in every module counts, at module level or inside a function (a lazy import is an
arrow all the same). The layers, top to bottom:

* ``relpoint_cli``: click, printing and exit codes;
* ``relpoint_app``: read a log, drive an estimator, write the outputs;
* ``formats``: bytes to core types and back; it may use only the core's value types, errors and geometry;
* ``relpoint``: the core, which never imports formats, the application layer or the CLI. Inside it the
  estimators import nothing from the packages that use them (pipeline, fusion, evaluation, simulation).

The one arrow up is the Python API in ``relpoint/__init__.py`` (``relpoint.run``, ``relpoint.evaluate``),
which hands over to the application layer when the attribute is first asked for.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("relpoint", "relpoint_app", "relpoint_cli", "formats")

#: What formats may import from the core.
FORMATS_MAY_USE = {"relpoint", "relpoint.types", "relpoint.errors", "relpoint.geometry"}
#: Core packages an estimator must not import: they sit above the estimators.
ABOVE_ESTIMATORS = ("relpoint.pipeline", "relpoint.fusion", "relpoint.evaluation", "relpoint.simulation")
#: The Python API's hand-over to the application layer.
API_FACADE = "relpoint"


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path, module: str) -> set[str]:
    """The project modules ``path`` imports, anywhere in the file (relative imports resolved)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(tree):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                base = ".".join([*anchor, base] if base else anchor)
            names = [base] + [f"{base}.{alias.name}" for alias in node.names]
        found |= {name for name in names if name.split(".")[0] in PACKAGES}
    return found


def _graph() -> dict[str, set[str]]:
    modules = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            module = _module_name(path)
            modules[module] = _imports(path, module)
    known = set(modules)
    # ``from pkg import name`` names a module only where ``pkg.name`` is one; otherwise it means ``pkg``
    return {module: {name for name in targets if name in known} for module, targets in modules.items()}


GRAPH = _graph()


def _within(name: str, package: str) -> bool:
    return name == package or name.startswith(package + ".")


def test_the_graph_covers_the_project() -> None:
    assert len(GRAPH) > 100
    assert "relpoint.estimators.relative_point.estimator" in GRAPH
    assert "relpoint.types" in GRAPH["formats.log"]


def test_formats_uses_only_the_cores_value_types_errors_and_geometry() -> None:
    offending = {
        module: sorted(name for name in targets if not _within(name, "formats") and name not in FORMATS_MAY_USE)
        for module, targets in GRAPH.items()
        if _within(module, "formats")
    }
    assert {module: names for module, names in offending.items() if names} == {}


@pytest.mark.parametrize("layer, above", [
    ("relpoint", ("formats", "relpoint_app", "relpoint_cli")),
    ("formats", ("relpoint_app", "relpoint_cli")),
    ("relpoint_app", ("relpoint_cli",)),
    ("relpoint.estimators", ABOVE_ESTIMATORS),
])  # fmt: skip
def test_no_arrow_back_up(layer: str, above: tuple[str, ...]) -> None:
    arrows = sorted(
        (module, name)
        for module, targets in GRAPH.items()
        if _within(module, layer) and module != API_FACADE
        for name in targets
        if any(_within(name, upper) for upper in above)
    )
    assert arrows == []


def test_the_api_facade_hands_over_to_the_application_layer_only() -> None:
    upward = {name for name in GRAPH[API_FACADE] if not _within(name, "relpoint")}
    assert upward == {"relpoint_app"}


def test_no_import_cycle_between_modules() -> None:
    """Tarjan's strongly connected components over the module graph: every one is a single module
    (a package's ``__init__`` re-exporting its own modules is not a cycle: it is dropped as a target
    of its own members)."""
    graph = {
        module: {
            name for name in targets
            if name != module and not (module.startswith(name + ".") and GRAPH.get(name) is not None)
        }
        for module, targets in GRAPH.items()
        if module != API_FACADE
    }  # fmt: skip
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for target in sorted(graph.get(node, ())):
            if target not in index:
                visit(target)
                low[node] = min(low[node], low[target])
            elif target in on_stack:
                low[node] = min(low[node], index[target])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    assert cycles == []
