"""What the bench's commands share: seeds, SlamConfig overrides from a file, the console for tables
(apart from :mod:`bench.cli`, which runs the tables that import these: no import cycle)."""

from __future__ import annotations

from pathlib import Path

import typer

SEEDS_HELP = "Seeds to run, e.g. '0-4' or '0,3,7'."


def parse_seeds(text: str) -> list[int]:
    """'0-4' -> [0, 1, 2, 3, 4]; '0,3,7' -> [0, 3, 7]; ranges and lists can be mixed."""
    seeds: list[int] = []
    for part in filter(None, (p.strip() for p in text.split(","))):
        first, dash, last = part.partition("-")
        try:
            seeds.extend(range(int(first), int(last) + 1) if dash else [int(first)])
        except ValueError:
            raise typer.BadParameter(f"{part!r} is not a seed or a range like 0-4") from None
    if not seeds:
        raise typer.BadParameter("no seeds given")
    return seeds


def read_overrides(config: Path | None) -> dict:
    """The SlamConfig overrides in ``config`` (YAML/JSON), none without one; a bad file is a usage error."""
    from slam_engine.config import read_settings
    from slam_engine.errors import ConfigError

    try:
        return read_settings(config) if config is not None else {}
    except ConfigError as error:
        raise typer.BadParameter(str(error)) from None


def report_console():
    """A rich console for the tables: files and pipes get the whole table, not an 80-column squeeze."""
    from rich.console import Console

    console = Console()
    return console if console.is_terminal else Console(width=200)
