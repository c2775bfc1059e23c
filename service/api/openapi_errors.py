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
from typing import Any

from fastapi import FastAPI
from fastapi.dependencies.models import Dependant
from fastapi.routing import APIRoute, iter_route_contexts

from api_schemas.error_body import ErrorResponse
from service.api.deps import get_owner

REF = "#/components/schemas/"
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


def error_statuses(route: Any) -> set[int]:
    """The error statuses ``route`` (an APIRoute or FastAPI's route context) can answer, from its
    parameters, body and dependencies."""
    statuses: set[int] = set()
    parts = list(_dependants(route.dependant))
    if any(d.call is get_owner for d in parts):
        statuses.add(401)
    if any(d.path_params for d in parts):
        statuses |= {404, 422}
    if any(d.query_params or d.header_params for d in parts):
        statuses.add(422)
    takes_body = route.body_field is not None or "requestBody" in (route.openapi_extra or {})
    if takes_body:
        statuses |= {400, 413, 422, 507}
    return statuses


def api_routes(app: FastAPI) -> Iterator[Any]:
    """Every API route of ``app`` as served (prefixes applied), in the schema or not."""
    for context in iter_route_contexts(app.routes):
        if isinstance(context.original_route, APIRoute):
            yield context


def document_errors(app: FastAPI) -> None:
    """Make ``app.openapi()`` list, for each operation, the error statuses it can answer (with the
    error body's schema), keeping any description a router already wrote."""
    generate = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is not None:
            return app.openapi_schema
        schema = generate()
        components = schema.setdefault("components", {}).setdefault("schemas", {})
        for name, definition in ErrorResponse.model_json_schema(ref_template=REF + "{model}").get("$defs", {}).items():
            components.setdefault(name, definition)
        error_schema = ErrorResponse.model_json_schema(ref_template=REF + "{model}")
        error_schema.pop("$defs", None)
        components.setdefault(ErrorResponse.__name__, error_schema)
        for route in api_routes(app):
            if not route.include_in_schema:
                continue
            for method in route.methods:
                operation = schema["paths"].get(route.path_format, {}).get(method.lower())
                if operation is None:
                    continue
                responses = operation.setdefault("responses", {})
                for status in sorted(error_statuses(route)):
                    responses.setdefault(str(status), {
                        "description": DESCRIPTIONS[status],
                        "content": {"application/json": {"schema": {"$ref": REF + ErrorResponse.__name__}}}})
        app.openapi_schema = schema
        return schema

    app.openapi = openapi  # type: ignore[method-assign]  # FastAPI's documented way to extend the schema
