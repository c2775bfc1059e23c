"""/v1/jobs/{id}/...: a job's products (maps, trajectories, tiles, animation, run record)."""

from __future__ import annotations

import asyncio
import json
import os
import pathlib
import time
from enum import StrEnum
from functools import partial
from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter, Path, Query, Request
from fastapi.encoders import jsonable_encoder
from fastapi.responses import FileResponse, JSONResponse, Response, StreamingResponse
from starlette.concurrency import run_in_threadpool
from starlette.datastructures import Headers
from starlette.responses import MalformedRangeHeader, RangeNotSatisfiable
from starlette.types import Receive, Scope, Send

from api_schemas.error_body import ErrorResponse
from api_schemas.jobs import JobStatus
from api_schemas.products import Pose, TrajectoryPublic
from service.api.deps import DataDep, JobDep, StoreDep
from service.api.error_handlers import error_response
from service.http_errors import InvalidInput, NotFound
from service.jobs.products import MEDIA_TYPES, product_path, tile_source
from service.jobs.trajectory_body import trajectory_body
from service.storage.data_dir import DataDir
from service.storage.rows import JobRow
from service.storage.store import JobStore

MAX_TILE_ZOOM = 24
MAX_TILE_INDEX = 2**MAX_TILE_ZOOM - 1

router = APIRouter(prefix="/v1/jobs/{job_id}", tags=["products"],
                   responses={401: {"model": ErrorResponse}, 404: {"model": ErrorResponse},
                              409: {"model": ErrorResponse, "description": "Not available (yet)."}})


class TrajectoryFormat(StrEnum):
    JSON = "json"
    TUM = "tum"


class TileLayer(StrEnum):
    OCCUPANCY = "occupancy"
    TEXTURE = "texture"


class TileScheme(StrEnum):
    SIMPLE = "simple"  # metric pyramid for Leaflet L.CRS.Simple
    WEBMERCATOR = "webmercator"  # standard XYZ tiles (EPSG:3857), for sessions with a geo origin


def _georeference(store: JobStore, job: JobRow) -> Any:
    """The map's placement on Earth from the job's session geo origin (422 when it has none)."""
    from slam_engine.products import GeoOrigin
    from slam_engine.products.georeference import Georeference

    session = store.get_session(job.session_id, job.owner)
    if session is None or session.geo is None:
        raise InvalidInput("Web Mercator tiles need a georeferenced session: create it with a geo origin "
                           "(lat_deg, lon_deg, heading_deg)", {"scheme": "webmercator"})
    geo = session.geo
    origin = GeoOrigin(latitude_deg=geo["lat_deg"], longitude_deg=geo["lon_deg"], heading_deg=geo["heading_deg"])
    return Georeference.utm(origin, start_pose=np.zeros(3))  # the map frame starts at the first pose


class ProductFileResponse(FileResponse):
    """A product file with byte ranges as Starlette serves them, except that a malformed or
    unsatisfiable ``Range`` header answers with the API's JSON error body (400 ``bad_range``, 416
    ``range_not_satisfiable`` with ``Content-Range: bytes */SIZE``), not Starlette's plain text."""

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        headers = Headers(scope=scope)
        http_range, if_range = headers.get("range"), headers.get("if-range")
        if http_range is not None and self.stat_result is None:
            try:
                self.stat_result = os.stat(self.path)
                self.set_stat_headers(self.stat_result)  # If-Range compares with them
            except OSError:
                http_range = None  # Starlette's own answer
        if (http_range is not None and self.stat_result is not None and self.status_code == 200
                and scope.get("method", "GET").upper() in ("GET", "HEAD")
                and (if_range is None or self._should_use_range(if_range))):
            size = self.stat_result.st_size
            try:
                self._parse_range_header(http_range, size)
            except MalformedRangeHeader as exc:
                answer = error_response(400, "bad_range", f"Range header: {exc.content}",
                                        {"range": http_range[:200]})
                await answer(scope, receive, send)
                return
            except RangeNotSatisfiable:
                answer = error_response(416, "range_not_satisfiable",
                                        f"Range header: no byte of the range lies in the file ({size} bytes)",
                                        {"range": http_range[:200], "size_bytes": size},
                                        headers={"Content-Range": f"bytes */{size}"})
                await answer(scope, receive, send)
                return
        await super().__call__(scope, receive, send)


