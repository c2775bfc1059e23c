"""The ``lidarmap`` command line: one typer app, one module per command group."""

from __future__ import annotations

import typer

from service.cli import bench_cmd, evaluate_cmd, formats_cmd, run_cmd, serve, worker_cmd

app = typer.Typer(name="lidarmap", help="Maps from drive logs with particle-filter SLAM.",
                  no_args_is_help=True, pretty_exceptions_enable=False, add_completion=False,
                  rich_markup_mode=None)


@app.callback()
def _root() -> None:
    """lidarmap: occupancy grids, texture maps and trajectories from drive logs."""


serve.register(app)
run_cmd.register(app)
evaluate_cmd.register(app)
formats_cmd.register(app)
bench_cmd.register(app)
worker_cmd.register(app)


def main() -> None:
    """Console-script entry point."""
    app()
