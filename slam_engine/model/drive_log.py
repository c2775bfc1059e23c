"""The engine's input: a drive log as columnar, time-stamped streams plus the vehicle's calibration.

Every loader returns a :class:`DriveLog`; the simulator produces one; the service's streamed chunks
are converted into one. Units are normalised here: seconds, metres, radians.

Frames: the vehicle frame has x forward, y left, z up, origin at the vehicle's reference point
(rear axle or robot centre). ``T_a_from_b`` maps points from frame b into frame a (4x4, metres).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np

from slam_engine.errors import LogFormatError
from slam_engine.model.messages import (
    EncoderMessage,
    GyroMessage,
    Message,
    OdometryMessage,
    RgbdMessage,
    ScanMessage,
    StereoMessage,
)

# Physically absurd values no log may hold (loaders refuse them, naming the record and the value;
# the bounds are far beyond any real drive, so no real log's numbers change)
MAX_COORDINATE_M = 1e6  # |x|, |y| of a pose: 1000 km from the log's origin
MAX_ANGLE_RAD = 1e6  # |theta| of a pose (unwrapped headings grow, never this far)
MAX_TIME_S = 1e10  # |t|: beyond the year 2286 in Unix time
MAX_RANGE_M = 1e6  # a LiDAR range
MAX_YAW_RATE_RAD_S = 1e3  # a gyro's yaw rate: 160 turns a second


CHECK_BLOCK_VALUES = 1 << 20  # values checked at once: a check's copies stay small beside the array


def first_beyond(values: np.ndarray, limit: float) -> int | None:
    """Flat index of the first value that is NaN, infinite or beyond +-``limit``; None when all are fine
    (``limit`` inf: the first value not finite). Checked in blocks of rows (copies of about 8 MB)."""
    values = np.asarray(values)
    if values.ndim == 0:
        values = values.reshape(1)
    per_row = int(np.prod(values.shape[1:], dtype=np.int64))
    rows = max(1, CHECK_BLOCK_VALUES // max(per_row, 1))
    for start in range(0, len(values), rows):
        block = np.asarray(values[start:start + rows], dtype=np.float64).reshape(-1)
        bad = np.flatnonzero(~(np.isfinite(block) if limit == np.inf else np.abs(block) <= limit))
        if bad.size:
            return start * per_row + int(bad[0])
    return None


class MotionModelKind(StrEnum):
    """How the vehicle's motion is measured."""

    DIFFERENTIAL = "differential"  # two wheel encoders (left, right), optional gyro/FOG yaw
    SKID_STEER = "skid_steer"  # four wheel encoders (FR, FL, RR, RL) + IMU yaw rate
    ODOMETRY = "odometry"  # logged odometry poses (CARMEN ODOM, MRPT, ROS nav_msgs/Odometry)


@dataclass(frozen=True)
class LidarModel:
    """Geometry of a 2-D scanning LiDAR.

    Beam ``i`` points at ``angle_min_rad + i * angle_increment_rad`` in the LiDAR frame
    (counter-clockwise about its z axis, 0 = its x axis). Ranges outside
    ``[range_min_m, range_max_m]`` and ``inf`` mean "no return". ``time_increment_s``: time between
    the measurements of consecutive beams [s] (negative: the beams were swept in reverse order), where
    the log or the sensor's specification gives it; None = unknown (scans are not de-skewed).
    """

    num_beams: int
    angle_min_rad: float
    angle_increment_rad: float
    range_min_m: float
    range_max_m: float
    T_vehicle_from_lidar: np.ndarray = field(default_factory=lambda: np.eye(4))
    name: str = "lidar"
    time_increment_s: float | None = None

    @property
    def beam_angles_rad(self) -> np.ndarray:
        """(num_beams,) beam angles in the LiDAR frame [rad]."""
        return self.angle_min_rad + self.angle_increment_rad * np.arange(self.num_beams)