def _file(data: DataDir, job: JobRow, name: str) -> FileResponse:
    path = product_path(data, job, name)
    headers = {"Cache-Control": "no-store"} if job.status is JobStatus.RUNNING else None
    return ProductFileResponse(path, media_type=MEDIA_TYPES[name], headers=headers)


def _trajectory(request: Request, data: DataDir, job: JobRow, stem: str, kind: str,
                fmt: TrajectoryFormat) -> Response:
    """A trajectory from the file the job wrote: TUM as the file; JSON streamed from the file's poses
    (HEAD: the size from the file, no body built); files of the first trajectory format converted."""
    from slam_engine.products import read_trajectory

    if fmt is TrajectoryFormat.TUM:
        return _file(data, job, f"{stem}.tum")
    path = product_path(data, job, f"{stem}.json")
    body = trajectory_body(path, job.id, kind)
    if body is not None:
        headers = {"Content-Length": str(body.size_bytes)}
        if job.status is JobStatus.RUNNING:
            headers["Cache-Control"] = "no-store"
        if request.method == "HEAD":
            body.close()
            return Response(media_type="application/json", headers=headers)
        return StreamingResponse(body.blocks(), media_type="application/json", headers=headers)
    traj = read_trajectory(path)
    poses = [Pose(t_s=float(t), x_m=float(p[0]), y_m=float(p[1]), theta_rad=float(p[2]))
             for t, p in zip(traj.t_s, traj.poses, strict=True)]
    answer = JSONResponse(jsonable_encoder(TrajectoryPublic(job_id=job.id, kind=kind, count=len(poses),
                                                            poses=poses)))
    if request.method == "HEAD":  # the same headers as the GET's
        return Response(media_type="application/json", headers={"Content-Length": str(len(answer.body))})
    return answer


TrajectoryFormatQuery = Annotated[TrajectoryFormat, Query(alias="format", description="json or tum (text)")]
TEXT: dict[int | str, dict[str, Any]] = {200: {"content": {"text/plain": {}},
                                               "description": "JSON, or TUM text with ?format=tum."}}


@router.get("/trajectory", response_model=TrajectoryPublic, responses=TEXT)
@router.head("/trajectory", response_model=TrajectoryPublic, responses=TEXT, name="trajectory (head)")
def trajectory(request: Request, job: JobDep, data: DataDep, fmt: TrajectoryFormatQuery = TrajectoryFormat.JSON):
    """The SLAM trajectory: JSON poses, or TUM (``t x y z qx qy qz qw``) with ?format=tum."""
    return _trajectory(request, data, job, "trajectory", "slam", fmt)


@router.get("/dead-reckoning", response_model=TrajectoryPublic, responses=TEXT)
@router.head("/dead-reckoning", response_model=TrajectoryPublic, responses=TEXT, name="dead_reckoning (head)")
def dead_reckoning(request: Request, job: JobDep, data: DataDep,
                   fmt: TrajectoryFormatQuery = TrajectoryFormat.JSON):
    """Odometry alone, for comparison."""
    return _trajectory(request, data, job, "dead_reckoning", "dead_reckoning", fmt)


def _file_route(name: str, summary: str) -> None:
    """GET and HEAD /v1/jobs/{id}/{name}: the product file under the name the job lists."""
    media = MEDIA_TYPES[name]

    def route(job: JobDep, data: DataDep) -> FileResponse:
        return _file(data, job, name)

    route.__doc__ = summary
    for method in ("GET", "HEAD"):  # HEAD: the same headers (size, type), no body
        router.add_api_route(f"/{name}", route, methods=[method], response_class=FileResponse,
                             name=name if method == "GET" else f"{name} (head)", summary=summary,
                             responses={200: {"content": {media: {}}}})


