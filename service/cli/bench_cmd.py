"""``lidarmap bench``: the accuracy and speed benchmark (``bench/`` in a source checkout)."""

from __future__ import annotations

import typer


def register(app: typer.Typer) -> None:
    try:
        from bench.cli import accuracy
    except ModuleNotFoundError as error:
        if error.name != "bench":
            raise

        @app.command(name="bench", context_settings={"allow_extra_args": True, "ignore_unknown_options": True})
        def bench_unavailable() -> None:
            """Accuracy and speed benchmark (runs from a source checkout only)."""
            typer.echo("lidarmap bench needs the bench/ folder of a source checkout; it is not installed here",
                       err=True)
            raise typer.Exit(2)

        return
    app.command(name="bench")(accuracy)
