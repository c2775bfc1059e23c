"""Products served as JSON: trajectories and the run record."""

from __future__ import annotations

from pydantic import AliasChoices, BaseModel, Field


class Pose(BaseModel):
    """A planar pose in the map frame. The API names carry units (as every message of the API does);
    the trajectory files' names (``t, x, y, theta`` with a ``units`` block) are accepted as aliases, so
    ``Pose.model_validate`` reads the poses of a downloaded ``trajectory.json`` too."""

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
