"""The ``lidarmap`` command line: one typer app, one module per command group."""

from __future__ import annotations

import typer

from service.cli import bench_cmd, formats_cmd, serve

app = typer.Typer(name="lidarmap", help="Maps from drive logs with particle-filter SLAM.",
                  no_args_is_help=True, pretty_exceptions_enable=False, add_completion=False)
serve.register(app)
formats_cmd.register(app)
bench_cmd.register(app)


def main() -> None:
    """Console-script entry point."""
    app()
