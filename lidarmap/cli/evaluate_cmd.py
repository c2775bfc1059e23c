"""``lidarmap evaluate TRAJECTORY --relations R [--ground-truth G]``: accuracy of a trajectory.

Trajectories: lidarmap JSON, TUM, or ``t x y theta`` text (the benchmark's ground-truth format).
Prints the relation errors (all / local / loop) and the absolute trajectory error; ``--json`` prints
the same figures as JSON.
"""

from __future__ import annotations

import json
from pathlib import Path

import typer

from lidarmap.cli.bad_input import bad_input_exits
from slam_engine.errors import ConfigError, LogFormatError


def read_any_trajectory(path: Path):
    """A trajectory in lidarmap JSON, TUM (8 columns) or ``t x y theta`` (4 columns)."""
    from slam_engine.evaluation.metrics import read_ground_truth
    from slam_engine.products import read_trajectory

    try:
        with open(path, encoding="utf-8") as handle:
            for line in handle:
                stripped = line.strip()
                if stripped and not stripped.startswith("#"):
                    if stripped[0] not in "{[" and len(stripped.split()) == 4:
                        return read_ground_truth(path)
                    break
        return read_trajectory(path)
    except UnicodeDecodeError as error:
        raise LogFormatError(f"not a text trajectory (byte {error.start} is not UTF-8)", path) from None


def register(app: typer.Typer) -> None:
    @app.command()
    def evaluate(
        trajectory: Path = typer.Argument(..., help="Estimated trajectory (lidarmap JSON, TUM or 't x y theta')."),
        relations: Path | None = typer.Option(None, help="Relations file 't1 t2 x y z roll pitch yaw'."),
        ground_truth: Path | None = typer.Option(None, "--ground-truth", help="Ground-truth trajectory "
                                                 "for the absolute trajectory error."),
        as_json: bool = typer.Option(False, "--json", help="Print the figures as JSON."),
        verbose: bool = typer.Option(False, "--verbose", "-v", help="Show tracebacks."),
    ) -> None:
        """Relation errors (mean +- std, translation m / rotation deg; all, local, loop) and ATE."""
        from slam_engine.products import accuracy_figures

        with bad_input_exits(verbose):
            if relations is None and ground_truth is None:
                raise ConfigError("nothing to compare with: give --relations and/or --ground-truth")
            estimate = read_any_trajectory(trajectory)
            truth = None if ground_truth is None else read_any_trajectory(ground_truth)
            figures = accuracy_figures(estimate, relations, truth) or {}  # None only with nothing to compare
            if figures.get("ate_error"):
                raise ConfigError(f"{trajectory} vs {ground_truth}: {figures['ate_error']}")
        if as_json:
            typer.echo(json.dumps(figures, indent=1))
            return
        for subset, stats in (figures.get("relations") or {}).items():
            if not isinstance(stats, dict):
                continue
            scored = stats["n_relations"] - stats["n_failed"]
            typer.echo(f"relations {subset:5s}: trans {_f(stats['trans_mean_m'], '.4f')} +- "
                       f"{_f(stats['trans_std_m'], '.4f')} m, rot {_f(stats['rot_mean_deg'], '.3f')} +- "
                       f"{_f(stats['rot_std_deg'], '.3f')} deg ({scored} scored, {stats['n_failed']} failed)")
        if figures.get("ate_m") is not None:
            typer.echo(f"ATE (rigid 2-D alignment): {figures['ate_m']:.4f} m")


def _f(value: float | None, spec: str) -> str:
    return "n/a" if value is None else format(value, spec)
