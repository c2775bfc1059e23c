"""Helpers that cut real logs down for fast tests."""

from __future__ import annotations

import dataclasses

from slam_engine.model.drive_log import DriveLog, OdometryStream, ScanStream


def first_scans(log: DriveLog, n: int) -> DriveLog:
    """``log`` up to its ``n``-th scan: the first ``n`` scans and the odometry until then."""
    t_end = log.scans.t_s[n - 1]
    keep = log.odometry.t_s <= t_end
    return dataclasses.replace(
        log,
        scans=ScanStream(t_s=log.scans.t_s[:n], ranges_m=log.scans.ranges_m[:n]),
        odometry=OdometryStream(t_s=log.odometry.t_s[keep], poses=log.odometry.poses[keep]),
    )
