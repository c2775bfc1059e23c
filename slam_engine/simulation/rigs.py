"""Simulated vehicles with their sensors: each rig mirrors the robot behind one log format, with the
calibration that format declares (``vehicle``, ``lidar``) and the hidden errors of the real sensors."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from slam_engine.formats.breezyslam import MINES_ROVER, urg_04lx
from slam_engine.formats.thor import EFFECTIVE_TRACK_M, THOR_VEHICLE, UTM_30LX
from slam_engine.model.drive_log import LidarModel, MotionModelKind, RgbdCalibration, StereoCalibration, VehicleModel
from slam_engine.texture.calibration import ece276a_car_stereo_calibration, thor_kinect_calibration

# UCSD ECE276A car calibration (param/Vehicle2Lidar.txt, Vehicle2FOG.txt), vehicle <- sensor.
CAR_R_VEHICLE_FROM_LIDAR = np.array([[0.00130201, 0.796097, 0.605167],
                                     [0.999999, -0.000419027, -0.00160026],
                                     [-0.00102038, 0.605169, -0.796097]])
CAR_T_VEHICLE_FROM_LIDAR_M = np.array([0.8349, -0.0126869, 1.76416])
CAR_T_VEHICLE_FROM_FOG_M = np.array([-0.335, -0.035, 0.78])


def transform(R: np.ndarray | None = None, t=(0.0, 0.0, 0.0)) -> np.ndarray:
    """4x4 transform from a rotation matrix and a translation [m]."""
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = R
    T[:3, 3] = t
    return T


@dataclass(frozen=True)
class Rig:
    """A vehicle, its sensors and their error model.

    ``vehicle``/``lidar`` are the *declared* calibration written into logs; ``true_track_m`` and
    ``wheel_scale_errors`` (per wheel, relative; their left/right difference of 0.1-0.3 % bends the
    wheel-only heading by roughly 10-30 deg over the office loop) make the real motion differ from it.
    Rates in Hz; ``None`` = sensor absent. ``stereo`` / ``rgbd``: the calibration of the rig's
    stereo pair / Kinect, which see the world's floor texture at ``camera_hz``.
    ``log_odometry_hz`` logs dead-reckoned odometry poses (CARMEN ODOM, ROS Odometry) instead of
    encoder ticks.
    """

    name: str
    vehicle: VehicleModel
    lidar: LidarModel
    scan_hz: float
    encoder_hz: float | None
    gyro_hz: float | None
    log_odometry_hz: float | None
    true_track_m: float
    wheel_scale_errors: tuple[float, ...]
    slip_noise: float  # relative sd of each wheel increment
    gyro_bias_rad_s: float
    gyro_noise_rad_s: float
    range_noise_m: float
    dropout_probability: float
    encoders_at_scan_times: bool = False  # BreezySLAM: ticks sampled on each scan line
    t0_s: float = 0.0
    turn_radius_m: float = 0.5
    lateral_accel_m_s2: float = 0.4
    accel_m_s2: float = 0.4
    default_scenario: str = "office"
    stereo: StereoCalibration | None = None
    rgbd: RgbdCalibration | None = None
    camera_hz: float | None = None
    # an interlaced LiDAR: scan k starts (k % interlace_phases) * interlace_step_rad later than the
    # model's start angle (the logs carry each scan's start angle)
    interlace_phases: int = 1
    interlace_step_rad: float = 0.0

    def scan_angle_offsets_rad(self, n_scans: int) -> np.ndarray | None:
        """(n_scans,) each scan's start-angle offset [rad]; None for a LiDAR whose beams never move."""
        if self.interlace_phases <= 1:
            return None
        return (np.arange(n_scans) % self.interlace_phases) * self.interlace_step_rad


def _two_wheels(ticks: float, d_left: float, d_right: float, track: float, name: str) -> VehicleModel:
    return VehicleModel(kind=MotionModelKind.DIFFERENTIAL, ticks_per_revolution=ticks,
                        wheel_diameters_m=(d_left, d_right), wheel_names=("left", "right"), track_width_m=track,
                        name=name)


def _deg(value: float) -> float:
    return float(np.radians(value))


