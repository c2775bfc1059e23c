"""The type checker's configuration: mypy covers the engine, the schemas and the whole service, and
no service module is let off any error code (.ci/run runs mypy; this guards the configuration)."""

from __future__ import annotations

import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_mypy_checks_every_service_module_in_full() -> None:
    mypy = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["mypy"]
    assert set(mypy["packages"]) >= {"slam_engine", "api_schemas", "service"}
    let_off = [module for override in mypy.get("overrides", []) for module in override["module"]
               if override.get("disable_error_code") or override.get("ignore_errors")]
    assert [m for m in let_off if m.split(".")[0] in ("service", "api_schemas")] == []
    assert "mypy" in (ROOT / ".ci" / "run").read_text()