@dataclass(frozen=True)
class VehicleModel:
    """Calibration of the vehicle's odometry sensors.

    ``wheel_names`` gives the column order of :class:`EncoderStream` ticks, e.g.
    ``("left", "right")`` or ``("front_right", "front_left", "rear_right", "rear_left")``.
    ``track_width_m`` is the *effective* track width (skid-steer slip included).
    """

    kind: MotionModelKind
    ticks_per_revolution: float | None = None
    wheel_diameters_m: tuple[float, ...] | None = None
    wheel_names: tuple[str, ...] = ()
    track_width_m: float | None = None
    gyro_lowpass_hz: float | None = None
    T_vehicle_from_gyro: np.ndarray = field(default_factory=lambda: np.eye(4))
    name: str = "vehicle"


@dataclass(frozen=True)
class ScanStream:
    """LiDAR scans: ``t_s`` (N,) seconds, ``ranges_m`` (N, num_beams) float32; ``inf`` = no return.

    ``angle_offset_rad`` (N,) [rad], for a laser whose beam geometry changes from scan to scan: scan
    ``k``'s beam ``i`` points at ``angle_min_rad + angle_offset_rad[k] + i * angle_increment_rad``
    (an interlaced SICK cycles through start angles 0.25 deg apart). A scan with fewer beams than
    ``num_beams`` is padded with ``inf`` (no return) at its end. None: every scan has the model's
    geometry."""

    t_s: np.ndarray
    ranges_m: np.ndarray
    angle_offset_rad: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.t_s.shape[0])


@dataclass(frozen=True)
class EncoderStream:
    """Wheel encoders: ``t_s`` (N,) seconds, ``ticks`` (N, n_wheels) int64 *cumulative* counts."""

    t_s: np.ndarray
    ticks: np.ndarray

    def __len__(self) -> int:
        return int(self.t_s.shape[0])


@dataclass(frozen=True)
class GyroStream:
    """Yaw rate about the vehicle's z axis: ``t_s`` (N,) seconds, ``yaw_rate_rad_s`` (N,) rad/s.

    A FOG that reports yaw *deltas* is converted by its loader to rates (delta / dt).
    """

    t_s: np.ndarray
    yaw_rate_rad_s: np.ndarray

    def __len__(self) -> int:
        return int(self.t_s.shape[0])


@dataclass(frozen=True)
class OdometryStream:
    """Logged odometry poses: ``t_s`` (N,) seconds, ``poses`` (N, 3) [x_m, y_m, theta_rad] in the
    odometry frame (arbitrary origin, only increments are used)."""

    t_s: np.ndarray
    poses: np.ndarray

    def __len__(self) -> int:
        return int(self.t_s.shape[0])


@dataclass(frozen=True)
class StereoCalibration:
    """Rectification and placement of a stereo pair (OpenCV conventions, pixels and metres).

    ``T_vehicle_from_camera`` places the *left camera's optical frame* (z forward, x right, y down).
    ``bayer_pattern`` names the colour filter of raw single-channel images in OpenCV's
    ``COLOR_BAYER_<pattern>2RGB`` spelling ("BG", "GB", "RG", "GR"); None = already grayscale/colour.
    """

    image_size_wh: tuple[int, int]
    K_left: np.ndarray
    D_left: np.ndarray
    R_left: np.ndarray
    P_left: np.ndarray
    K_right: np.ndarray
    D_right: np.ndarray
    R_right: np.ndarray
    P_right: np.ndarray
    baseline_m: float
    T_vehicle_from_camera: np.ndarray
    bayer_pattern: str | None = None


@dataclass(frozen=True)
class StereoStream:
    """Stereo image pairs: ``t_s`` (N,); images are file paths (read lazily) or arrays."""

    t_s: np.ndarray
    left_images: Sequence[str | np.ndarray]
    right_images: Sequence[str | np.ndarray]
    calibration: StereoCalibration

    def __len__(self) -> int:
        return int(self.t_s.shape[0])


@dataclass(frozen=True)
class RgbdCalibration:
    """A Kinect-style RGB-D camera: depth intrinsics, the disparity-to-depth model and placement.

    ``T_vehicle_from_camera`` places the depth camera's optical frame (z forward, x right, y down).
    """

    image_size_wh: tuple[int, int]
    fx: float
    fy: float
    cx: float
    cy: float
    T_vehicle_from_camera: np.ndarray
    model: str = "kinect_v1_thor"


