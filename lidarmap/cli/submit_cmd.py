"""``lidarmap submit LOG --server URL --out DIR``: map a log on a running service (lidarmap.client)
and download every product, with a progress bar."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import typer

from lidarmap.cli.bad_input import BAD_INPUT_EXIT_CODE, one_line
from lidarmap.cli.run_cmd import prepare_out_dir, print_warnings
from slam_engine.errors import ConfigError

JOB_FAILED_EXIT_CODE = 1


def register(app: typer.Typer) -> None:
    @app.command()
    def submit(
        log: Path = typer.Argument(..., metavar="LOG", help="Drive log: a file, or a folder (sent as a zip)."),
        server: str = typer.Option(..., "--server", "-s", envvar="LIDARMAP_SERVER",
                                   help="The service's base URL, e.g. http://127.0.0.1:8000."),
        out: Path = typer.Option(..., "--out", "-o", help="Folder for the products (created)."),
        particles: int | None = typer.Option(None, help="Number of particles (default: the service's)."),
        seed: int | None = typer.Option(None, help="Random seed."),
        resolution_m: float | None = typer.Option(None, "--resolution-m", "--resolution", help="Grid cell size [m]."),
        format: str = typer.Option("auto", "--format", "-f", help="Log format, or auto to detect it."),
        api_key: str | None = typer.Option(None, envvar="LIDARMAP_API_KEY", help="API key, when the service "
                                           "needs one."),
        mode: str = typer.Option("map", help="map, localize (in the saved map of --map-job; without it, in "
                                 "whichever saved map of the key the drive is in) or extend (that map)."),
        map_job: str | None = typer.Option(None, "--map-job", help="The finished job whose saved map a "
                                           "localize or extend job starts from."),
        timeout: float | None = typer.Option(None, min=1.0, help="Give up waiting after this long [s]."),
        force: bool = typer.Option(False, "--force", help="Write into an existing, non-empty --out folder."),
    ) -> None:
        """Upload a drive log to a running service, map it (or localise it in, or extend with it, the saved map
        of a finished job), wait with progress, download every product."""
        import httpx
        from pydantic import ValidationError
        from rich.console import Console
        from rich.progress import BarColumn, Progress, TaskProgressColumn, TextColumn, TimeRemainingColumn

        from api_schemas.jobs import JobCreate, JobPublic, JobStatus
        from lidarmap.client import ApiError, LidarmapClient
        from slam_engine.config import shortcut_overrides, validate_config

        def fail(message: str, code: int = BAD_INPUT_EXIT_CODE) -> typer.Exit:
            typer.echo(f"error: {' '.join(message.split())}", err=True)
            return typer.Exit(code)

        try:
            prepare_out_dir(out, force)
        except ConfigError as error:
            raise fail(str(error)) from None
        if not log.exists():
            raise fail(f"{log}: no such file or folder")
        given: dict[str, Any] = {"particles": particles, "seed": seed, "resolution_m": resolution_m}
        try:  # settings out of the engine's bounds fail here, before anything is uploaded
            settings = JobCreate(**{k: v for k, v in given.items() if v is not None}, mode=mode, map_job_id=map_job)
            validate_config(shortcut_overrides(given), "job settings")  # the engine's own bounds
        except ValidationError as error:
            raise fail(one_line(error)) from None
        except ConfigError as error:
            raise fail(str(error)) from None
        try:
            with LidarmapClient(server, api_key=api_key) as api:
                session = api.create_session(log.name[:200] or "log")
                uploaded = api.upload_log(session.id, log, format=format)
                typer.echo(f"uploaded {uploaded.filename} ({uploaded.summary.format}, "
                           f"{uploaded.summary.streams.get('scans', 0)} scans) to session {session.id}", err=True)
                job = api.start_job(session.id, settings)
                columns = (TextColumn("{task.description:<19}"), BarColumn(), TaskProgressColumn(),
                           TextColumn("{task.fields[scans]}"), TextColumn("ETA"), TimeRemainingColumn())
                with Progress(*columns, console=Console(stderr=True)) as bar:
                    task = bar.add_task("queued", total=1.0, scans="")

                    def show(state: JobPublic) -> None:  # the job's stage and share done (scans, back end, products)
                        scans = f"{state.scans_done}/{state.scans_total} scans" if state.scans_total else ""
                        done = 1.0 if state.status is JobStatus.SUCCEEDED else state.progress or 0.0
                        bar.update(task, completed=done, description=state.stage or state.status.value, scans=scans)

                    job = api.wait(job.id, on_progress=show, timeout_s=timeout)
                if job.status is not JobStatus.SUCCEEDED:
                    raise fail(f"job {job.id} {job.status.value}: {job.error}", JOB_FAILED_EXIT_CODE)
                written = api.download_products(job.id, out)
        except ApiError as error:
            where = error.detail.get("location") if isinstance(error.detail, dict) else None
            at = f" ({where})" if where and str(where) not in error.message else ""
            raise fail(f"{server}: {error.message}{at} (HTTP {error.status})") from None
        except httpx.HTTPError as error:
            raise fail(f"{server}: {error or type(error).__name__}") from None
        except TimeoutError as error:
            raise fail(str(error), JOB_FAILED_EXIT_CODE) from None
        for _name, path in sorted(written.items()):
            typer.echo(f"{path}  {path.stat().st_size:,} bytes")
        typer.echo(f"job {job.id}: {job.scans_done} scans, {len(written)} products in {out}")
        if "run.json" in written:
            print_warnings(written["run.json"])
