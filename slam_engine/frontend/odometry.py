"""Dead reckoning: turn a drive log's odometry sources (wheel encoders, gyro, logged odometry) into
one odometry pose track, streamed message by message or for a whole log at its scan times (and
for format writers, at the odometry stamps).

The odometry frame is arbitrary; only its increments matter. Which source drives the track:
logged odometry for ``MotionModelKind.ODOMETRY`` (or when a log has no encoders), otherwise the
wheel encoders, with the gyro's yaw for the heading when the log has one.
"""

from __future__ import annotations

import numpy as np

from slam_engine.errors import ConfigError
from slam_engine.frontend.motion_models import (
    differential_drive_increments,
    lowpass_alpha,
    skid_steer_increments,
    skid_steer_sides,
    wheel_distances_m,
)
from slam_engine.model.drive_log import DriveLog, MotionModelKind, OdometryStream, VehicleModel
from slam_engine.model.messages import EncoderMessage, GyroMessage, Message, OdometryMessage
from slam_engine.model.poses import compose, interpolate, relative
from slam_engine.model.result import Trajectory

SKID_STEER_ORDER = ("front_right", "front_left", "rear_right", "rear_left")


def odometry_source(log: DriveLog) -> str:
    """``"encoders"`` or ``"odometry"``: the stream that drives dead reckoning for ``log``.
    Raises :class:`ConfigError` when the log has neither."""
    has_encoders = log.encoders is not None and len(log.encoders) > 0
    has_odometry = log.odometry is not None and len(log.odometry) > 0
    if log.vehicle.kind == MotionModelKind.ODOMETRY and has_odometry:
        return "odometry"
    if has_encoders:
        return "encoders"
    if has_odometry:
        return "odometry"
    raise ConfigError(
        f"the log ({log.source_format}, {log.source_path or 'in memory'}) has no odometry source: "
        "it needs wheel encoders or logged odometry poses to run SLAM"
    )


def _wheel_order(vehicle: VehicleModel, n_wheels: int) -> np.ndarray:
    """Column indices that put the encoder columns into (left, right) or (FR, FL, RR, RL) order."""
    names = [name.lower() for name in vehicle.wheel_names]
    if vehicle.kind == MotionModelKind.SKID_STEER:
        if len(names) == 4 and set(names) == set(SKID_STEER_ORDER):
            return np.array([names.index(w) for w in SKID_STEER_ORDER])
        return np.arange(4)
    if len(names) == 2 and any("left" in n for n in names) and any("right" in n for n in names):
        left = next(i for i, n in enumerate(names) if "left" in n)
        return np.array([left, 1 - left])
    return np.arange(n_wheels)


