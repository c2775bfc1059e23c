"""FastAPI dependencies and their ``Annotated`` aliases: settings, store, data folder, runner, caller."""

from __future__ import annotations

import hashlib
from typing import Annotated

from fastapi import Depends, Path, Request
from fastapi.security import APIKeyHeader, HTTPAuthorizationCredentials, HTTPBearer

from service.api.access import is_known_key, offered_key
from service.http_errors import NotFound, Unauthorized
from service.runners.base import JobRunner
from service.settings import Settings
from service.storage.data_dir import DataDir
from service.storage.rows import JobRow, SessionRow
from service.storage.store import JobStore

ANONYMOUS = ""
MAX_OFFSET = 2**31 - 1  # list offsets beyond any real count (SQLite integers are 64-bit)

_api_key_header = APIKeyHeader(name="X-API-Key", auto_error=False, description="An API key (when keys are set).")
_bearer = HTTPBearer(auto_error=False, description="An API key as a bearer token (when keys are set).")


def get_settings_dep(request: Request) -> Settings:
    return request.app.state.settings


def get_store(request: Request) -> JobStore:
    return request.app.state.store


def get_data(request: Request) -> DataDir:
    return request.app.state.data


def get_runner(request: Request) -> JobRunner:
    return request.app.state.runner


SettingsDep = Annotated[Settings, Depends(get_settings_dep)]
StoreDep = Annotated[JobStore, Depends(get_store)]
DataDep = Annotated[DataDir, Depends(get_data)]
RunnerDep = Annotated[JobRunner, Depends(get_runner)]


def get_owner(request: Request, settings: SettingsDep, _key: Annotated[str | None, Depends(_api_key_header)],
              _token: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]) -> str:
    """Who calls: with no keys configured everyone is the same anonymous owner; otherwise the key
    (X-API-Key header or Bearer token) must match one, and its hash names the owner.
    (The two security parameters document the schemes in OpenAPI.)"""
    keys = settings.api_key_list()
    if not keys:
        return ANONYMOUS
    offered = offered_key(request.headers)
    if not offered:
        raise Unauthorized("an API key is required (header X-API-Key or Authorization: Bearer)",
                           headers={"WWW-Authenticate": "Bearer"})
    if not is_known_key(offered, keys):
        raise Unauthorized("unknown API key", headers={"WWW-Authenticate": "Bearer"})
    return "key:" + hashlib.sha256(offered.encode()).hexdigest()[:32]


OwnerDep = Annotated[str, Depends(get_owner)]

UUID_PATTERN = r"^[0-9a-fA-F]{8}-[0-9a-fA-F]{4}-[0-9a-fA-F]{4}-[0-9a-fA-F]{4}-[0-9a-fA-F]{12}$"


def session_or_404(store: StoreDep, owner: OwnerDep,
                   session_id: Annotated[str, Path(max_length=64)]) -> SessionRow:
    """The caller's session (another owner's session is as unknown as a missing one)."""
    session = store.get_session(session_id, owner)
    if session is None:
        raise NotFound(f"no session {session_id!r}", {"session_id": session_id})
    return session


def job_or_404(store: StoreDep, owner: OwnerDep, job_id: Annotated[str, Path(max_length=64)]) -> JobRow:
    job = store.get_job(job_id, owner)
    if job is None:
        raise NotFound(f"no job {job_id!r}", {"job_id": job_id})
    return job


SessionDep = Annotated[SessionRow, Depends(session_or_404)]
JobDep = Annotated[JobRow, Depends(job_or_404)]
