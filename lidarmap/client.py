"""A small typed Python client of the lidarmap HTTP API (httpx + the ``api_schemas`` models).

    with LidarmapClient("http://127.0.0.1:8000") as api:
        session = api.create_session("intel")
        api.upload_log(session.id, Path("intel.clf"))
        job = api.start_job(session.id, JobCreate(particles=30))
        job = api.wait(job.id, on_progress=lambda j: print(j.scans_done, j.scans_total))
        api.download_products(job.id, Path("out/intel"))

Every API error (4xx/5xx) raises :class:`ApiError` with the service's status, code and message.
"""

from __future__ import annotations

import json
import shutil
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Literal

import httpx

from api_schemas.chunks import ChunkCreate, ChunkPublic, StreamState
from api_schemas.jobs import JobCreate, JobPublic, JobStatus
from api_schemas.logs import LogPublic
from api_schemas.products import TrajectoryPublic
from api_schemas.sessions import SessionCreate, SessionPublic
from api_schemas.tiles import TileSchemePublic

FINISHED = frozenset({JobStatus.SUCCEEDED, JobStatus.FAILED, JobStatus.CANCELLED})
TIMEOUT_S = 60.0  # per request (connect, read, write); uploads and downloads stream
MAX_POLL_INTERVAL_S = 10.0


class ApiError(Exception):
    """The service answered with an error: HTTP ``status``, its ``code`` and ``message``."""

    def __init__(self, status: int, code: str, message: str, detail: Any = None):
        super().__init__(f"{status} {code}: {message}")
        self.status, self.code, self.message, self.detail = status, code, message, detail


