"""The layering rules, downwards only: the engine knows nothing of the web, the command line or the
benchmark; the service nothing of the command line or the benchmark; the schemas nothing but pydantic."""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
FORBIDDEN = {
    "slam_engine": {"service", "api_schemas", "lidarmap", "bench",
                    "fastapi", "starlette", "uvicorn", "celery", "redis"},
    "service": {"lidarmap", "bench"},
}
STDLIB = set(sys.stdlib_module_names)


def imported_top_modules(package: str) -> dict[str, set[str]]:
    """Top-level module names imported by each file of ``package`` (absolute imports only)."""
    found: dict[str, set[str]] = {}
    for path in sorted((ROOT / package).rglob("*.py")):
        tree = ast.parse(path.read_text(), filename=str(path))
        names: set[str] = set()
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                names.update(alias.name.split(".")[0] for alias in node.names)
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names.add(node.module.split(".")[0])
        found[str(path.relative_to(ROOT))] = names
    return found


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_layers_import_only_downwards(package: str) -> None:
    files = imported_top_modules(package)
    assert files, f"{package} has no Python files"
    offenders = {f: sorted(n & FORBIDDEN[package]) for f, n in files.items() if n & FORBIDDEN[package]}
    assert offenders == {}


def test_api_schemas_import_only_pydantic_and_stdlib() -> None:
    files = imported_top_modules("api_schemas")
    assert files
    allowed = STDLIB | {"pydantic", "pydantic_core", "api_schemas", "typing_extensions", "annotated_types"}
    offenders = {f: sorted(n - allowed) for f, n in files.items() if n - allowed}
    assert offenders == {}


def test_checker_sees_a_forbidden_import(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The scan itself works: a planted forbidden import is reported."""
    pkg = tmp_path / "slam_engine"
    pkg.mkdir()
    (pkg / "bad.py").write_text("from service.api.app import create_app\nimport numpy\n")
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    assert imported_top_modules("slam_engine") == {"slam_engine/bad.py": {"service", "numpy"}}
