"""Sessions: one vehicle's drive, fed by uploaded logs or streamed chunks, mapped by jobs."""

from __future__ import annotations

from datetime import datetime

from pydantic import BaseModel, ConfigDict, Field

from api_schemas.calibration import Calibration


class GeoOrigin(BaseModel):
    """Where the map frame's origin (the first pose) lies on Earth and how it is turned."""

    model_config = ConfigDict(extra="forbid")

    lat_deg: float = Field(strict=True, ge=-80.0, le=84.0, description="WGS84 latitude of the map origin [deg] "
                           "(the UTM domain, -80..84).")
    lon_deg: float = Field(strict=True, ge=-180.0, le=180.0, description="WGS84 longitude of the map origin [deg].")
    heading_deg: float = Field(0.0, strict=True,
                               ge=0.0, lt=360.0, description="Compass heading of the vehicle's x axis "
                               "(forward) at the first pose, clockwise from true north [deg].")


class SessionCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")

    name: str = Field(min_length=1, max_length=200, description="A label for people.")
    vehicle_preset: str | None = Field(None, min_length=1, max_length=64, pattern=r"^[a-z0-9_-]+$",
                                       description="Name of a known vehicle (a label kept with the session; "
                                                   "streamed chunks need 'calibration').")
    calibration: Calibration | None = Field(None, description="Vehicle and LiDAR calibration, needed to "
                                            "map streamed chunks (uploaded logs carry their own).")
    geo: GeoOrigin | None = None


class SessionPublic(BaseModel):
    id: str
    name: str
    vehicle_preset: str | None
    calibration: Calibration | None
    geo: GeoOrigin | None
    created_at: datetime
    logs: int = Field(description="Uploaded logs.")
    chunks: int = Field(description="Streamed chunks received.")
    jobs: int = Field(description="Jobs created.")


class SessionsPublic(BaseModel):
    data: list[SessionPublic]
    count: int


class SessionDeleted(BaseModel):
    id: str
    jobs_cancelled: int = Field(description="Jobs that were still queued or running and were cancelled.")
