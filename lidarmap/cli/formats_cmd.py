"""``lidarmap formats``: the drive-log formats lidarmap reads and writes, and their schemas."""

from __future__ import annotations

import json

import typer


def register(app: typer.Typer) -> None:
    @app.command()
    def formats(
        schema: bool = typer.Option(False, "--schema", help="Print the JSON Schemas of the drivelog manifest "
                                                            "and message chunks instead."),
    ) -> None:
        """List the drive-log formats lidarmap reads and writes."""
        if schema:
            from api_schemas.drivelog import json_schemas

            typer.echo(json.dumps(json_schemas(), indent=2))
            return
        from slam_engine.formats import list_formats

        for info in list_formats():
            mode = "read/write" if info.can_write else "read"
            typer.echo(f"{info.name:12s} {mode:10s} {info.description}")
