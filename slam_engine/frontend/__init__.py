"""The front end: the Rao-Blackwellized particle filter and its parts.

- ``particle_filter``: :class:`SlamFilter`, one step per odometry or scan message;
- ``motion_models``, ``odometry``, ``odometry_noise``, ``heading_calibration``, ``time_offset``: where
  the vehicle went between two scans, by how much to doubt it, and when each scan was measured;
- ``lidar_points``: a scan's end points in the vehicle frame through the LiDAR's 4x4 extrinsics;
- ``scan_matcher``: each particle's pose fitted to its own map (the proposal and the weight);
- ``grid``, ``raycast``, ``map_pooling``: the particles' tiled log-odds maps and the rays written into them;
- ``resampling``: low-variance resampling when the effective sample size falls.
"""

from typing import TYPE_CHECKING

from slam_engine._exports import lazy_exports

if TYPE_CHECKING:
    from slam_engine.frontend.particle_filter import SlamFilter, engine_threads

__all__ = ["SlamFilter", "engine_threads"]
__getattr__, __dir__ = lazy_exports({"SlamFilter": "slam_engine.frontend.particle_filter",
                                     "engine_threads": "slam_engine.frontend.particle_filter"})
