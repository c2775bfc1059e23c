"""The ``lidarmap`` command line: one typer app, one module per command group."""

from __future__ import annotations

import typer

from service.cli import bench_cmd, config_cmd, evaluate_cmd, formats_cmd, run_cmd, serve, submit_cmd, worker_cmd

app = typer.Typer(name="lidarmap", help="Maps from drive logs with particle-filter SLAM.",
                  no_args_is_help=True, pretty_exceptions_enable=False, add_completion=False,
                  rich_markup_mode=None)


def _print_version(value: bool) -> None:
    if value:
        typer.echo(f"lidarmap {package_version()}")
        raise typer.Exit()


def package_version() -> str:
    """The installed distribution's version (the source tree's when it is not installed)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("lidarmap")
    except PackageNotFoundError:
        from slam_engine import __version__

        return __version__


@app.callback()
def _root(
    version: bool = typer.Option(False, "--version", callback=_print_version, is_eager=True,
                                 help="Print the version and exit."),
) -> None:
    """lidarmap: occupancy grids, texture maps and trajectories from drive logs."""


serve.register(app)
run_cmd.register(app)
submit_cmd.register(app)
evaluate_cmd.register(app)
config_cmd.register(app)
formats_cmd.register(app)
bench_cmd.register(app)
worker_cmd.register(app)


def main() -> None:
    """Console-script entry point."""
    app()
