"""Lazy re-exports for the engine's packages: ``from slam_engine import run_slam`` imports the
pipeline only when the name is first read, so importing one small module (``slam_engine.model.poses``)
never loads the whole engine, and packages can re-export modules that import each other."""

from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import Any


def lazy_exports(exports: dict[str, str]) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """``__getattr__`` and ``__dir__`` for a package that exports ``name -> module`` lazily."""

    def getattr_(name: str) -> Any:
        if name not in exports:
            raise AttributeError(name)
        return getattr(importlib.import_module(exports[name]), name)

    def dir_() -> list[str]:
        return sorted(exports)

    return getattr_, dir_
