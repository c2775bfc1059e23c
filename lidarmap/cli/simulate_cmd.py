"""``lidarmap simulate``: write a simulated drive with exact ground truth as a log of any format."""

from __future__ import annotations

from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    @app.command()
    def simulate(
        format: str = typer.Option(..., "--format", help="Log format to write (see `lidarmap formats`)."),
        out: Path = typer.Option(..., "--out", help="Folder to create (must be new or empty)."),
        seed: int = typer.Option(0, help="Random seed: same seed, same drive."),
        scenario: str | None = typer.Option(None, help="office, office-changed (the office days later, "
                                             "with changes.json: what changed), office-north, campus, or a made-up "
                                             "office floor building-N / building-N-back (N 1-99; -back: driven the "
                                             "other way round) (default: the vehicle's own)."),
        duration: float | None = typer.Option(None, help="Stop the drive after this many seconds."),
        cameras: bool = typer.Option(True, help="Render the vehicle's cameras (the car's stereo pair, "
                                     "THOR's Kinect) from the floor texture; about a second per frame."),
    ) -> None:
        """Simulate a drive with exact ground truth and write it as a log, with ground_truth.txt and
        a .relations file (and ground_texture.json when cameras were rendered)."""
        from slam_engine.errors import SlamEngineError
        from slam_engine.simulation import rig_for_format, write_simulated
        from slam_engine.simulation import simulate as simulate_drive

        try:
            if out.exists() and (not out.is_dir() or any(out.iterdir())):
                raise SlamEngineError(f"{out}: output folder exists and is not empty")
            drive = simulate_drive(scenario=scenario, seed=seed, rig=rig_for_format(format), max_duration_s=duration,
                                  cameras=cameras)
            out.mkdir(parents=True, exist_ok=True)
            path = write_simulated(drive, format, out)
        except SlamEngineError as error:
            typer.echo(f"error: {error}", err=True)
            raise typer.Exit(2) from None
        streams = ", ".join(f"{n} {c}" for n, c in drive.log.streams().items())
        typer.echo(f"wrote {format} log {path} ({drive.scenario}, {drive.motion.duration_s:.0f} s, {streams}); "
                   f"ground truth in {out / 'ground_truth.txt'}, relations in {out / (drive.scenario + '.relations')}")