def _rigs() -> dict[str, Rig]:
    return {
        "robot": Rig(
            "robot", _two_wheels(1024, 0.15, 0.15, 0.40, "lidarmap robot"),
            LidarModel(541, _deg(-135), _deg(0.5), 0.05, 20.0, transform(t=(0.15, 0.0, 0.30)), "270 deg lidar"),
            scan_hz=5, encoder_hz=50, gyro_hz=100, log_odometry_hz=None, true_track_m=0.40,
            wheel_scale_errors=(0.006, 0.004), slip_noise=0.02, gyro_bias_rad_s=0.004, gyro_noise_rad_s=0.01,
            range_noise_m=0.01, dropout_probability=0.01, t0_s=1_700_000_000.0),
        "carmen-robot": Rig(
            "carmen-robot", VehicleModel(kind=MotionModelKind.ODOMETRY, name="carmen robot"),
            LidarModel(180, _deg(-90), _deg(1.0), 0.0, 50.0, transform(t=(0.12, 0.0, 0.35)), "SICK LMS"),
            scan_hz=5, encoder_hz=None, gyro_hz=None, log_odometry_hz=20, true_track_m=0.45,
            wheel_scale_errors=(0.012, 0.010), slip_noise=0.02, gyro_bias_rad_s=0.0, gyro_noise_rad_s=0.0,
            range_noise_m=0.01, dropout_probability=0.005, t0_s=100.0),
        "mines-rover": Rig(
            "mines-rover", MINES_ROVER, urg_04lx(),
            scan_hz=10, encoder_hz=None, gyro_hz=None, log_odometry_hz=None, true_track_m=0.33,
            wheel_scale_errors=(0.008, 0.005), slip_noise=0.03, gyro_bias_rad_s=0.0, gyro_noise_rad_s=0.0,
            range_noise_m=0.01, dropout_probability=0.02, encoders_at_scan_times=True, t0_s=212.387282),
        "thor": Rig(
            "thor", THOR_VEHICLE, UTM_30LX,
            scan_hz=10, encoder_hz=40, gyro_hz=100, log_odometry_hz=None, true_track_m=EFFECTIVE_TRACK_M,
            wheel_scale_errors=(0.006, 0.004, 0.007, 0.004), slip_noise=0.08, gyro_bias_rad_s=0.0012,
            gyro_noise_rad_s=0.02, range_noise_m=0.01, dropout_probability=0.01, t0_s=1_298_445_274.54,
            rgbd=thor_kinect_calibration(), camera_hz=1.0),
        "car": Rig(
            "car", VehicleModel(kind=MotionModelKind.DIFFERENTIAL, ticks_per_revolution=4096,
                                wheel_diameters_m=(0.623479, 0.622806), wheel_names=("left", "right"),
                                track_width_m=1.52439, T_vehicle_from_gyro=transform(t=CAR_T_VEHICLE_FROM_FOG_M),
                                name="ECE276A car"),
            LidarModel(286, _deg(-5), _deg(190 / 285), 0.1, 80.0,
                       transform(CAR_R_VEHICLE_FROM_LIDAR, CAR_T_VEHICLE_FROM_LIDAR_M), "SICK LMS511"),
            scan_hz=10, encoder_hz=100, gyro_hz=100, log_odometry_hz=None, true_track_m=1.52439,
            wheel_scale_errors=(0.002, 0.001), slip_noise=0.01, gyro_bias_rad_s=0.0003, gyro_noise_rad_s=0.002,
            range_noise_m=0.03, dropout_probability=0.01, t0_s=1_544_582_648.0, turn_radius_m=8.0,
            lateral_accel_m_s2=2.0, accel_m_s2=1.5, default_scenario="campus",
            stereo=ece276a_car_stereo_calibration(), camera_hz=1.0),
        "ros-robot": Rig(
            "ros-robot", VehicleModel(kind=MotionModelKind.ODOMETRY, name="ROS robot"),
            LidarModel(360, _deg(-180), _deg(1.0), 0.15, 12.0, transform(t=(0.05, 0.0, 0.25)), "RPLIDAR"),
            scan_hz=5, encoder_hz=None, gyro_hz=100, log_odometry_hz=20, true_track_m=0.30,
            wheel_scale_errors=(0.006, 0.004), slip_noise=0.02, gyro_bias_rad_s=0.003, gyro_noise_rad_s=0.01,
            range_noise_m=0.01, dropout_probability=0.01, t0_s=1_700_000_000.0),
    }


def _with_interlaced(rigs: dict[str, Rig]) -> dict[str, Rig]:
    """``rigs`` plus ``carmen-interlaced``: the CARMEN robot with an interlaced SICK (four start angles
    0.25 deg apart, cycling), otherwise the same rig (same seed, same drive and noise)."""
    rigs["carmen-interlaced"] = dataclasses.replace(rigs["carmen-robot"], name="carmen-interlaced",
                                                    interlace_phases=4, interlace_step_rad=_deg(0.25))
    return rigs


RIGS: dict[str, Rig] = _with_interlaced(_rigs())
# The rig whose sensors each log format can hold.
FORMAT_RIGS = {"carmen": "carmen-robot", "breezyslam": "mines-rover", "thor": "thor", "ece276a-car": "car",
               "rosbag": "ros-robot", "drivelog": "robot"}
