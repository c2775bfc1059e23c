"""``python -m bench [SUBCOMMAND] ...``: ``accuracy`` (the default) runs the SLAM benchmark;
``throughput`` measures jobs per minute through the Celery runner; ``sessions`` localises, extends and
merges maps on the two-session drives; ``margin`` maps the sparse logs at 15 particles over ten seeds;
``live`` streams the simulated car at real time into a live job."""

from __future__ import annotations

import sys

import typer

from bench.cli import accuracy
from bench.live import live
from bench.margin import margin
from bench.sessions import sessions
from bench.throughput import throughput

SUBCOMMANDS = {"accuracy": accuracy, "throughput": throughput, "sessions": sessions, "margin": margin,
               "live": live}


def main(argv: list[str]) -> None:
    name = argv[0] if argv and argv[0] in SUBCOMMANDS else "accuracy"
    rest = argv[1:] if argv and argv[0] in SUBCOMMANDS else argv
    app = typer.Typer(add_completion=False, pretty_exceptions_enable=False)
    app.command(name=name)(SUBCOMMANDS[name])
    app(args=rest, prog_name=f"python -m bench {name}" if name != "accuracy" else "python -m bench")


if __name__ == "__main__":
    main(sys.argv[1:])
