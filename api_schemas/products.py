"""Products served as JSON: trajectories and the run record."""

from __future__ import annotations

from pydantic import BaseModel, Field


class Pose(BaseModel):
    t_s: float
    x_m: float
    y_m: float
    theta_rad: float


class TrajectoryPublic(BaseModel):
    """SE(2) poses in the map frame (origin at the first pose), one per scan of the log."""

    job_id: str
    kind: str = Field(description="'slam' or 'dead_reckoning'.")
    count: int
    poses: list[Pose]
