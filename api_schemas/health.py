"""Liveness and readiness."""

from __future__ import annotations

from pydantic import BaseModel


class Health(BaseModel):
    status: str
    version: str


class WorkerState(BaseModel):
    runner: str
    workers_total: int
    workers_alive: int
    busy: int
    queued: int


class StorageState(BaseModel):
    data_dir_writable: bool
    database_ok: bool
    free_bytes: int


class Readiness(BaseModel):
    ready: bool
    workers: WorkerState
    storage: StorageState
