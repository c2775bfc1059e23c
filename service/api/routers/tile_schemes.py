"""/v1/jobs/{id}/tiles/{layer}: the layout of a job's tile pyramid (zooms, origin, Leaflet transformation)."""

from __future__ import annotations

from fastapi import APIRouter, Request
from fastapi.responses import JSONResponse, Response
from starlette.concurrency import run_in_threadpool

from api_schemas.error_body import ErrorResponse
from api_schemas.tiles import TileSchemePublic
from service.api.deps import DataDep, JobDep
from service.api.routers.products import TileLayer
from service.jobs.products import tile_source

router = APIRouter(prefix="/v1/jobs/{job_id}", tags=["products"],
                   responses={401: {"model": ErrorResponse}, 404: {"model": ErrorResponse},
                              409: {"model": ErrorResponse, "description": "Not available (yet)."}})


@router.get("/tiles/{layer}", response_model=TileSchemePublic)
@router.head("/tiles/{layer}", response_model=TileSchemePublic, name="tile_scheme (head)")
async def tile_scheme(request: Request, job: JobDep, data: DataDep, layer: TileLayer) -> TileSchemePublic | Response:
    """Which zooms and tiles exist and where they lie in the map frame. While the job runs the map may
    grow: fetch this again when ``scans_done`` changes."""
    from slam_engine.products import TileScheme

    source, _ = await run_in_threadpool(tile_source, data, job, layer.value)
    description = TileScheme.for_map(source).describe()
    scheme = TileSchemePublic(job_id=job.id, layer=layer.value, scans_done=job.scans_done, **description)
    if request.method == "HEAD":  # the GET's headers, no body
        body = JSONResponse(scheme.model_dump(mode="json")).body
        return Response(media_type="application/json", headers={"Content-Length": str(len(body))})
    return scheme