PRODUCT_SUMMARIES = {
    "occupancy.png": "Occupancy grid as PNG (north up). While the job runs: the map so far.",
    "occupancy_trajectory.png": "Occupancy grid with the SLAM trajectory, dead reckoning and start drawn on it.",
    "occupancy.tif": "Occupancy probability as a georeferenced GeoTIFF.",
    "map.yaml": "ROS map_server metadata (with map.pgm).",
    "map.pgm": "ROS map_server image.",
    "texture.png": "Ground texture map as PNG (when the log has a camera).",
    "texture.tif": "Ground texture map as GeoTIFF.",
    "animation.gif": "The map growing over the run.",
    "trajectory.json": "The SLAM trajectory as the lidarmap JSON file (poses t_s, x_m, y_m, theta_rad, as the API's). "
                       "While the job runs: the trajectory so far.",
    "trajectory.tum": "The SLAM trajectory in TUM format (t x y z qx qy qz qw).",
    "dead_reckoning.json": "Odometry alone, as the lidarmap JSON file.",
    "dead_reckoning.tum": "Odometry alone, in TUM format.",
    "run.json": "The run record file: configuration, timings, scan statistics, input summary, accuracy.",
    "map_points.ply": "The map as a point cloud (binary PLY: Open3D, CloudCompare): every scan's returns at the "
                      "optimised poses, one point per map cell, stray points removed.",
    "map_bundle.npz": "The map bundle: key frames, their scans and the pose graph, to localise a later drive in "
                      "this map, extend it or merge it (`lidarmap localize/run --map/merge`; docs/map-bundle.md).",
    "drives.png": "An extended map with each drive's trajectory in its own colour (mode 'extend').",
    "localization.png": "A localised drive's scans over the saved map: red where they matched it, blue where the "
                        "drive's own motion carried them (mode 'localize').",
    "confidence.json": "A localised drive's confidence per pose: its match score against the map, 0-1 "
                       "(mode 'localize').",
    "poses.jsonl": "A live localisation's reports as it made them, one JSON object a line: scan, t_s, pose "
                   "[x_m, y_m, theta_rad] (null while searching), confidence, state, the chunk's seq and "
                   "latency_s (mode 'localize', live; GET /v1/jobs/{id}/poses serves them while it runs).",
    "changes.png": "What changed since the saved map (modes 'localize' and 'extend'): the saved map with the cells "
                   "the drive saw added in red and removed in blue.",
    "changes.geojson": "What changed since the saved map as polygons (kind 'added' or 'removed', area_m2), in the "
                       "map frame [m], or WGS 84 when the session has a geo origin (modes 'localize' and 'extend').",
}
assert set(PRODUCT_SUMMARIES) == set(MEDIA_TYPES), "every product the worker lists has a route"
for _name, _summary in PRODUCT_SUMMARIES.items():
    _file_route(_name, _summary)


@router.get("/run", response_model=dict[str, Any], response_class=FileResponse,
            responses={200: {"content": {"application/json": {}}}})
@router.head("/run", response_model=dict[str, Any], response_class=FileResponse, name="run_record (head)")
def run_record(job: JobDep, data: DataDep) -> FileResponse:
    """The run record: configuration used, timings, scan statistics, input summary (the file run.json)."""
    return _file(data, job, "run.json")


@router.get("/tiles/{layer}/{z}/{x}/{y}.png", response_class=Response,
            responses={200: {"content": {"image/png": {}}}, 422: {"model": ErrorResponse}})
@router.head("/tiles/{layer}/{z}/{x}/{y}.png", response_class=Response, name="tile (head)",
             responses={200: {"content": {"image/png": {}}}, 422: {"model": ErrorResponse}})
async def tile(request: Request, job: JobDep, data: DataDep, store: StoreDep, layer: TileLayer,
               z: Annotated[int, Path(ge=0, le=MAX_TILE_ZOOM)], x: Annotated[int, Path(ge=0, le=MAX_TILE_INDEX)],
               y: Annotated[int, Path(ge=0, le=MAX_TILE_INDEX)],
               scheme: Annotated[TileScheme, Query(description="simple (metric) or webmercator (XYZ, needs "
                                                               "a session geo origin)")] = TileScheme.SIMPLE,
               ) -> Response:
    """A 256x256 PNG tile of the map (z=0: the whole map; x, y in 0..2^z-1; 404 beyond the map's
    deepest zoom, or outside the map in Web Mercator). While the job runs: tiles of the map so far."""
    if x >= 2**z or y >= 2**z:
        raise InvalidInput(f"tile ({x}, {y}) does not exist at zoom {z}: x and y must be below {2**z}",
                           {"z": z, "x": x, "y": y})
    from slam_engine.products import render_tile

    source, version = await run_in_threadpool(tile_source, data, job, layer.value)
    georef = _georeference(store, job) if scheme is TileScheme.WEBMERCATOR else None
    png = await run_in_threadpool(partial(render_tile, source, z, x, y, layer.value, scheme=scheme.value,
                                          georef=georef, map_version=(version, scheme.value)))
    headers = {"Cache-Control": "no-store"} if job.status is JobStatus.RUNNING else {}
    if request.method == "HEAD":  # the GET's headers, no body
        return Response(media_type="image/png", headers={**headers, "Content-Length": str(len(png))})
    return Response(png, media_type="image/png", headers=headers or None)


