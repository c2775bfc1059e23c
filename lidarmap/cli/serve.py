"""``lidarmap serve``: run the HTTP service with uvicorn."""

from __future__ import annotations

import copy
import ipaddress
import signal
import sys
from types import FrameType
from typing import Any

import typer

LOOPBACK_NAMES = ("localhost",)


def is_loopback(host: str) -> bool:
    """Whether ``host`` (an address or ``localhost``) is reachable from this machine only."""
    if host in LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False  # a host name: it may resolve to any interface


def open_without_key_warning(host: str, api_keys: list[str]) -> str | None:
    """The warning for a service listening beyond this machine without API keys (None: no warning)."""
    if is_loopback(host) or api_keys:
        return None
    return (f"warning: listening on {host} without API keys: anyone who reaches this port can upload logs and "
            "run jobs (set LIDARMAP_API_KEYS, or listen on 127.0.0.1)")


def log_config() -> dict[str, Any]:
    """uvicorn's logging set-up, plus the service's own loggers (``lidarmap.*``: job lifecycle, runner,
    workers) at INFO on stderr in uvicorn's format."""
    from uvicorn.config import LOGGING_CONFIG

    config = copy.deepcopy(LOGGING_CONFIG)
    config["loggers"]["lidarmap"] = {"handlers": ["default"], "level": "INFO", "propagate": False}
    return config


def exit_normally_on_sigterm() -> None:
    """After uvicorn's graceful shutdown on SIGTERM (``docker stop``, systemd), leave through a normal
    interpreter exit with status 0 instead of dying by the signal: exit handlers run, so the worker pool's
    queues release their semaphores (no "leaked semaphore objects" from the resource tracker). uvicorn
    catches SIGTERM while it serves and raises it again, to this handler, once the app has shut down."""

    def stop(signum: int, frame: FrameType | None) -> None:
        sys.exit(0)

    signal.signal(signal.SIGTERM, stop)


def register(app: typer.Typer) -> None:
    @app.command()
    def serve(
        host: str = typer.Option("127.0.0.1", help="Address to listen on."),
        port: int = typer.Option(8000, min=1, max=65535, help="TCP port."),
    ) -> None:
        """Start the mapping service (embedded defaults: SQLite, local disk, local workers)."""
        from service.api.app import create_app
        from service.api.server import serve as run_server
        from service.settings import get_settings

        settings = get_settings()
        warning = open_without_key_warning(host, settings.api_key_list())
        if warning:
            typer.echo(warning, err=True)
        exit_normally_on_sigterm()
        run_server(create_app(settings), host=host, port=port, max_head_bytes=settings.max_header_bytes,
                   log_config=log_config())
