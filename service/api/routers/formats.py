"""/v1/formats: the drive-log formats the service reads."""

from __future__ import annotations

from fastapi import APIRouter

from api_schemas.logs import FormatPublic, FormatsPublic
from service.api.deps import OwnerDep

router = APIRouter(prefix="/v1/formats", tags=["formats"])


@router.get("", response_model=FormatsPublic)
def list_formats(_: OwnerDep) -> FormatsPublic:
    from slam_engine.formats import list_formats as engine_formats

    data = [FormatPublic(name=f.name, description=f.description, can_write=f.can_write) for f in engine_formats()]
    return FormatsPublic(data=data, count=len(data))