POSES_POLL_S = 0.02  # how often a pose stream looks for new reports in the job's file [s] ...
POSES_STATUS_S = 0.5  # ... and for the job's end in the store [s]
POSES_KEEPALIVE_S = 15.0  # a comment line this often while nothing happens (proxies close idle streams)


def _poses_file(data: DataDir, job: JobRow) -> pathlib.Path | None:
    """A live localisation's reports: the live file while it runs, the product once it finished (None:
    not written yet)."""
    from service.jobs.live_localization import POSES_FILE

    stored = job.products.get(POSES_FILE)
    if stored is not None:
        return data.resolve(str(pathlib.PurePath("jobs") / job.id / stored))
    live = data.live_dir(job.id) / POSES_FILE
    return live if live.exists() else None


def _read_lines(path: pathlib.Path | None, offset: int) -> tuple[list[str], int]:
    """The complete lines of ``path`` from byte ``offset`` on, and the offset after them."""
    if path is None:
        return [], offset
    try:
        with path.open("rb") as f:
            f.seek(offset)
            block = f.read()
    except FileNotFoundError:  # the live file, just moved into the products
        return [], offset
    end = block.rfind(b"\n") + 1
    return block[:end].decode().splitlines(), offset + end


def _after(report: dict[str, Any], after: int) -> bool:
    """Whether a live report comes after scan ``after``: a later scan's, or a revision of that scan's."""
    return report["scan"] > after or (bool(report.get("revised")) and report["scan"] == after)


@router.get("/poses", summary="A live localisation's poses, as it makes them",
            description="Every scan's report of a live job of mode 'localize': `scan`, `t_s`, `pose` "
                        "[x_m, y_m, theta_rad] in the saved map's frame (null while searching), `confidence` "
                        "(0-1), `state` (searching, found, carried, outside, lost), the chunk's `seq` and "
                        "`latency_s` from the chunk accepted (or the job ready, when later) to the pose written. "
                        "The last scan may come again, found and marked `revised: true`, when the search "
                        "running as the stream ended placed the drive. With `stream=true` "
                        "(or `Accept: text/event-stream`): server-sent events, one `pose` event per scan "
                        "(`id`: the scan) as it is made, then an `end` event with the job's status; "
                        "`Last-Event-ID` or `after` resumes after a scan (a revision of that scan still comes).")
async def live_poses(job: JobDep, data: DataDep, store: StoreDep, request: Request,
                     stream: Annotated[bool, Query(description="Server-sent events until the job ends.")] = False,
                     after: Annotated[int, Query(ge=-1, le=10**9, description="Only scans after this one.")] = -1
                     ) -> Response:
    if not (job.live and job.config.get("mode") == "localize"):
        raise NotFound("this job has no poses: they are a live localisation's (a live job of mode 'localize')",
                       {"job_id": job.id, "live": job.live, "mode": job.config.get("mode")})
    last_event = request.headers.get("last-event-id", "")
    if last_event.isdigit():
        after = max(after, int(last_event))
    wants_events = stream or "text/event-stream" in request.headers.get("accept", "")
    if not wants_events:
        lines, _ = await run_in_threadpool(_read_lines, _poses_file(data, job), 0)
        poses = [p for p in (json.loads(line) for line in lines) if _after(p, after)]
        return JSONResponse({"job_id": job.id, "status": job.status.value, "count": len(poses), "poses": poses})

    async def events():
        offset, last_sent, checked = 0, time.monotonic(), time.monotonic()
        current = job
        while True:
            finished = current.status not in (JobStatus.QUEUED, JobStatus.RUNNING)
            lines, offset = await run_in_threadpool(_read_lines, _poses_file(data, current), offset)
            for line in lines:
                report = json.loads(line)
                if _after(report, after):
                    yield f"id: {report['scan']}\nevent: pose\ndata: {line}\n\n"
                    last_sent = time.monotonic()
            if finished and not lines:
                yield f"event: end\ndata: {json.dumps({'status': current.status.value})}\n\n"
                return
            if await request.is_disconnected():
                return
            if time.monotonic() - last_sent > POSES_KEEPALIVE_S:
                yield ": waiting for the next scan\n\n"
                last_sent = time.monotonic()
            await asyncio.sleep(POSES_POLL_S)
            if time.monotonic() - checked >= POSES_STATUS_S:
                checked = time.monotonic()
                current = await run_in_threadpool(store.get_job, job.id) or current

    return StreamingResponse(events(), media_type="text/event-stream",
                             headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})
