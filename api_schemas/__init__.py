"""Pydantic models shared by the service, the CLI and clients. Imports only pydantic and the
standard library."""

from api_schemas.jobs import JobCreate, JobMode, JobPublic, JobSource, JobsPublic, JobStatus

__all__ = ["JobCreate", "JobMode", "JobPublic", "JobSource", "JobStatus", "JobsPublic"]