@dataclass(frozen=True)
class RgbdStream:
    """Disparity (or depth) images and RGB images with their own timestamps."""

    depth_t_s: np.ndarray
    depth_images: Sequence[str | np.ndarray]
    rgb_t_s: np.ndarray
    rgb_images: Sequence[str | np.ndarray]
    calibration: RgbdCalibration

    def __len__(self) -> int:
        return int(self.depth_t_s.shape[0])


@dataclass
class DriveLog:
    """A whole drive: calibration plus every stream, each sorted by time.

    Streams that a log lacks are ``None``. With no scans the engine can only dead-reckon; with
    no odometry source (encoders or logged odometry) it cannot run and says so.
    """

    vehicle: VehicleModel
    lidar: LidarModel | None = None
    scans: ScanStream | None = None
    encoders: EncoderStream | None = None
    gyro: GyroStream | None = None
    odometry: OdometryStream | None = None
    stereo: StereoStream | None = None
    rgbd: RgbdStream | None = None
    source_format: str = "unknown"
    source_path: str | None = None
    warnings: list[str] = field(default_factory=list)

    def streams(self) -> dict[str, int]:
        """Names of the streams present and their message counts."""
        named = {
            "scans": self.scans,
            "encoders": self.encoders,
            "gyro": self.gyro,
            "odometry": self.odometry,
            "stereo": self.stereo,
            "rgbd": self.rgbd,
        }
        return {name: len(stream) for name, stream in named.items() if stream is not None}

    def time_span_s(self) -> tuple[float, float] | None:
        """(first, last) timestamp over all streams [s], or None for an empty log."""
        stamps = [
            s
            for s in (
                getattr(self.scans, "t_s", None),
                getattr(self.encoders, "t_s", None),
                getattr(self.gyro, "t_s", None),
                getattr(self.odometry, "t_s", None),
                getattr(self.stereo, "t_s", None),
                getattr(self.rgbd, "depth_t_s", None),
            )
            if s is not None and len(s)
        ]
        if not stamps:
            return None
        return float(min(s[0] for s in stamps)), float(max(s[-1] for s in stamps))

    def summary(self) -> dict:
        """Format, streams with counts, time span: what a user sees after an upload."""
        span = self.time_span_s()
        return {
            "format": self.source_format,
            "vehicle": self.vehicle.kind.value,
            "streams": self.streams(),
            "time_span_s": None if span is None else [span[0], span[1]],
            "duration_s": None if span is None else span[1] - span[0],
            "lidar_beams": None if self.lidar is None else self.lidar.num_beams,
            "warnings": list(self.warnings),
        }

    def check_values(self, location_of: dict[str, Callable[[int], str]] | None = None) -> None:
        """LogFormatError naming the stream's record and the value when a stamp, pose, range or yaw rate
        is not finite or physically absurd (beyond the ``MAX_*`` bounds above); ``location_of`` names a
        stream's record ``i`` (default ``"<stream> record <i>"``). Infinite ranges (no return) are fine."""
        location_of = location_of or {}

        def check(name: str, what: str, values: np.ndarray, limit: float, unit: str, columns: int = 1,
                  allow_inf: bool = False) -> None:
            values = np.asarray(values, dtype=np.float64)
            if allow_inf:
                values = np.where(np.isposinf(values), 0.0, values)
            bad = first_beyond(values, limit)
            if bad is None:
                return
            record = bad // columns
            where = location_of.get(name, lambda i: f"{name} record {i}")(record)
            raise LogFormatError(f"{what} is {values.reshape(-1)[bad]:g} {unit}, beyond +-{limit:g} {unit}",
                                 path=self.source_path, location=where)

        for name in ("scans", "encoders", "gyro", "odometry"):
            stream = getattr(self, name)
            if stream is not None:
                check(name, f"{name} timestamp", stream.t_s, MAX_TIME_S, "s")
        if self.odometry is not None and len(self.odometry):
            poses = np.asarray(self.odometry.poses, dtype=np.float64).reshape(-1, 3)
            check("odometry", "odometry position", poses[:, :2], MAX_COORDINATE_M, "m", columns=2)
            check("odometry", "odometry heading", poses[:, 2], MAX_ANGLE_RAD, "rad")
        if self.scans is not None and len(self.scans):
            ranges = np.asarray(self.scans.ranges_m)
            check("scans", "range", ranges, MAX_RANGE_M, "m", columns=ranges.shape[1] if ranges.ndim == 2 else 1,
                  allow_inf=True)
        if self.scans is not None and self.scans.angle_offset_rad is not None:
            check("scans", "scan angle offset", self.scans.angle_offset_rad, 2 * np.pi, "rad")
        if self.gyro is not None:
            check("gyro", "yaw rate", self.gyro.yaw_rate_rad_s, MAX_YAW_RATE_RAD_S, "rad/s")

    def between(self, start_s: float, end_s: float) -> DriveLog:
        """The part of the drive with stamps in ``[start_s, end_s)`` [s]: its scans, wheel ticks, gyro and
        odometry (camera streams are left out). Cumulative ticks and logged odometry keep their values:
        only their increments are used, so the part starts wherever its own odometry says, as a drive
        switched off and on again."""

        def cut(stream, **arrays):
            if stream is None:
                return None
            keep = (stream.t_s >= start_s) & (stream.t_s < end_s)
            return dataclasses.replace(stream, t_s=stream.t_s[keep], **{k: v[keep] for k, v in arrays.items()})

        return dataclasses.replace(
            self, scans=None if self.scans is None else cut(self.scans, ranges_m=self.scans.ranges_m),
            encoders=None if self.encoders is None else cut(self.encoders, ticks=self.encoders.ticks),
            gyro=None if self.gyro is None else cut(self.gyro, yaw_rate_rad_s=self.gyro.yaw_rate_rad_s),
            odometry=None if self.odometry is None else cut(self.odometry, poses=self.odometry.poses),
            stereo=None, rgbd=None, warnings=list(self.warnings))

    def messages(self) -> Iterator[Message]:
        """All messages, merged into one time-ordered stream (stable for equal stamps:
        odometry sources first, then scans, then cameras)."""
        sources: list[tuple[np.ndarray, int, object]] = []
        for order, stream in enumerate(
            (self.encoders, self.gyro, self.odometry, self.scans, self.stereo, self.rgbd)
        ):
            if stream is None:
                continue
            t = stream.depth_t_s if isinstance(stream, RgbdStream) else stream.t_s
            sources.append((np.asarray(t, dtype=np.float64), order, stream))
        if not sources:
            return
        all_t = np.concatenate([t for t, _, _ in sources])
        all_src = np.concatenate([np.full(len(t), k) for k, (t, _, _) in enumerate(sources)])
        all_idx = np.concatenate([np.arange(len(t)) for t, _, _ in sources])
        all_order = np.concatenate([np.full(len(t), o) for t, o, _ in sources])
        ordering = np.lexsort((all_order, all_t))
        for k in ordering:
            yield _message_at(sources[all_src[k]][2], int(all_idx[k]))