class OdometryIntegrator:
    """Streaming dead reckoning. Feed it odometry-source messages in time order with
    :meth:`update`; read the pose at a time with :meth:`pose_at` (linear between the last two
    updates). Before the first message the pose is unknown (``t_s is None``)."""

    def __init__(self, vehicle: VehicleModel, source: str, use_gyro: bool):
        self.vehicle = vehicle
        self.source = source
        self.use_gyro = use_gyro
        self.t_s: float | None = None
        self.pose = np.zeros(3)
        self.prev_t_s: float | None = None
        self.prev_pose = np.zeros(3)
        self._ticks: np.ndarray | None = None
        self._gyro_t: float | None = None
        self._gyro_yaw = 0.0
        self._gyro_rate = 0.0
        self._yaw_at_last_ticks = 0.0
        self._sides_m = np.zeros(2)  # cumulative (left, right) side distances [m] since the first ticks
        self._gyro_sign = 1.0 if float(np.asarray(vehicle.T_vehicle_from_gyro)[2, 2]) >= 0 else -1.0
        if source == "encoders":
            self._check_encoder_calibration()

    def _check_encoder_calibration(self) -> None:
        v = self.vehicle
        n_wheels = 4 if v.kind == MotionModelKind.SKID_STEER else 2
        if not v.ticks_per_revolution or v.ticks_per_revolution <= 0:
            raise ConfigError(f"vehicle {v.name!r}: wheel encoders need ticks_per_revolution > 0")
        self._ticks_per_revolution: float = v.ticks_per_revolution
        if not v.wheel_diameters_m or len(v.wheel_diameters_m) not in (1, n_wheels):
            raise ConfigError(f"vehicle {v.name!r}: wheel encoders need {n_wheels} wheel diameters, "
                              f"got {v.wheel_diameters_m!r}")
        if not self.use_gyro and (not v.track_width_m or v.track_width_m <= 0):
            raise ConfigError(f"vehicle {v.name!r}: without a gyro the heading comes from the wheels, "
                              "which needs track_width_m > 0")
        self._order = _wheel_order(v, n_wheels)
        diameters = np.asarray(v.wheel_diameters_m, dtype=np.float64)
        self._diameters = np.broadcast_to(diameters, (n_wheels,))[self._order]

    def _gyro_yaw_at(self, t_s: float) -> float:
        if self._gyro_t is None:
            return self._gyro_yaw
        return self._gyro_yaw + self._gyro_rate * (t_s - self._gyro_t)

    def _advance(self, t_s: float, pose: np.ndarray) -> None:
        self.prev_t_s, self.prev_pose = self.t_s, self.pose
        self.t_s, self.pose = t_s, pose

    def update(self, message: Message) -> bool:
        """Take one message; returns True when the odometry pose was advanced."""
        if isinstance(message, GyroMessage):
            if self.use_gyro:
                self._gyro_yaw = self._gyro_yaw_at(message.t_s)
                dt = 0.0 if self._gyro_t is None else message.t_s - self._gyro_t
                rate = self._gyro_sign * message.yaw_rate_rad_s
                if self._gyro_t is None:
                    self._gyro_rate = rate
                else:
                    self._gyro_rate += lowpass_alpha(dt, self.vehicle.gyro_lowpass_hz) * (rate - self._gyro_rate)
                self._gyro_t = message.t_s
            return False
        if isinstance(message, OdometryMessage) and self.source == "odometry":
            pose = np.array([message.x_m, message.y_m, message.theta_rad])
            if self.t_s is None:
                self._advance(message.t_s, pose)
                self.prev_t_s, self.prev_pose = message.t_s, pose
            else:
                self._advance(message.t_s, pose)
            return True
        if isinstance(message, EncoderMessage) and self.source == "encoders":
            ticks = np.asarray(message.ticks, dtype=np.int64)[self._order]
            yaw = self._gyro_yaw_at(message.t_s)
            if self._ticks is None:
                self._ticks = ticks
                self._yaw_at_last_ticks = yaw
                self._advance(message.t_s, self.pose)
                self.prev_t_s = message.t_s
                return True
            meters = wheel_distances_m((ticks - self._ticks)[None, :], self._ticks_per_revolution,
                                       self._diameters)
            delta_yaw = np.array([yaw - self._yaw_at_last_ticks]) if self.use_gyro and self._gyro_t is not None \
                else None
            if self.vehicle.kind == MotionModelKind.SKID_STEER:
                inc = skid_steer_increments(meters, self.vehicle.track_width_m or 0.0, delta_yaw)
                left, right = skid_steer_sides(meters[0])
            else:
                inc = differential_drive_increments(meters[:, 0], meters[:, 1], self.vehicle.track_width_m or 0.0,
                                                    delta_yaw)
                left, right = meters[0, 0], meters[0, 1]
            self._sides_m += (float(left), float(right))
            self._ticks = ticks
            self._yaw_at_last_ticks = yaw
            self._advance(message.t_s, compose(self.pose, inc[0]))
            return True
        return False

    def wheel_check(self) -> np.ndarray | None:
        """``[left_m, right_m, yaw_rad]`` at the last encoder message: the cumulative side distances
        since the first ticks and the gyro's (unwrapped) yaw, for cross-checking the wheels against the
        gyro (:func:`slam_engine.frontend.odometry_noise.wheel_distance_sd_m`); None unless the heading comes
        from a gyro and the distance from encoders."""
        if self.source != "encoders" or not self.use_gyro or self._ticks is None or self._gyro_t is None:
            return None
        return np.array([self._sides_m[0], self._sides_m[1], self._yaw_at_last_ticks])

    def pose_at(self, t_s: float) -> np.ndarray:
        """Odometry pose at ``t_s``: interpolated between the last two updates, the last pose
        after them."""
        if self.t_s is None:
            raise ValueError("no odometry yet")
        if self.prev_t_s is None or self.t_s <= self.prev_t_s or t_s >= self.t_s:
            return self.pose.copy()
        return interpolate(np.array([self.prev_t_s, self.t_s]), np.stack([self.prev_pose, self.pose]),
                           np.array([t_s]))[0]


