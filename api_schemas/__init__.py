"""Pydantic models shared by the service, the CLI and clients. Imports only pydantic and the
standard library."""

from api_schemas.jobs import LOADING_MAP_STAGE, JobCreate, JobMode, JobPublic, JobSource, JobsPublic, JobStatus

__all__ = ["LOADING_MAP_STAGE", "JobCreate", "JobMode", "JobPublic", "JobSource", "JobStatus", "JobsPublic"]
