"""``lidarmap worker``: run SLAM jobs from the Celery broker (deployments with LIDARMAP_RUNNER=celery).

A thin wrapper over the Celery worker with the project's settings: the broker
(``LIDARMAP_BROKER_URL``), the job store (``LIDARMAP_DATABASE_URL`` or the SQLite file in
``LIDARMAP_DATA_DIR``) and the data folder must be the ones the API uses.
"""

from __future__ import annotations

import os

import typer


def register(app: typer.Typer) -> None:
    @app.command()
    def worker(
        concurrency: int = typer.Option(1, min=1, max=256, help="Jobs run at once (one pool process each)."),
        queue: str | None = typer.Option(None, help="Queue to consume (default LIDARMAP_QUEUE, 'lidarmap')."),
        loglevel: str = typer.Option("info", help="debug, info, warning or error."),
        hostname: str | None = typer.Option(None, help="Worker node name (default celery@<host>)."),
        job_function: str | None = typer.Option(None, hidden=True, help="Job function module:function (tests)."),
    ) -> None:
        """Run mapping jobs sent by the API through the broker (scale out with more workers)."""
        from service.runners.celery_runner import make_celery
        from service.settings import get_settings
        from service.storage.data_dir import DataDir
        from service.storage.store import open_store

        if loglevel.lower() not in ("debug", "info", "warning", "error"):
            raise typer.BadParameter(f"unknown log level {loglevel!r}", param_hint="--loglevel")
        # Share the cores between the pool processes (each SLAM run is multi-threaded) unless told otherwise.
        os.environ.setdefault("LIDARMAP_THREADS", str(max(1, (os.cpu_count() or 1) // concurrency)))
        settings = get_settings()
        data = DataDir(settings.data_dir)
        data.create()
        open_store(settings.database_url, data.database).initialise()
        celery = make_celery(settings, job_function, concurrency)
        argv = ["worker", f"--concurrency={concurrency}", f"--queues={queue or settings.queue}",
                f"--loglevel={loglevel.upper()}", "--pool=prefork", "--without-gossip", "--without-mingle"]
        if hostname:
            argv.append(f"--hostname={hostname}")
        celery.worker_main(argv)