class LidarmapClient:
    """One connection pool to a lidarmap service at ``base_url`` (e.g. ``http://127.0.0.1:8000``)."""

    def __init__(self, base_url: str, api_key: str | None = None, timeout_s: float = TIMEOUT_S,
                 transport: httpx.BaseTransport | None = None):
        headers = {"X-API-Key": api_key} if api_key else {}
        self._http = httpx.Client(base_url=base_url.rstrip("/"), headers=headers, timeout=timeout_s,
                                  transport=transport)

    def __enter__(self) -> LidarmapClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._http.close()

    # --- sessions, uploads, jobs ------------------------------------------------------------------

    def create_session(self, name: str, **fields: Any) -> SessionPublic:
        """A new session; ``fields``: the other SessionCreate fields (calibration, geo, vehicle_preset)."""
        body = SessionCreate(name=name, **fields).model_dump(mode="json", exclude_none=True)
        return SessionPublic.model_validate(self._json("POST", "/v1/sessions", json=body))

    def upload_log(self, session_id: str, path: Path, format: str = "auto") -> LogPublic:
        """Upload a drive log file; a folder (a folder format) is sent as a zip of its contents."""
        path = Path(path)
        with _as_upload_file(path) as (upload, filename), upload.open("rb") as stream:
            answer = self._json("POST", f"/v1/sessions/{session_id}/logs", params={"format": format},
                                files={"file": (filename, stream, "application/octet-stream")})
        return LogPublic.model_validate(answer)

    def upload_map(self, session_id: str, path: Path) -> JobPublic:
        """Upload a saved map (a run's ``map_bundle.npz``, or the run's folder holding one): a finished job
        whose id a 'localize' or 'extend' job names as ``map_job_id``."""
        path = Path(path)
        if path.is_dir():
            path = path / "map_bundle.npz"
        with path.open("rb") as stream:
            answer = self._json("POST", f"/v1/sessions/{session_id}/maps",
                                files={"file": (path.name, stream, "application/octet-stream")})
        return JobPublic.model_validate(answer)

    def start_job(self, session_id: str, settings: JobCreate | None = None) -> JobPublic:
        """Queue a mapping job on the session (defaults: the newest upload, default settings)."""
        body = (settings or JobCreate()).model_dump(mode="json", exclude_unset=True)
        return JobPublic.model_validate(self._json("POST", f"/v1/sessions/{session_id}/jobs", json=body))

    def job(self, job_id: str, include_config: bool = False) -> JobPublic:
        """The job's status; its settings (``config``) too with ``include_config``."""
        params = {"include": "config"} if include_config else None
        return JobPublic.model_validate(self._json("GET", f"/v1/jobs/{job_id}", params=params))

    def cancel(self, job_id: str) -> JobPublic:
        return JobPublic.model_validate(self._json("DELETE", f"/v1/jobs/{job_id}"))

    def wait(self, job_id: str, on_progress: Callable[[JobPublic], None] | None = None, poll_s: float = 0.5,
             timeout_s: float | None = None) -> JobPublic:
        """Poll the job until it is succeeded, failed or cancelled; ``on_progress`` sees every poll.
        The interval grows from ``poll_s`` to at most 10 s. TimeoutError after ``timeout_s`` [s]."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        interval = poll_s
        while True:
            job = self.job(job_id)
            if on_progress is not None:
                on_progress(job)
            if job.status in FINISHED:
                return job
            if deadline is not None and time.monotonic() + interval > deadline:
                raise TimeoutError(f"job {job_id} still {job.status} after {timeout_s} s")
            time.sleep(interval)
            interval = min(MAX_POLL_INTERVAL_S, interval * 1.2)

    # --- products ---------------------------------------------------------------------------------

    def download(self, job_id: str, name: str, destination: Path) -> Path:
        """Stream product ``name`` (as the job lists it, e.g. 'occupancy.png') into ``destination``
        (a file path, or a folder to put it in); written whole or not at all."""
        destination = Path(destination)
        target = destination / name if destination.is_dir() else destination
        partial = target.with_name(target.name + ".part")
        with self._http.stream("GET", f"/v1/jobs/{job_id}/{name}") as response:
            _raise_for_error(response)
            with partial.open("wb") as out:
                for block in response.iter_bytes():
                    out.write(block)
        partial.replace(target)
        return target

    def download_products(self, job_id: str, out_dir: Path) -> dict[str, Path]:
        """Every file product the job lists, into ``out_dir`` (created); {name: path}."""
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        job = self.job(job_id)
        return {name: self.download(job_id, name, out_dir / name)
                for name in job.products if not name.startswith("tiles/")}

    # --- streams and live jobs -------------------------------------------------------------------

    def send_chunk(self, session_id: str, seq: int, messages: list[dict[str, Any]]) -> ChunkPublic:
        """Post chunk ``seq`` of the session's stream (sensor messages in time order, as the API takes them)."""
        body = ChunkCreate.model_validate({"seq": seq, "messages": messages}).model_dump(mode="json",
                                                                                          exclude_none=True)
        return ChunkPublic.model_validate(self._json("POST", f"/v1/sessions/{session_id}/chunks", json=body))

    def finish_stream(self, session_id: str, last_seq: int | None = None) -> StreamState:
        """The session's stream ends at ``last_seq`` (default: the highest chunk sent)."""
        body = {} if last_seq is None else {"last_seq": last_seq}
        return StreamState.model_validate(self._json("POST", f"/v1/sessions/{session_id}/chunks/finish", json=body))

    def follow_poses(self, job_id: str, after: int = -1) -> Iterator[dict[str, Any]]:
        """A live localisation's scan reports as the service makes them (server-sent events; each a dict:
        ``scan``, ``t_s``, ``pose`` [x_m, y_m, theta_rad] or None, ``confidence``, ``state``, ``seq``,
        ``latency_s``; ``revised``: true on a scan reported again, found, as the stream ended), from the scan
        after ``after``, until the job ends. A dropped connection is taken up again after the last scan
        received."""
        last, revised = after, False
        while True:
            try:
                with self._http.stream("GET", f"/v1/jobs/{job_id}/poses", params={"stream": "true", "after": last},
                                       timeout=httpx.Timeout(TIMEOUT_S, read=None)) as response:
                    _raise_for_error(response)
                    event: dict[str, str] = {}
                    for line in response.iter_lines():
                        if line:
                            name, _, value = line.partition(": ")
                            if not line.startswith(":"):
                                event[name] = value
                            continue
                        if event.get("event") == "end":
                            return
                        if event.get("event") == "pose":
                            report = json.loads(event["data"])
                            if not (report.get("revised") and revised and report["scan"] == last):  # not twice
                                revised = bool(report.get("revised"))
                                last = report["scan"]
                                yield report
                        event = {}
            except httpx.TransportError:
                if self.job(job_id).status in FINISHED:
                    return
                time.sleep(0.5)

    def changes(self, job_id: str) -> dict:
        """What a localise or extend job's drive saw changed since the saved map: ``changes.geojson`` as a
        GeoJSON FeatureCollection (each feature's ``properties``: ``kind`` 'added' or 'removed', ``area_m2``);
        run.json's ``changes`` sums them up."""
        return self._json("GET", f"/v1/jobs/{job_id}/changes.geojson")

    def trajectory(self, job_id: str, kind: Literal["slam", "dead_reckoning"] = "slam") -> TrajectoryPublic:
        path = "trajectory" if kind == "slam" else "dead-reckoning"
        return TrajectoryPublic.model_validate(self._json("GET", f"/v1/jobs/{job_id}/{path}"))

    def tile_scheme(self, job_id: str, layer: Literal["occupancy", "texture"] = "occupancy") -> TileSchemePublic:
        return TileSchemePublic.model_validate(self._json("GET", f"/v1/jobs/{job_id}/tiles/{layer}"))

    def tile(self, job_id: str, z: int, x: int, y: int, layer: Literal["occupancy", "texture"] = "occupancy",
             scheme: Literal["simple", "webmercator"] = "simple") -> bytes:
        """One 256x256 PNG map tile."""
        response = self._http.get(f"/v1/jobs/{job_id}/tiles/{layer}/{z}/{x}/{y}.png", params={"scheme": scheme})
        _raise_for_error(response)
        return response.content

    def _json(self, method: str, url: str, **kwargs: Any) -> Any:
        response = self._http.request(method, url, **kwargs)
        _raise_for_error(response)
        return response.json()


def _raise_for_error(response: httpx.Response) -> None:
    if response.is_success:
        return
    response.read()
    try:
        error = response.json()["error"]
        code, message, detail = str(error["code"]), str(error["message"]), error.get("detail")
    except (ValueError, KeyError, TypeError):
        code, message, detail = "http_error", response.text[:500] or response.reason_phrase, None
    raise ApiError(response.status_code, code, message, detail)


@contextmanager
def _as_upload_file(path: Path) -> Iterator[tuple[Path, str]]:
    """The file to send and its name: the file itself, or a temporary zip of a folder."""
    if not path.is_dir():
        yield path, path.name
        return
    with tempfile.TemporaryDirectory(prefix="lidarmap-upload-") as tmp:
        archive = shutil.make_archive(str(Path(tmp) / path.name), "zip", root_dir=path)
        yield Path(archive), f"{path.name}.zip"
