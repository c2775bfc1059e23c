"""Vehicle and LiDAR calibration as JSON: what a streaming session needs, since streamed messages
carry none. Mirrors slam_engine.model.drive_log.VehicleModel and LidarModel (metres, radians)."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field

from api_schemas.drivelog import Matrix4  # 4x4, row-major, metres


class VehicleCalibration(BaseModel):
    model_config = ConfigDict(extra="forbid")

    kind: Literal["differential", "skid_steer", "odometry"]
    ticks_per_revolution: float | None = Field(None, strict=True, gt=0, le=1e7)
    wheel_diameters_m: list[Annotated[float, Field(strict=True, gt=0, le=10)]] | None = Field(
        None, strict=True, min_length=1, max_length=8)
    wheel_names: list[Annotated[str, Field(max_length=40)]] = Field(default_factory=list, max_length=8)
    track_width_m: float | None = Field(None, strict=True, gt=0, le=20)
    gyro_lowpass_hz: float | None = Field(None, strict=True, gt=0, le=10_000)
    T_vehicle_from_gyro: Matrix4 | None = None
    name: str = Field("vehicle", max_length=100)


class LidarCalibration(BaseModel):
    model_config = ConfigDict(extra="forbid")

    num_beams: int = Field(strict=True, ge=1, le=100_000)
    angle_min_rad: float = Field(strict=True, ge=-7.0, le=7.0)
    angle_increment_rad: float = Field(strict=True, ge=-3.2, le=3.2)
    range_min_m: float = Field(strict=True, ge=0.0, le=1000.0)
    range_max_m: float = Field(strict=True, gt=0.0, le=1000.0)
    T_vehicle_from_lidar: Matrix4 | None = None
    name: str = Field("lidar", max_length=100)
    time_increment_s: float | None = Field(None, strict=True, ge=-0.01, le=0.01,
                                           description="Seconds between consecutive "
                                           "beams (negative: swept in reverse order), for de-skew; null = unknown.")


class Calibration(BaseModel):
    """Everything the engine needs besides the messages."""

    model_config = ConfigDict(extra="forbid")

    vehicle: VehicleCalibration
    lidar: LidarCalibration | None = None
