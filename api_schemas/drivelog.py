"""The drive-log archive's manifest and the drive-log message schema, as pydantic models.

The same JSON is read by the engine (``slam_engine.formats.drivelog``, plain-Python validation);
a test keeps the two in agreement. The service's streamed upload chunks carry the same
``DriveLogMessage`` objects. Units: seconds, metres, radians; ``null`` range = no return.
"""

from __future__ import annotations

import math
from typing import Annotated, Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    SerializerFunctionWrapHandler,
    field_validator,
    model_serializer,
    model_validator,
)

FORMAT_NAME = "lidarmap-drivelog"
FORMAT_VERSION = 2  # 2 added the optional scans column angle_offset_rad
MEMBER_PATTERN = r"^[a-z_]+/[a-z_]+\.npy$"
STREAM_COLUMNS = {
    "scans": ("t_s", "ranges_m"),
    "encoders": ("t_s", "ticks"),
    "gyro": ("t_s", "yaw_rate_rad_s"),
    "odometry": ("t_s", "poses"),
}

# optional columns: kind -> {column: first format version with it}
OPTIONAL_STREAM_COLUMNS = {"scans": {"angle_offset_rad": 2}}

Matrix4 = Annotated[list[Annotated[list[float], Field(strict=True, min_length=4, max_length=4)]],
                    Field(min_length=4, max_length=4, description="4x4 rigid transform, row-major, metres")]


def _check_rigid(matrix: list[list[float]]) -> list[list[float]]:
    if not all(math.isfinite(v) for row in matrix for v in row):
        raise ValueError("must be finite")
    if [round(v, 6) for v in matrix[3]] != [0.0, 0.0, 0.0, 1.0]:
        raise ValueError("last row must be 0 0 0 1")
    for i in range(3):
        for j in range(3):
            dot = sum(matrix[k][i] * matrix[k][j] for k in range(3))
            if abs(dot - (1.0 if i == j else 0.0)) > 1e-6:
                raise ValueError("rotation part must be orthonormal")
    return matrix


def _identity() -> list[list[float]]:
    return [[1.0 if i == j else 0.0 for j in range(4)] for i in range(4)]


class VehicleSpec(BaseModel):
    """Calibration of the vehicle's odometry sensors (mirrors slam_engine VehicleModel)."""

    model_config = ConfigDict(extra="ignore")

    kind: Literal["differential", "skid_steer", "odometry"]
    ticks_per_revolution: float | None = Field(None, gt=0, allow_inf_nan=False)
    wheel_diameters_m: list[Annotated[float, Field(gt=0, allow_inf_nan=False)]] | None = Field(None, min_length=1)
    wheel_names: list[str] = []
    track_width_m: float | None = Field(None, gt=0, allow_inf_nan=False, description="effective track width")
    gyro_lowpass_hz: float | None = Field(None, gt=0, allow_inf_nan=False)
    T_vehicle_from_gyro: Matrix4 = Field(default_factory=_identity)
    name: str = "vehicle"

    _rigid = field_validator("T_vehicle_from_gyro")(_check_rigid)


class LidarSpec(BaseModel):
    """Beam geometry and mounting of a 2-D LiDAR (mirrors slam_engine LidarModel)."""

    model_config = ConfigDict(extra="ignore")

    num_beams: int = Field(gt=0, strict=True)
    angle_min_rad: float = Field(allow_inf_nan=False)
    angle_increment_rad: float = Field(allow_inf_nan=False)
    range_min_m: float = Field(ge=0, allow_inf_nan=False)
    range_max_m: float = Field(gt=0, allow_inf_nan=False)
    T_vehicle_from_lidar: Matrix4
    name: str = "lidar"
    time_increment_s: float | None = Field(None, allow_inf_nan=False)

    _rigid = field_validator("T_vehicle_from_lidar")(_check_rigid)

    @model_validator(mode="after")
    def _ranges_ordered(self) -> LidarSpec:
        if self.range_min_m >= self.range_max_m:
            raise ValueError("need range_min_m < range_max_m")
        return self


class StreamSpec(BaseModel):
    """One columnar stream: its kind, row count and the archive member of each column."""

    kind: Literal["scans", "encoders", "gyro", "odometry"]
    count: int = Field(ge=0, strict=True)
    columns: dict[str, Annotated[str, Field(pattern=MEMBER_PATTERN)]]

    @model_validator(mode="after")
    def _columns_match_kind(self) -> StreamSpec:
        required, optional = set(STREAM_COLUMNS[self.kind]), set(OPTIONAL_STREAM_COLUMNS.get(self.kind, {}))
        if not required <= set(self.columns) <= required | optional:
            raise ValueError(f"columns must be exactly {sorted(required)}"
                             + (f", optionally with {sorted(optional)}" if optional else ""))
        return self


class SourceSpec(BaseModel):
    format: str | None = None
    path: str | None = None


