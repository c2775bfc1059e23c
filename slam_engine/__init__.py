"""lidarmap's SLAM engine: Rao-Blackwellized particle-filter SLAM on 2-D LiDAR drive logs.

Arrays and dataclasses in, result objects out; no web code and no file writing here (loaders read
files, ``slam_engine.products`` writes them). Laid out as its pipeline:

- ``model``: the drive log, messages, poses and the result;
- ``formats``: drive-log loaders and writers (``load_log``);
- ``frontend``: the particle filter (``SlamFilter``) and its parts;
- ``backend``: submaps, loop closing, the pose graph, the map alignment and the final map;
- ``texture``: the ground's colour map from stereo or RGB-D cameras;
- ``products``: every file a run writes (``write_products``);
- ``simulation``: drives with exact ground truth; ``evaluation``: how good a run is;
- ``config`` (``SlamConfig``), ``pipeline`` (``run_slam``: one whole drive), ``kernels`` (numba's cache).

    >>> from slam_engine import load_log, run_slam, SlamConfig
    >>> result = run_slam(load_log("intel.clf"), SlamConfig(seed=0))
"""

import os as _os

# The parallel kernels' OpenMP threads sleep while they wait for work instead of spinning: a
# spinning thread takes its core from other work on a busy machine (service workers, CI, laptops).
# libgomp reads this once, when it loads (at the first parallel kernel), so it is set here, on the
# engine's first import; a value the user set is kept.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

__version__ = "0.1.0"

from typing import TYPE_CHECKING  # noqa: E402  (after the environment is set)

from slam_engine._exports import lazy_exports  # noqa: E402

if TYPE_CHECKING:
    from slam_engine.config import SlamConfig
    from slam_engine.formats import load_log
    from slam_engine.frontend.particle_filter import SlamFilter
    from slam_engine.model.drive_log import DriveLog
    from slam_engine.model.result import SlamResult
    from slam_engine.pipeline import run_slam
    from slam_engine.products import write_products
    from slam_engine.simulation import simulate

__all__ = ["DriveLog", "SlamConfig", "SlamFilter", "SlamResult", "load_log", "run_slam", "simulate", "write_products"]
__getattr__, __dir__ = lazy_exports({
    "SlamConfig": "slam_engine.config", "load_log": "slam_engine.formats",
    "SlamFilter": "slam_engine.frontend.particle_filter", "DriveLog": "slam_engine.model.drive_log",
    "SlamResult": "slam_engine.model.result", "run_slam": "slam_engine.pipeline",
    "write_products": "slam_engine.products", "simulate": "slam_engine.simulation",
})
