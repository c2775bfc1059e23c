"""Streamed chunks -> a DriveLog (the session's calibration plus the messages of chunks 0..k), or
-> engine messages one at a time, for a live job that steps the filter as chunks arrive.

Message JSON follows api_schemas.drivelog (``type`` discriminator); a ``null`` range is a beam
with no return (``inf`` in the engine). Both conversions give the same values (float64 times and
poses, float32 ranges, int64 ticks), so a live job steps the filter through exactly what a job
over the whole DriveLog would.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np

from slam_engine.errors import LogFormatError
from slam_engine.formats.drivelog import lidar_from_json, lidar_to_json, vehicle_from_json, vehicle_to_json
from slam_engine.model.drive_log import (
    DriveLog,
    EncoderStream,
    GyroStream,
    LidarModel,
    OdometryStream,
    ScanStream,
    VehicleModel,
)
from slam_engine.model.messages import EncoderMessage, GyroMessage, Message, OdometryMessage, ScanMessage

# DriveLog.messages() puts messages with equal stamps in this order (odometry sources before scans)
MESSAGE_ORDER = {"encoder": 0, "gyro": 1, "odometry": 2, "scan": 3}


def vehicle_from_calibration(vehicle: dict[str, Any]) -> VehicleModel:
    """VehicleModel from a session's calibration (the .drivelog manifest's ``vehicle`` object;
    a null ``T_vehicle_from_gyro`` is the identity)."""
    return vehicle_from_json(_identity_if_null(vehicle, "T_vehicle_from_gyro"))


def lidar_from_calibration(lidar: dict[str, Any] | None) -> LidarModel | None:
    """LidarModel from a session's calibration (None without a LiDAR; a null mounting is the identity)."""
    return None if lidar is None else lidar_from_json(_identity_if_null(lidar, "T_vehicle_from_lidar"))


def calibration_from_log(log: DriveLog) -> dict[str, Any]:
    """The calibration JSON of a DriveLog (what a client sends when it streams that log)."""
    out: dict[str, Any] = {"vehicle": vehicle_to_json(log.vehicle)}
    if log.lidar is not None:
        out["lidar"] = lidar_to_json(log.lidar)
    return out


def _identity_if_null(section: dict[str, Any], key: str) -> dict[str, Any]:
    return {**section, key: np.eye(4).tolist()} if section.get(key) is None else section


def drive_log_from_messages(calibration: dict[str, Any], messages: Iterable[dict[str, Any]],
                            source: str = "stream") -> DriveLog:
    """Columnar DriveLog from time-ordered message dicts. Raises LogFormatError naming the message
    when one does not fit the calibration (wrong beam count, wrong wheel count)."""
    lidar = lidar_from_calibration(calibration.get("lidar"))
    vehicle = vehicle_from_calibration(calibration["vehicle"])
    cols: dict[str, list] = {k: [] for k in ("scan_t", "scan_r", "scan_a", "enc_t", "enc", "gyro_t", "gyro", "odo_t",
                                             "odo")}
    for i, m in enumerate(messages):
        kind = check_message(m, lidar, f"message {i}")
        if kind == "scan":
            cols["scan_t"].append(m["t_s"])
            cols["scan_r"].append([np.inf if r is None else r for r in m["ranges_m"]])
            cols["scan_a"].append(_angle_offset(m))
        elif kind == "encoder":
            cols["enc_t"].append(m["t_s"])
            cols["enc"].append(m["ticks"])
        elif kind == "gyro":
            cols["gyro_t"].append(m["t_s"])
            cols["gyro"].append(m["yaw_rate_rad_s"])
        else:
            cols["odo_t"].append(m["t_s"])
            cols["odo"].append([m["x_m"], m["y_m"], m["theta_rad"]])
    if cols["enc"] and len({len(t) for t in cols["enc"]}) > 1:
        raise LogFormatError("encoder messages carry different numbers of wheels", location="encoder messages")

    def times(key: str) -> np.ndarray:
        return np.asarray(cols[key], dtype=np.float64)

    offsets = times("scan_a") if any(a != 0.0 for a in cols["scan_a"]) else None
    return DriveLog(
        vehicle=vehicle, lidar=lidar,
        scans=ScanStream(times("scan_t"), np.asarray(cols["scan_r"], dtype=np.float32), offsets)
        if cols["scan_t"] else None,
        encoders=EncoderStream(times("enc_t"), np.asarray(cols["enc"], dtype=np.int64)) if cols["enc"] else None,
        gyro=GyroStream(times("gyro_t"), np.asarray(cols["gyro"], dtype=np.float64)) if cols["gyro"] else None,
        odometry=OdometryStream(times("odo_t"), np.asarray(cols["odo"], dtype=np.float64)) if cols["odo"] else None,
        source_format=source,
    )