class DriveLogManifest(BaseModel):
    """``manifest.json`` of a ``.drivelog`` archive."""

    model_config = ConfigDict(extra="ignore")

    format: Literal["lidarmap-drivelog"]
    format_version: int = Field(ge=1, le=FORMAT_VERSION, strict=True)
    vehicle: VehicleSpec
    lidar: LidarSpec | None
    streams: list[StreamSpec]
    omitted_streams: list[str] = []
    source: SourceSpec | None = None

    @model_validator(mode="after")
    def _consistent(self) -> DriveLogManifest:
        kinds = [s.kind for s in self.streams]
        if len(kinds) != len(set(kinds)):
            raise ValueError("each stream kind may appear once")
        if "scans" in kinds and self.lidar is None:
            raise ValueError("a scans stream needs a lidar model")
        for stream in self.streams:
            for column, since in OPTIONAL_STREAM_COLUMNS.get(stream.kind, {}).items():
                if column in stream.columns and self.format_version < since:
                    raise ValueError(f"{stream.kind} column {column} needs format_version {since}")
        return self


# ---------------------------------------------------------------------------------------------- messages

# The engine's bounds on a log's values (slam_engine.model.drive_log: what an uploaded log may not hold,
# far beyond any real drive); a streamed message is held to the same (a test keeps them equal)
MAX_TIME_S = 1e10  # |t| [s]
MAX_COORDINATE_M = 1e6  # |x|, |y| of an odometry pose [m]
MAX_ANGLE_RAD = 1e6  # |theta| of an odometry pose [rad]
MAX_RANGE_M = 1e6  # a LiDAR range [m]
MAX_YAW_RATE_RAD_S = 1e3  # a gyro's yaw rate [rad/s]
MAX_TICKS = 2**62  # |cumulative ticks| (int64 with room for differences)

def _bounded(limit: float, description: str) -> Any:
    return Field(strict=True, allow_inf_nan=False, ge=-limit, le=limit, description=description)


class EncoderMessageModel(BaseModel):
    type: Literal["encoder"] = "encoder"
    t_s: float = _bounded(MAX_TIME_S, "time [s]")
    ticks: list[Annotated[int, Field(strict=True, ge=-MAX_TICKS, le=MAX_TICKS)]] = Field(
        strict=True, min_length=1, max_length=8, description="cumulative ticks, vehicle wheel_names order")


class GyroMessageModel(BaseModel):
    type: Literal["gyro"] = "gyro"
    t_s: float = _bounded(MAX_TIME_S, "time [s]")
    yaw_rate_rad_s: float = _bounded(MAX_YAW_RATE_RAD_S, "yaw rate [rad/s]")


class OdometryMessageModel(BaseModel):
    type: Literal["odometry"] = "odometry"
    t_s: float = _bounded(MAX_TIME_S, "time [s]")
    x_m: float = _bounded(MAX_COORDINATE_M, "odometry position [m]")
    y_m: float = _bounded(MAX_COORDINATE_M, "odometry position [m]")
    theta_rad: float = _bounded(MAX_ANGLE_RAD, "odometry heading [rad]")


Range = Annotated[float, Field(strict=True, ge=0, le=MAX_RANGE_M, allow_inf_nan=False)]  # [m]


class ScanMessageModel(BaseModel):
    type: Literal["scan"] = "scan"
    t_s: float = _bounded(MAX_TIME_S, "time [s]")
    ranges_m: list[Range | None] = Field(
        strict=True, min_length=1, max_length=100_000, description="metres in beam order; null = no return")
    angle_offset_rad: float | None = Field(
        default=None, strict=True, ge=-2 * math.pi, le=2 * math.pi, allow_inf_nan=False,
        description="this scan's start angle beyond the lidar's angle_min_rad [rad] (a laser whose start "
                    "angle changes from scan to scan, e.g. an interlaced SICK); absent = the lidar's")

    @model_serializer(mode="wrap")
    def _without_absent_offset(self, handler: SerializerFunctionWrapHandler) -> dict[str, Any]:
        """An absent offset is left out, so a scan without one serialises as it always did."""
        out = handler(self)
        if out.get("angle_offset_rad", 0) is None:
            del out["angle_offset_rad"]
        return out


DriveLogMessage = Annotated[EncoderMessageModel | GyroMessageModel | OdometryMessageModel | ScanMessageModel,
                            Field(discriminator="type")]


class DriveLogChunk(BaseModel):
    """A batch of time-ordered messages (the service's streamed upload chunk)."""

    messages: list[DriveLogMessage]


def json_schemas() -> dict[str, dict]:
    """JSON Schemas of the manifest and the message chunk, keyed by name."""
    return {"DriveLogManifest": DriveLogManifest.model_json_schema(),
            "DriveLogChunk": DriveLogChunk.model_json_schema()}
