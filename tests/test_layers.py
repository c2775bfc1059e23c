"""No import cycles among the project's modules (slam_engine, api_schemas, service, lidarmap, bench).

Every ``import`` counts, wherever it stands: at the top of a module, inside a function (a lazy import
is still a dependency, it only fails later), under ``if TYPE_CHECKING``. ``import a.b`` depends on
``a.b``; ``from a.b import c`` on the module ``a.b.c`` when there is one, else on ``a.b`` (the name is
defined there). Parent packages are not counted: importing ``a.b.c`` runs ``a/b/__init__.py`` first,
but a package that re-exports its own modules is no cycle worth the name.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("slam_engine", "api_schemas", "service", "lidarmap", "bench")


def module_files(root: Path, packages: tuple[str, ...]) -> dict[str, Path]:
    """Dotted module name -> file, for every .py file of ``packages`` under ``root``."""
    found: dict[str, Path] = {}
    for package in packages:
        for path in sorted((root / package).rglob("*.py")):
            parts = list(path.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            found[".".join(parts)] = path
    return found


def imported_modules(name: str, path: Path, modules: set[str]) -> set[str]:
    """The project modules that module ``name`` (file ``path``) imports, anywhere in its body."""
    is_package = path.name == "__init__.py"
    tree = ast.parse(path.read_text(), filename=str(path))
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                target = alias.name
                while target and target not in modules:  # `import a.b.c` of a name only: its module
                    target = target.rpartition(".")[0]
                if target:
                    found.add(target)
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: from the module's own package upwards
                base = name.split(".") if is_package else name.split(".")[:-1]
                base = base[: len(base) - (node.level - 1)]
                source = ".".join(base + ([node.module] if node.module else []))
            else:
                source = node.module or ""
            for alias in node.names:
                submodule = f"{source}.{alias.name}"
                if submodule in modules:
                    found.add(submodule)
                elif source in modules:
                    found.add(source)
    found.discard(name)
    return found


def import_graph(root: Path, packages: tuple[str, ...]) -> dict[str, set[str]]:
    files = module_files(root, packages)
    return {name: imported_modules(name, path, set(files)) for name, path in files.items()}


def find_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """One cycle per strongly connected component of more than one module (Tarjan's algorithm),
    each as a path that starts and ends at the same module."""
    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10 * len(graph) + 100))
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[set[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for nxt in sorted(graph.get(node, ())):
            if nxt not in index:
                visit(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in on_stack:
                low[node] = min(low[node], index[nxt])
        if low[node] == index[node]:
            component = set()
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.add(member)
                if member == node:
                    break
            if len(component) > 1:
                components.append(component)

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return [_cycle_in(graph, component) for component in components]


def _cycle_in(graph: dict[str, set[str]], component: set[str]) -> list[str]:
    """A shortest cycle through the component's first module (breadth-first within the component)."""
    start = min(component)
    paths = {start: [start]}
    frontier = [start]
    while frontier:
        following = []
        for node in frontier:
            for nxt in sorted(graph[node] & component):
                if nxt == start:
                    return paths[node] + [start]
                if nxt not in paths:
                    paths[nxt] = paths[node] + [nxt]
                    following.append(nxt)
        frontier = following
    raise AssertionError(f"no cycle through {start} in {sorted(component)}")


def test_the_project_has_no_import_cycles() -> None:
    graph = import_graph(ROOT, PACKAGES)
    assert len(graph) > 100, "the scan found too few modules"
    assert graph["service.jobs.mapping"] >= {"service.jobs.live", "service.jobs.context"}  # edges are seen
    assert "bench.margin" in graph["bench.cli"]  # the bench is scanned too (its tables once imported the CLI)
    cycles = [" -> ".join(cycle) for cycle in find_cycles(graph)]
    assert cycles == []


def package_graph(graph: dict[str, set[str]], package: str) -> dict[str, set[str]]:
    """``graph`` collapsed onto the parts of ``package`` (``service.storage``, ``service.http_errors``, ...)."""
    def part(module: str) -> str | None:
        names = module.split(".")
        return ".".join(names[:2]) if names[0] == package and len(names) > 1 else None

    collapsed: dict[str, set[str]] = {}
    for module, targets in graph.items():
        if (source := part(module)) is not None:
            collapsed.setdefault(source, set()).update(
                p for p in map(part, targets) if p is not None and p != source)
    return collapsed


def test_the_service_layers_have_no_cycles() -> None:
    """The service's sub-packages stack up: storage <- jobs <- runners <- api, never back."""
    layers = package_graph(import_graph(ROOT, PACKAGES), "service")
    assert {"service.storage", "service.jobs", "service.runners", "service.api"} <= set(layers)
    assert "service.storage" in layers["service.jobs"] and "service.jobs" in layers["service.runners"]
    assert [" -> ".join(cycle) for cycle in find_cycles(layers)] == []
    assert not layers["service.storage"] & {"service.jobs", "service.runners", "service.api"}


def test_the_engine_stages_stack_up() -> None:
    """The engine's packages as its pipeline: the front end never depends on the back end, products,
    texture or evaluation; the loaders (formats) never on the back end, the products or the pipeline."""
    layers = package_graph(import_graph(ROOT, PACKAGES), "slam_engine")
    stages = {"slam_engine.frontend", "slam_engine.backend", "slam_engine.products", "slam_engine.texture",
              "slam_engine.evaluation", "slam_engine.pipeline", "slam_engine.simulation"}
    assert {"slam_engine.model", "slam_engine.frontend", "slam_engine.backend"} <= set(layers)
    assert "slam_engine.model" in layers["slam_engine.frontend"]  # edges are seen
    assert not layers["slam_engine.frontend"] & (stages - {"slam_engine.frontend"})
    assert not layers["slam_engine.formats"] & {"slam_engine.backend", "slam_engine.products", "slam_engine.pipeline",
                                                "slam_engine.evaluation", "slam_engine.simulation"}


@pytest.mark.parametrize("where", ["top", "function", "relative"])
def test_a_planted_cycle_is_found(tmp_path: Path, where: str) -> None:
    """The checker itself works: a cycle through a top-level, a function-level or a relative import."""
    pkg = tmp_path / "service"
    (pkg / "runners").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "runners" / "__init__.py").write_text("")
    (pkg / "runners" / "local.py").write_text("from service.runners.celery_runner import CeleryRunner\n")
    back = {
        "top": "from service.runners import local\n",
        "function": "def create():\n    from service.runners.local import LocalRunner\n    return LocalRunner\n",
        "relative": "from .local import LocalRunner\n",
    }[where]
    (pkg / "runners" / "celery_runner.py").write_text(back)
    (pkg / "runners" / "base.py").write_text("import service.runners.local\n")  # into the cycle, not on it
    graph = import_graph(tmp_path, ("service",))
    assert graph["service.runners.base"] == {"service.runners.local"}
    assert find_cycles(graph) == [["service.runners.celery_runner", "service.runners.local",
                                   "service.runners.celery_runner"]]


def test_no_cycle_is_reported_without_one(tmp_path: Path) -> None:
    pkg = tmp_path / "service"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("from service import a\n")  # a package re-exporting its module
    (pkg / "a.py").write_text("import json\nfrom service.b import f\n")
    (pkg / "b.py").write_text("def f():\n    import service.c\n")
    (pkg / "c.py").write_text("")
    graph = import_graph(tmp_path, ("service",))
    assert graph == {"service": {"service.a"}, "service.a": {"service.b"}, "service.b": {"service.c"},
                     "service.c": set()}
    assert find_cycles(graph) == []
