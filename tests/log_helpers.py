"""Helpers that cut real logs down for fast tests, and make small logs with a known quirk."""

from __future__ import annotations

import dataclasses
from pathlib import Path

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


def saturated_log(folder: Path) -> Path:
    """A simulated drive whose last 4 of every 180 ranges read 30 m, below the 50 m maximum: the reader
    takes that for the scanner's no-return code, warns and treats them as no return."""
    from slam_engine.simulation import simulate, write_simulated

    path = write_simulated(simulate("office", seed=3, rig="carmen-robot", max_duration_s=15.0), "carmen", folder)
    lines = []
    for line in path.read_text().splitlines():
        if line.startswith("FLASER "):
            words = line.split()
            beams = int(words[1])
            words[2 + beams - 4: 2 + beams] = ["30.000"] * 4
            line = " ".join(words)
        lines.append(line)
    path.write_text("\n".join(lines) + "\n")
    return path
