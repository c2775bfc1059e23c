"""PROVISIONAL stand-in for the drive-log message schema (the formats branch owns this file and
replaces it on merge). JSON mirror of slam_engine.messages; ``null`` range = no return."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field


class _Msg(BaseModel):
    model_config = ConfigDict(extra="forbid")

    t_s: float = Field(allow_inf_nan=False)


class EncoderMessage(_Msg):
    type: Literal["encoder"] = "encoder"
    ticks: list[int] = Field(min_length=1, max_length=8)


class GyroMessage(_Msg):
    type: Literal["gyro"] = "gyro"
    yaw_rate_rad_s: float = Field(allow_inf_nan=False)


class OdometryMessage(_Msg):
    type: Literal["odometry"] = "odometry"
    x_m: float = Field(allow_inf_nan=False)
    y_m: float = Field(allow_inf_nan=False)
    theta_rad: float = Field(allow_inf_nan=False)


class ScanMessage(_Msg):
    type: Literal["scan"] = "scan"
    ranges_m: list[float | None] = Field(min_length=1, max_length=100_000)


Message = Annotated[EncoderMessage | GyroMessage | OdometryMessage | ScanMessage, Field(discriminator="type")]
