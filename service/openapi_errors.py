"""Every route's error answers, written into the OpenAPI schema from what the route takes.

A client (and the schema fuzzer, tests/stress/fuzz_service.py) must find every status the service
can answer in the schema. Rather than trusting each router to list them, :func:`document_errors`
derives them from the route itself, so a new route cannot forget one:

| the route...                         | may answer |
|--------------------------------------|------------|
| needs the caller (API keys)          | 401 |
| has path parameters (ids)            | 404 (unknown id, or another key's), 422 (malformed) |
| has query parameters                 | 422 |
| takes a body                         | 400 (unparsable), 413 (too big), 422 (invalid), 507 (disk full) |
"""

from __future__ import annotations

from collections.abc import Iterator

from fastapi import FastAPI
from fastapi.dependencies.models import Dependant
from fastapi.routing import APIRoute
from fastapi.utils import create_model_field

from api_schemas.errors import ErrorResponse
from service.deps import get_owner

DESCRIPTIONS = {
    400: "The body cannot be parsed.",
    401: "No API key, or an unknown one (when keys are configured).",
    404: "No such resource for this caller.",
    413: "The body is larger than the limit.",
    422: "A parameter or the body is invalid (the message names the field).",
    507: "The server's disk is (nearly) full: nothing was stored; retry later.",
}


def _dependants(dependant: Dependant) -> Iterator[Dependant]:
    yield dependant
    for sub in dependant.dependencies:
        yield from _dependants(sub)


def error_statuses(route: APIRoute) -> set[int]:
    """The error statuses ``route`` can answer, from its parameters, body and dependencies."""
    statuses: set[int] = set()
    parts = list(_dependants(route.dependant))
    if any(d.call is get_owner for d in parts):
        statuses.add(401)
    if any(d.path_params for d in parts):
        statuses |= {404, 422}
    if any(d.query_params or d.header_params for d in parts):
        statuses.add(422)
    takes_body = any(d.body_params for d in parts) or "requestBody" in (route.openapi_extra or {})
    if takes_body:
        statuses |= {400, 413, 422, 507}
    return statuses


def document_errors(app: FastAPI) -> None:
    """Add the error statuses each route can answer (with the error body's schema) to its OpenAPI
    responses, keeping any description a router already wrote."""
    for route in app.routes:
        if not isinstance(route, APIRoute):
            continue
        for status in sorted(error_statuses(route)):
            if status in route.responses or str(status) in route.responses:
                continue
            route.responses[status] = {"model": ErrorResponse, "description": DESCRIPTIONS[status]}
            route.response_fields[status] = create_model_field(
                name=f"Response_{status}_{route.unique_id}", type_=ErrorResponse, mode="serialization")
    app.openapi_schema = None
