"""Products served as JSON: trajectories and the run record."""

from __future__ import annotations

from pydantic import AliasChoices, BaseModel, Field


class Pose(BaseModel):
    """A planar pose in the map frame. The names carry units (as every message of the API does), and the
    trajectory files (``trajectory.json``, ``dead_reckoning.json``) use the same names, so
    ``Pose.model_validate`` reads a downloaded file's poses. The names of files written before that
    (``t, x, y, theta``, trajectory JSON version 1) are accepted as aliases."""

    t_s: float = Field(validation_alias=AliasChoices("t_s", "t"), description="Time [s].")
    x_m: float = Field(validation_alias=AliasChoices("x_m", "x"), description="[m]")
    y_m: float = Field(validation_alias=AliasChoices("y_m", "y"), description="[m]")
    theta_rad: float = Field(validation_alias=AliasChoices("theta_rad", "theta"),
                             description="Heading [rad], counter-clockwise from the map's x axis.")


class TrajectoryPublic(BaseModel):
    """SE(2) poses in the map frame (origin at the first pose), one per scan of the log."""

    job_id: str
    kind: str = Field(description="'slam' or 'dead_reckoning'.")
    count: int
    poses: list[Pose]
