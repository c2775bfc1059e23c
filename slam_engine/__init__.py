"""lidarmap's SLAM engine: Rao-Blackwellized particle-filter SLAM on 2-D LiDAR drive logs.

Arrays and dataclasses in, result objects out; no web code and no file writing here (loaders read
files, ``slam_engine.products`` writes them).
"""

import os as _os

# The parallel kernels' OpenMP threads sleep while they wait for work instead of spinning: a
# spinning thread takes its core from other work on a busy machine (service workers, CI, laptops).
# libgomp reads this once, when it loads (at the first parallel kernel), so it is set here, on the
# engine's first import; a value the user set is kept.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

__version__ = "0.1.0"
