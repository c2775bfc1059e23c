"""``lidarmap bench``: the accuracy and speed benchmark (the ``bench`` package, installed with lidarmap)."""

from __future__ import annotations

import typer


def register(app: typer.Typer) -> None:
    from bench.cli import accuracy

    app.command(name="bench")(accuracy)
