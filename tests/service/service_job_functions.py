"""Tiny job functions injected into the worker processes by the lifecycle tests (imported by name
in the spawned workers). ``particles`` sets the number of steps, ``seed`` the step time in ms."""

from __future__ import annotations

import json
import time

from service.jobs.settings import engine_config
from slam_engine.errors import LogFormatError


def counting(ctx) -> None:
    """``particles`` steps of ``seed`` ms, reporting progress; writes run.json."""
    config = engine_config(ctx.job.config)
    steps, step_s = config.particles, config.seed / 1000.0
    for i in range(steps):
        ctx.progress(i, steps)
        time.sleep(step_s)
    ctx.progress(steps, steps, force=True)
    (ctx.out_dir / "run.json").write_text(json.dumps({"steps": steps}))
    ctx.store.set_products(ctx.job_id, {"run.json": "run.json"})


def stubborn(ctx) -> None:
    """Never checks for a cancel."""
    ctx.progress(0, 10, force=True)
    time.sleep(60)


def bad_log(ctx) -> None:
    raise LogFormatError("range count 179 does not match 180 beams", path="/secret/server/path", location="line 3")


def buggy(ctx) -> None:
    raise ZeroDivisionError("division by zero")


def compiling(ctx) -> None:
    """Reports a numba compilation (the engine's event, as a real compile sends it) until the test
    writes ``release`` into the data folder (at most 30 s), then counts like :func:`counting`."""
    from numba.core import event

    from service.jobs.mapping import compiling_status

    release = ctx.data.root / "release"
    with compiling_status(ctx):
        ctx.progress(1, 10, force=True)  # as the first scan of a real run, before a kernel compiles
        event.start_event("numba:compile", data={})
        deadline = time.monotonic() + 30.0
        while not release.exists() and time.monotonic() < deadline:
            time.sleep(0.02)
        event.end_event("numba:compile", data={})
        counting(ctx)


def live_writer(ctx) -> None:
    """Like the mapping job with ``snapshot_every_scans: 1``: a live file after every step of ``seed``
    ms (``particles`` steps), cancel checked through the throttled progress; ``linear_update_m`` > 0:
    never checks for a cancel."""
    config = engine_config(ctx.job.config)
    for i in range(config.particles):
        live = ctx.data.live_dir(ctx.job_id)
        live.mkdir(parents=True, exist_ok=True)
        (live / "frame.json").write_text(json.dumps({"step": i}))
        if not config.scheduling.linear_update_m:
            ctx.progress(i, config.particles)
        time.sleep(config.seed / 1000.0)


def late_writer(ctx) -> None:
    """Runs until the test writes ``release`` into the data folder (at most 30 s, never checking for a
    cancel), then writes its product and lists it, as a worker that lost its job would."""
    ctx.progress(1, 2, force=True)
    release = ctx.data.root / "release"
    deadline = time.monotonic() + 30.0
    while not release.exists() and time.monotonic() < deadline:
        time.sleep(0.02)
    (ctx.out_dir / "run.json").write_text(json.dumps({"steps": 2}))
    ctx.store.set_products(ctx.job_id, {"run.json": "run.json"})


HOARD_MB = 200
_hoard: list = []  # what a job leaves behind in its worker (as a run's caches and heap do)


def hoarding(ctx) -> None:
    """Leaves HOARD_MB of touched memory behind in the worker process, then succeeds."""
    _hoard.append(bytearray(b"\x01" * (HOARD_MB * 1024 * 1024)))
    ctx.progress(1, 1, force=True)


def disk_full_writer(ctx) -> None:
    """Fails as writing a product on a full disk does (ENOSPC from the file system)."""
    import errno

    ctx.progress(1, 2, force=True)
    live = ctx.data.live_dir(ctx.job_id)  # a live snapshot written before the disk filled
    live.mkdir(parents=True, exist_ok=True)
    (live / "occupancy.png").write_bytes(b"\x89PNG" + b"\0" * 100_000)
    raise OSError(errno.ENOSPC, "No space left on device", str(ctx.out_dir / "products" / "occupancy.png"))


def _refuse_while(ctx, refused) -> None:
    """Make this worker's store writes of this job's outcome raise SQLite's full-disk error while
    ``refused()`` holds (other jobs' writes go through)."""
    import sqlite3

    store_class = type(ctx.store)
    finish, job_id = store_class.finish, ctx.job_id

    def refusing_finish(store, job, *args, **kwargs):
        if job == job_id and refused():
            raise sqlite3.OperationalError("database or disk is full")
        return finish(store, job, *args, **kwargs)

    store_class.finish = refusing_finish


def store_full(ctx) -> None:
    """A progress write meets a full disk, and so does every write of the job's outcome in this worker
    (as a database on a full disk: the worker's own writes all fail)."""
    import sqlite3

    ctx.progress(1, 2, force=True)
    _refuse_while(ctx, lambda: True)
    raise sqlite3.OperationalError("database or disk is full")


def store_full_but_spare(ctx) -> None:
    """As :func:`store_full`, but the outcome's write fits once the data folder's spare file is gone
    (a disk that another writer keeps full)."""
    import sqlite3

    ctx.progress(1, 2, force=True)
    _refuse_while(ctx, ctx.data.spare.exists)
    raise sqlite3.OperationalError("database or disk is full")


def fills_the_disk(ctx) -> None:
    """Fills the data folder's file system (as another writer would: a file outside the job's
    folders), then reports progress and writes its product, as a job does."""
    ctx.progress(1, 3, force=True)
    with open(ctx.data.root / "filler", "wb", buffering=0) as out:
        try:
            while True:
                out.write(b"\0" * 4096)
        except OSError:
            pass
    ctx.progress(2, 3, force=True)
    (ctx.out_dir / "run.json").write_text(json.dumps({"steps": 3}) + " " * 1_000_000)


def map_index_held(ctx) -> None:
    """The service's own job function, with a live localisation's map index built only once the test writes
    ``release`` into the data folder (at most 60 s later): its time loading the map, as long as a test needs."""
    from service.jobs.mapping import run_mapping_job
    from slam_engine.multisession.localization import MapIndex

    built = MapIndex.__dict__["of_bundle"]

    def held(cls, *args, **kwargs):
        deadline = time.monotonic() + 60.0
        while not (ctx.data.root / "release").exists() and time.monotonic() < deadline:
            time.sleep(0.02)
        return built.__func__(cls, *args, **kwargs)

    MapIndex.of_bundle = classmethod(held)
    try:
        run_mapping_job(ctx)
    finally:
        MapIndex.of_bundle = built


def placement_held_to_the_end(ctx) -> None:
    """The service's own job function, with a live localisation's background search that places the drive
    taken only when the stream has ended (``LiveLocalizer.wait``), not with the next scan: the stream ends
    right after the search delivered, whenever that was."""
    from service.jobs.mapping import run_mapping_job
    from slam_engine.multisession.live_localization import LiveLocalizer

    add = LiveLocalizer.add

    def held_add(self, *args):
        search = self._search
        if search is None or not search.done() or search.result() is None:
            return add(self, *args)
        self._take_search = lambda: None  # held (no other search starts meanwhile)
        try:
            return add(self, *args)
        finally:
            del self._take_search

    LiveLocalizer.add = held_add
    try:
        run_mapping_job(ctx)
    finally:
        LiveLocalizer.add = add