def _angle_offset(m: dict[str, Any]) -> float:
    """A scan message's start angle beyond the lidar's [rad] (0 when it has none)."""
    offset = m.get("angle_offset_rad")
    return 0.0 if offset is None else float(np.float64(offset))


def check_message(m: dict[str, Any], lidar: LidarModel | None, location: str) -> str:
    """The message's type, once it is known to fit the calibration (LogFormatError at ``location``
    otherwise: an unknown type, a scan without a lidar or with the wrong number of ranges)."""
    kind = m.get("type")
    if kind not in MESSAGE_ORDER:
        raise LogFormatError(f"message type {kind!r} cannot be mapped from a stream", location=location)
    if kind == "scan":
        if lidar is None:
            raise LogFormatError("scan message but the session's calibration has no lidar", location=location)
        if len(m["ranges_m"]) != lidar.num_beams:
            raise LogFormatError(f"scan has {len(m['ranges_m'])} ranges, the lidar has {lidar.num_beams} beams",
                                 location=location)
    return kind


def in_log_order(messages: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Time-ordered messages in the order DriveLog.messages() would give them (equal stamps:
    encoders, gyro, odometry, then scans; otherwise as sent)."""
    return sorted(messages, key=lambda m: (m["t_s"], MESSAGE_ORDER.get(str(m.get("type")), len(MESSAGE_ORDER))))


def engine_message(m: dict[str, Any], lidar: LidarModel | None, location: str) -> Message:
    """One stream message as the engine's message (the values a DriveLog of it would hold)."""
    kind = check_message(m, lidar, location)
    t_s = float(np.float64(m["t_s"]))
    if kind == "scan":
        return ScanMessage(t_s=t_s, ranges_m=np.asarray([np.inf if r is None else r for r in m["ranges_m"]],
                                                        dtype=np.float32), angle_offset_rad=_angle_offset(m))
    if kind == "encoder":
        return EncoderMessage(t_s=t_s, ticks=np.asarray(m["ticks"], dtype=np.int64))
    if kind == "gyro":
        return GyroMessage(t_s=t_s, yaw_rate_rad_s=float(np.float64(m["yaw_rate_rad_s"])))
    return OdometryMessage(t_s=t_s, x_m=float(np.float64(m["x_m"])), y_m=float(np.float64(m["y_m"])),
                           theta_rad=float(np.float64(m["theta_rad"])))


def messages_of_log(log: DriveLog) -> list[dict[str, Any]]:
    """A DriveLog's messages as stream JSON dicts (time-ordered): what a streaming client sends (a scan's
    ``angle_offset_rad`` only where the log's scans carry their own start angles)."""
    per_scan = log.scans is not None and log.scans.angle_offset_rad is not None
    out: list[dict[str, Any]] = []
    for m in log.messages():
        if isinstance(m, ScanMessage):
            ranges = [None if not np.isfinite(r) else float(r) for r in np.asarray(m.ranges_m)]
            out.append({"type": "scan", "t_s": m.t_s, "ranges_m": ranges,
                        **({"angle_offset_rad": m.angle_offset_rad} if per_scan else {})})
        elif isinstance(m, EncoderMessage):
            out.append({"type": "encoder", "t_s": m.t_s, "ticks": [int(t) for t in m.ticks]})
        elif isinstance(m, GyroMessage):
            out.append({"type": "gyro", "t_s": m.t_s, "yaw_rate_rad_s": m.yaw_rate_rad_s})
        elif isinstance(m, OdometryMessage):
            out.append({"type": "odometry", "t_s": m.t_s, "x_m": m.x_m, "y_m": m.y_m, "theta_rad": m.theta_rad})
    return out
