"""The type checker's configuration: mypy covers the engine, the schemas, the whole service and the command line, and
no project module is let off any error code (.ci/run runs mypy; this guards the configuration)."""

from __future__ import annotations

import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PROJECT_PACKAGES = ("slam_engine", "api_schemas", "service", "lidarmap")


def _mypy_config() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["mypy"]


def _modules(override: dict) -> list[str]:
    """An override's ``module``: one pattern or a list of them."""
    module = override.get("module", [])
    return [module] if isinstance(module, str) else list(module)


def _is_project_module(pattern: str) -> bool:
    """A module pattern that names (or matches, ``*`` included) a module of one of the project's packages."""
    top = pattern.split(".")[0]
    return top in PROJECT_PACKAGES or top == "*"


def test_mypy_checks_every_project_module_in_full() -> None:
    mypy = _mypy_config()
    assert set(mypy["packages"]) >= set(PROJECT_PACKAGES)
    assert not mypy.get("disable_error_code") and not mypy.get("ignore_errors")
    let_off = [(module, override.get("disable_error_code"), override.get("ignore_errors"))
               for override in mypy.get("overrides", []) for module in _modules(override)
               if _is_project_module(module) and (override.get("disable_error_code") or override.get("ignore_errors"))]
    assert let_off == [], f"project modules let off error codes in [[tool.mypy.overrides]]: {let_off}"
    assert "mypy" in (ROOT / ".ci" / "run").read_text()


def test_override_check_sees_a_disabled_error_code() -> None:
    """The check above catches both spellings of ``module`` and package-wide patterns."""
    assert _modules({"module": "slam_engine.frontend.grid"}) == ["slam_engine.frontend.grid"]
    assert _modules({"module": ["service.api", "numba.*"]}) == ["service.api", "numba.*"]
    assert _is_project_module("slam_engine.formats.carmen")
    assert _is_project_module("service.*")
    assert _is_project_module("api_schemas")
    assert not _is_project_module("numba.*")
    assert not _is_project_module("slam_engine_extras.x")
