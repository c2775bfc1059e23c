"""The data model: what a drive log holds (:class:`DriveLog` and its streams, the sensor models), the
messages a filter is stepped with, planar poses and their algebra (``[x_m, y_m, theta_rad]``), and what
a run returns (:class:`SlamResult`: trajectory, occupancy grid, texture, statistics)."""

from typing import TYPE_CHECKING

from slam_engine._exports import lazy_exports

if TYPE_CHECKING:
    from slam_engine.model.drive_log import DriveLog, LidarModel, VehicleModel
    from slam_engine.model.result import OccupancyGrid, SlamResult, TextureMap, Trajectory

__all__ = ["DriveLog", "LidarModel", "VehicleModel", "OccupancyGrid", "SlamResult", "TextureMap", "Trajectory"]
__getattr__, __dir__ = lazy_exports({
    "DriveLog": "slam_engine.model.drive_log", "LidarModel": "slam_engine.model.drive_log",
    "VehicleModel": "slam_engine.model.drive_log", "OccupancyGrid": "slam_engine.model.result",
    "SlamResult": "slam_engine.model.result", "TextureMap": "slam_engine.model.result",
    "Trajectory": "slam_engine.model.result",
})
