"""/healthz (liveness, open) and /readyz (workers and storage)."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import JSONResponse

from api_schemas.health import Health, Readiness, StorageState, WorkerState
from service.api.deps import DataDep, OwnerDep, RunnerDep, StoreDep
from slam_engine import __version__

router = APIRouter(tags=["health"])


@router.get("/healthz", response_model=Health)
def healthz() -> Health:
    """Liveness: the process answers."""
    return Health(status="ok", version=__version__)


@router.get("/readyz", response_model=Readiness, responses={503: {"model": Readiness}})
def readyz(_: OwnerDep, runner: RunnerDep, store: StoreDep, data: DataDep) -> Readiness | JSONResponse:
    """Readiness: every worker alive (Celery: at least one answers), the database answers, the data folder
    is writable."""
    h = runner.health()
    storage = StorageState(data_dir_writable=data.writable(), database_ok=store.ping(), free_bytes=data.free_bytes())
    ready = h.ready and storage.data_dir_writable and storage.database_ok
    body = Readiness(ready=ready, storage=storage,
                     workers=WorkerState(runner=h.runner, workers_total=h.workers_total,
                                         workers_alive=h.workers_alive, busy=h.busy, queued=h.queued))
    return body if ready else JSONResponse(body.model_dump(), status_code=503)