def make_integrator(log: DriveLog) -> OdometryIntegrator:
    """The integrator for ``log``'s odometry source (raises ConfigError when there is none)."""
    source = odometry_source(log)
    use_gyro = log.gyro is not None and len(log.gyro) > 0
    return OdometryIntegrator(log.vehicle, source, use_gyro)


def odometry_track(log: DriveLog) -> Trajectory:
    """The dead-reckoned odometry pose at every odometry-source message of ``log``."""
    integrator = make_integrator(log)
    odometry_only = DriveLog(vehicle=log.vehicle, encoders=log.encoders, gyro=log.gyro, odometry=log.odometry)
    t_list: list[float] = []
    poses: list[np.ndarray] = []
    for message in odometry_only.messages():
        if integrator.update(message):
            assert integrator.t_s is not None  # an update that advanced the pose set its time
            t_list.append(integrator.t_s)
            poses.append(integrator.pose)
    return Trajectory(t_s=np.asarray(t_list, dtype=np.float64),
                      poses=np.asarray(poses, dtype=np.float64).reshape(-1, 3))


def dead_reckoning(log: DriveLog) -> Trajectory:
    """Odometry-only trajectory, one pose per scan (per odometry message when the log has no scans),
    in the map frame (the first pose at the origin)."""
    track = odometry_track(log)
    if len(track) == 0:
        raise ConfigError("the log's odometry source has no messages")
    if log.scans is not None and len(log.scans) > 0:
        t_query = np.asarray(log.scans.t_s, dtype=np.float64)
        poses = interpolate(track.t_s, track.poses, t_query)
    else:
        t_query, poses = track.t_s, track.poses
    return Trajectory(t_s=t_query.copy(), poses=relative(poses[0], poses))


def odometry_poses(log: DriveLog) -> OdometryStream:
    """The log's own odometry poses, else poses dead-reckoned from its encoders (and gyro) at
    the encoder stamps, starting at the origin: what a format that stores odometry writes."""
    if log.odometry is not None and len(log.odometry) > 0:
        return log.odometry
    track = odometry_track(log)
    return OdometryStream(t_s=track.t_s, poses=track.poses)


def side_distances_m(vehicle: VehicleModel, ticks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cumulative (left, right) travelled distance [m] from (N, n_wheels) cumulative ticks; a skid
    steer's side is the mean of its two wheels."""
    skid = vehicle.kind == MotionModelKind.SKID_STEER
    n_wheels = 4 if skid else 2
    if not vehicle.ticks_per_revolution or not vehicle.wheel_diameters_m:
        raise ConfigError(f"vehicle {vehicle.name!r}: wheel distances need ticks_per_revolution and "
                          "wheel_diameters_m")
    order = _wheel_order(vehicle, n_wheels)
    diameters = np.broadcast_to(np.asarray(vehicle.wheel_diameters_m, dtype=np.float64), (n_wheels,))[order]
    metres = wheel_distances_m(np.asarray(ticks)[:, order], vehicle.ticks_per_revolution, diameters)
    if skid:
        return skid_steer_sides(metres)
    return metres[:, 0], metres[:, 1]


def integrate_yaw_rate(t_s: np.ndarray, yaw_rate_rad_s: np.ndarray, at_t_s: np.ndarray) -> np.ndarray:
    """Heading [rad] (unwrapped, 0 at the first gyro sample) at ``at_t_s`` by trapezoidal
    integration of the raw yaw rate (no low-pass, no mounting sign)."""
    t_s = np.asarray(t_s, dtype=np.float64)
    rate = np.asarray(yaw_rate_rad_s, dtype=np.float64)
    heading = np.concatenate([[0.0], np.cumsum(0.5 * (rate[1:] + rate[:-1]) * np.diff(t_s))])
    return np.interp(at_t_s, t_s, heading)
