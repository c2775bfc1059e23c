"""``lidarmap config``: the SLAM settings a config file (``--config``) or a job (``slam``) can set."""

from __future__ import annotations

import json

import typer


def register(app: typer.Typer) -> None:
    @app.command()
    def config(
        schema: bool = typer.Option(False, "--schema", help="Print the JSON Schema of SlamConfig instead."),
    ) -> None:
        """Print the default SLAM configuration as YAML, each setting with its meaning, units and bounds
        (a valid config file as it stands)."""
        from slam_engine.config import SlamConfig, defaults_yaml

        if schema:
            typer.echo(json.dumps(SlamConfig.model_json_schema(), indent=2))
            return
        typer.echo(defaults_yaml(), nl=False)