def _message_at(stream: object, i: int) -> Message:
    """Message ``i`` of a columnar stream."""
    if isinstance(stream, EncoderStream):
        return EncoderMessage(t_s=float(stream.t_s[i]), ticks=stream.ticks[i])
    if isinstance(stream, GyroStream):
        return GyroMessage(t_s=float(stream.t_s[i]), yaw_rate_rad_s=float(stream.yaw_rate_rad_s[i]))
    if isinstance(stream, OdometryStream):
        x, y, theta = stream.poses[i]
        return OdometryMessage(t_s=float(stream.t_s[i]), x_m=float(x), y_m=float(y), theta_rad=float(theta))
    if isinstance(stream, ScanStream):
        if stream.angle_offset_rad is None:
            return ScanMessage(t_s=float(stream.t_s[i]), ranges_m=stream.ranges_m[i])
        return ScanMessage(t_s=float(stream.t_s[i]), ranges_m=stream.ranges_m[i],
                           angle_offset_rad=float(stream.angle_offset_rad[i]))
    if isinstance(stream, StereoStream):
        return StereoMessage(t_s=float(stream.t_s[i]), left=stream.left_images[i], right=stream.right_images[i])
    if isinstance(stream, RgbdStream):
        return RgbdMessage(t_s=float(stream.depth_t_s[i]), depth=stream.depth_images[i])
    raise TypeError(f"not a stream: {type(stream).__name__}")
