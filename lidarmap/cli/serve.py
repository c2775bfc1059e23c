"""``lidarmap serve``: run the HTTP service with uvicorn."""

from __future__ import annotations

import typer


def register(app: typer.Typer) -> None:
    @app.command()
    def serve(
        host: str = typer.Option("127.0.0.1", help="Address to listen on."),
        port: int = typer.Option(8000, min=1, max=65535, help="TCP port."),
    ) -> None:
        """Start the mapping service (embedded defaults: SQLite, local disk, local workers)."""
        import uvicorn

        from service.api.app import create_app

        uvicorn.run(create_app(), host=host, port=port)
