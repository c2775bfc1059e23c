"""``lidarmap submit LOG --server URL --out DIR``: map a log on a running service (lidarmap.client)
and download every product, with a progress bar."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import typer

from lidarmap.cli.bad_input import BAD_INPUT_EXIT_CODE, one_line
from lidarmap.cli.run_cmd import prepare_out_dir, print_warnings
from slam_engine.errors import ConfigError, SlamEngineError

JOB_FAILED_EXIT_CODE = 1
CHUNK_S = 0.5  # --live: each chunk holds this much of the log's time [s]
REPORT_EVERY = 50  # --live localize: a line every this many scans, and at every change of state


class _Done(Exception):
    """The live branch's outcome, handed to the common end of ``submit``."""

    def __init__(self, job: Any, written: dict[str, Path]):
        self.job, self.written = job, written


def stream_live(api: Any, log_path: Path, format: str, settings: Any, rate: float, reader: Any) -> Any:
    """``log_path`` sent as a robot streams it into a new session's live job (``settings``): its messages
    in chunks of ``CHUNK_S`` of log time, each sent when ``rate`` times its time has passed (0: at once);
    a localisation's poses printed as they come (stdout), read by a second client (``reader()`` makes
    it). Returns the job once the stream is finished."""
    import threading

    from service.storage.stream_log import calibration_from_log, messages_of_log
    from slam_engine.formats import load_log

    drive = load_log(log_path, format)
    messages = messages_of_log(drive)
    if not messages:
        raise ConfigError(f"{log_path}: the log has no messages to stream")
    session = api.create_session(log_path.name[:200] or "log", calibration=calibration_from_log(drive))
    job = api.start_job(session.id, settings)
    typer.echo(f"live job {job.id} ({settings.mode.value}) on session {session.id}: streaming {len(messages)} "
               f"messages", err=True)
    follower = None
    if settings.mode.value == "localize":
        follower = threading.Thread(target=_print_poses, args=(reader, job.id), daemon=True)
        follower.start()
    t0, started = messages[0]["t_s"], time.monotonic()
    chunk: list[dict[str, Any]] = []
    seq = 0
    for message in [*messages, None]:
        if chunk and (message is None or message["t_s"] - chunk[0]["t_s"] >= CHUNK_S or len(chunk) >= 10_000):
            if rate > 0:
                time.sleep(max(0.0, (chunk[-1]["t_s"] - t0) / rate - (time.monotonic() - started)))
            api.send_chunk(session.id, seq, chunk)
            seq, chunk = seq + 1, []
        if message is not None:
            chunk.append(message)
    api.finish_stream(session.id, seq - 1)
    if follower is not None:
        follower.join()
    return job


def _print_poses(reader: Any, job_id: str) -> None:
    """A live localisation's stages until it is ready on stderr (``loading the map``, then ``localising
    scans``), then its poses on stdout: a line at each change of state and every REPORT_EVERY scans."""
    with reader() as api:
        _print_stages(api, job_id)
        _print_each(api.follow_poses(job_id))


def _print_stages(api: Any, job_id: str, poll_s: float = 0.1) -> None:
    """The job's stage on stderr each time it changes, until it is past loading its map (or ended)."""
    from api_schemas import LOADING_MAP_STAGE, JobStatus

    shown = None
    while True:
        job = api.job(job_id)
        if job.stage and job.stage != shown:
            typer.echo(f"job {job_id}: {job.stage}", err=True)
            shown = job.stage
        if job.status not in (JobStatus.QUEUED, JobStatus.RUNNING) or (job.stage and job.stage != LOADING_MAP_STAGE):
            return
        time.sleep(poll_s)


def _print_each(reports: Any) -> None:
    state = None
    for report in reports:
        if report["state"] != state or report["scan"] % REPORT_EVERY == 0:
            state = report["state"]
            pose = report["pose"]
            where = "" if pose is None else f" at x {pose[0]:.2f} m, y {pose[1]:.2f} m, theta {pose[2]:.3f} rad"
            latency = report.get("latency_s")
            typer.echo(f"scan {report['scan']} t {report['t_s']:.2f} s: {state}{where}, confidence "
                       f"{report['confidence']:.2f}" + ("" if latency is None else f", {1000 * latency:.0f} ms"))


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
        live: bool = typer.Option(False, "--live", help="Send the log as a robot streams: its messages in chunks "
                                  "at --rate times their own pace, into a live job that maps them as they come "
                                  "or, with --mode localize --map-job JOB, localises each scan in that map "
                                  "(each pose printed as the service makes it)."),
        rate: float = typer.Option(1.0, min=0.0, max=1000.0, help="With --live: this many times the log's own "
                                   "pace (0: as fast as the service takes the chunks)."),
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
        if live:
            try:
                settings = JobCreate(**{k: v for k, v in given.items() if v is not None}, mode=mode,
                                     map_job_id=map_job, live=True)
            except ValidationError as error:
                raise fail(one_line(error)) from None
        try:
            with LidarmapClient(server, api_key=api_key) as api:
                if live:
                    job = stream_live(api, log, format, settings, rate, lambda: LidarmapClient(server, api_key=api_key))
                    job = api.wait(job.id, timeout_s=timeout)
                    if job.status is not JobStatus.SUCCEEDED:
                        raise fail(f"job {job.id} {job.status.value}: {job.error}", JOB_FAILED_EXIT_CODE)
                    written = api.download_products(job.id, out)
                    raise _Done(job, written)
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
        except SlamEngineError as error:  # the log, read here to be streamed
            raise fail(str(error)) from None
        except _Done as done:
            job, written = done.job, done.written
        for _name, path in sorted(written.items()):
            typer.echo(f"{path}  {path.stat().st_size:,} bytes")
        typer.echo(f"job {job.id}: {job.scans_done} scans, {len(written)} products in {out}")
        if "run.json" in written:
            print_warnings(written["run.json"])
