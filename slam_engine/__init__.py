"""lidarmap's SLAM engine: Rao-Blackwellized particle-filter SLAM on 2-D LiDAR drive logs.

Arrays and dataclasses in, result objects out; no web code and no file writing here (loaders read
files, ``slam_engine.products`` writes them).
"""

__version__ = "0.1.0"
