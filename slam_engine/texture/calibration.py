"""Camera calibrations of the supported camera logs: the ECE276A car's stereo pair (parsed from its
``param`` folder) and the ECE276A/THOR robot's Kinect (published constants).

Frames: the vehicle frame has x forward, y left, z up; camera *optical* frames have z forward,
x right, y down. ``T_a_from_b`` maps points from frame b into frame a (4x4, metres).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from slam_engine.errors import LogFormatError
from slam_engine.model.drive_log import RgbdCalibration, StereoCalibration

# Rotation taking optical-frame coordinates (z forward, x right, y down) into the camera's body
# frame (x forward, y left, z up).
R_BODY_FROM_OPTICAL = np.array([[0.0, 0.0, 1.0],
                                [-1.0, 0.0, 0.0],
                                [0.0, -1.0, 0.0]])

# THOR / ECE276A PR2 Kinect v1 (course spec and docs/RobotConfiguration.pdf).
THOR_KINECT_POSITION_M = (0.18, 0.005, 0.36)
THOR_KINECT_RPY_RAD = (0.0, 0.36, 0.021)
THOR_KINECT_FOCAL_PX = 585.05108211
# The spec lists cu = 242.94140713 and cv = 315.83800193 with i/j pixel indices; the course's
# own sample code (``v, u = np.mgrid[...]``) pairs 315.838 with the image *column* and 242.941
# with the row, which also puts the principal point near the centre of the 640x480 image.
THOR_KINECT_CX_PX = 315.83800193
THOR_KINECT_CY_PX = 242.94140713
THOR_KINECT_IMAGE_WH = (640, 480)


# UCSD ECE276A car stereo pair (param/left_camera.yaml, right_camera.yaml, stereo_param.txt,
# Vehicle2Stereo.txt of the course data): 1280 x 560 raw Bayer "BG" frames.
CAR_STEREO_IMAGE_WH = (1280, 560)
CAR_STEREO_K_LEFT = ((816.90378992770002, 0.50510166700000003, 608.50726281690004),
                     (0.0, 811.56803828490001, 263.47599764440002), (0.0, 0.0, 1.0))
CAR_STEREO_D_LEFT = (-0.056143027800000002, 0.13952563200000001, -0.0012155906999999999,
                     -0.00097281389999999998, -0.080878168799999997)
CAR_STEREO_R_LEFT = ((0.99996942080938533, 0.00036208456669806118, -0.0078119357978017733),
                     (-0.00034412461339106772, 0.99999729518344416, 0.0023002617343453663),
                     (0.0078127475572218850, -0.0022975031148170580, 0.99996684067775188))
CAR_STEREO_K_RIGHT = ((813.78205539589999, 0.34880336220000002, 613.86419539320002),
                      (0.0, 808.52165574269998, 249.41049348650000), (0.0, 0.0, 1.0))
CAR_STEREO_D_RIGHT = (-0.054921981799999998, 0.14243657430000001, 0.000075412299999999996,
                      -0.00067560530000000001, -0.085665408299999996)
CAR_STEREO_R_RIGHT = ((0.99998812489422739, 0.0024089155522231892, -0.0042364131513853301),
                      (-0.0024186483057924992, 0.99999444433315865, -0.0022937835970734117),
                      (0.0042308640843048539, 0.0023040027516418276, 0.99998839561287933))
CAR_STEREO_FOCAL_PX = 775.37235550066748  # rectified (P) focal length and principal point
CAR_STEREO_RECT_CX_PX = 619.47309112548828
CAR_STEREO_RECT_CY_PX = 257.18049049377441
CAR_STEREO_RIGHT_TX_PX = -368.41758740842312  # P_right[0, 3] = -f * baseline, as calibrated
CAR_STEREO_BASELINE_M = 0.475143600050775
CAR_STEREO_R_VEHICLE_FROM_LEFT = ((-0.00680499, -0.0153215, 0.99985), (-0.999977, 0.000334627, -0.00680066),
                                  (-0.000230383, -0.999883, -0.0153234))
CAR_STEREO_T_VEHICLE_FROM_LEFT_M = (1.64239, 0.247401, 1.58411)


def rotation_from_rpy(roll_rad: float, pitch_rad: float, yaw_rad: float) -> np.ndarray:
    """3x3 rotation ``Rz(yaw) @ Ry(pitch) @ Rx(roll)`` (fixed-axis XYZ roll, pitch, yaw)."""
    cr, sr = np.cos(roll_rad), np.sin(roll_rad)
    cp, sp = np.cos(pitch_rad), np.sin(pitch_rad)
    cy, sy = np.cos(yaw_rad), np.sin(yaw_rad)
    Rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    Ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    Rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    return Rz @ Ry @ Rx


def homogeneous(R: np.ndarray, t: np.ndarray | tuple[float, float, float]) -> np.ndarray:
    """4x4 transform from a 3x3 rotation and a translation [m]."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=np.float64)
    return T


def thor_kinect_calibration() -> RgbdCalibration:
    """The ECE276A/THOR robot's Kinect: depth intrinsics and ``T_vehicle_from_camera``.

    The camera sits at (0.18, 0.005, 0.36) m from the robot centre with roll 0, pitch 0.36 rad
    (looking down) and yaw 0.021 rad; the returned transform places its optical frame.
    """
    R_vehicle_from_body = rotation_from_rpy(*THOR_KINECT_RPY_RAD)
    T_vehicle_from_camera = homogeneous(R_vehicle_from_body @ R_BODY_FROM_OPTICAL, THOR_KINECT_POSITION_M)
    return RgbdCalibration(
        image_size_wh=THOR_KINECT_IMAGE_WH,
        fx=THOR_KINECT_FOCAL_PX,
        fy=THOR_KINECT_FOCAL_PX,
        cx=THOR_KINECT_CX_PX,
        cy=THOR_KINECT_CY_PX,
        T_vehicle_from_camera=T_vehicle_from_camera,
        model="kinect_v1_thor",
    )


def ece276a_car_stereo_calibration() -> StereoCalibration:
    """The ECE276A car's stereo pair as its ``param`` folder states it (constants above): what
    :func:`load_ece276a_stereo_calibration` reads from the course data, for the simulated car."""
    f, cx, cy = CAR_STEREO_FOCAL_PX, CAR_STEREO_RECT_CX_PX, CAR_STEREO_RECT_CY_PX
    P_left = np.array([[f, 0.0, cx, 0.0], [0.0, f, cy, 0.0], [0.0, 0.0, 1.0, 0.0]])
    P_right = P_left.copy()
    P_right[0, 3] = CAR_STEREO_RIGHT_TX_PX
    return StereoCalibration(
        image_size_wh=CAR_STEREO_IMAGE_WH,
        K_left=np.array(CAR_STEREO_K_LEFT), D_left=np.array(CAR_STEREO_D_LEFT), R_left=np.array(CAR_STEREO_R_LEFT),
        P_left=P_left,
        K_right=np.array(CAR_STEREO_K_RIGHT), D_right=np.array(CAR_STEREO_D_RIGHT),
        R_right=np.array(CAR_STEREO_R_RIGHT), P_right=P_right,
        baseline_m=CAR_STEREO_BASELINE_M,
        T_vehicle_from_camera=homogeneous(np.array(CAR_STEREO_R_VEHICLE_FROM_LEFT), CAR_STEREO_T_VEHICLE_FROM_LEFT_M),
        bayer_pattern="BG",
    )


def write_camera_yaml(path: str | Path, image_size_wh: tuple[int, int], K: np.ndarray, D: np.ndarray,
                      R: np.ndarray, P: np.ndarray, camera_name: str) -> Path:
    """Write one camera's OpenCV/ROS calibration YAML (what :func:`load_ece276a_stereo_calibration`
    reads: image size, K, plumb_bob D, rectification R, projection P); returns the path."""
    import cv2  # imported when used: OpenCV (~15 MB) only for camera data
    storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    try:
        storage.write("image_width", int(image_size_wh[0]))
        storage.write("image_height", int(image_size_wh[1]))
        storage.write("camera_name", camera_name)
        storage.write("camera_matrix", np.asarray(K, dtype=np.float64).reshape(3, 3))
        storage.write("distortion_model", "plumb_bob")
        storage.write("distortion_coefficients", np.asarray(D, dtype=np.float64).reshape(1, -1))
        storage.write("rectification_matrix", np.asarray(R, dtype=np.float64).reshape(3, 3))
        storage.write("projection_matrix", np.asarray(P, dtype=np.float64).reshape(3, 4))
    finally:
        storage.release()
    return Path(path)


def load_ece276a_stereo_calibration(param_dir: str | Path) -> StereoCalibration:
    """Parse the ECE276A car's ``param`` folder into a :class:`StereoCalibration`.

    Reads ``left_camera.yaml`` / ``right_camera.yaml`` (OpenCV YAML: K, D, R, P),
    ``stereo_param.txt`` (baseline in mm) and ``Vehicle2Stereo.txt`` (R, T of the left camera's
    optical frame in the vehicle frame). The car's images are raw Bayer ("BG") frames.
    Raises :class:`LogFormatError` naming the file and field when something is missing or malformed.
    """
    folder = Path(param_dir)
    left = _read_camera_yaml(folder / "left_camera.yaml")
    right = _read_camera_yaml(folder / "right_camera.yaml")
    if left["image_size_wh"] != right["image_size_wh"]:
        raise LogFormatError(f"left image size {left['image_size_wh']} differs from right "
                             f"{right['image_size_wh']}", folder / "right_camera.yaml", "image_width")
    baseline_m = _read_baseline_m(folder / "stereo_param.txt")
    T_vehicle_from_camera = _read_extrinsic(folder / "Vehicle2Stereo.txt")
    return StereoCalibration(
        image_size_wh=left["image_size_wh"],
        K_left=left["K"], D_left=left["D"], R_left=left["R"], P_left=left["P"],
        K_right=right["K"], D_right=right["D"], R_right=right["R"], P_right=right["P"],
        baseline_m=baseline_m,
        T_vehicle_from_camera=T_vehicle_from_camera,
        bayer_pattern="BG",
    )


_YAML_MATRICES = {"K": ("camera_matrix", (3, 3)), "D": ("distortion_coefficients", None),
                  "R": ("rectification_matrix", (3, 3)), "P": ("projection_matrix", (3, 4))}


def _read_camera_yaml(path: Path) -> dict:
    """Image size and K, D, R, P of one camera from an OpenCV/ROS camera YAML file."""
    import cv2  # imported when used: OpenCV (~15 MB) only for camera data
    if not path.is_file():
        raise LogFormatError("calibration file missing", path)
    try:
        storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except cv2.error as exc:
        raise LogFormatError(f"not an OpenCV YAML file ({exc.err})", path) from exc
    try:
        if not storage.isOpened():
            raise LogFormatError("not an OpenCV YAML file", path)
        size = []
        for key in ("image_width", "image_height"):
            node = storage.getNode(key)
            if node.empty() or not (node.isInt() or node.isReal()) or node.real() <= 0:
                raise LogFormatError("missing or non-positive", path, key)
            size.append(int(node.real()))
        out: dict = {"image_size_wh": (size[0], size[1])}
        for name, (key, shape) in _YAML_MATRICES.items():
            node = storage.getNode(key)
            matrix = None if node.empty() or not node.isMap() else node.mat()
            if matrix is None:
                raise LogFormatError("missing or not an opencv-matrix", path, key)
            matrix = np.asarray(matrix, dtype=np.float64)
            if shape is not None and matrix.shape != shape:
                raise LogFormatError(f"shape {matrix.shape}, expected {shape}", path, key)
            if not np.all(np.isfinite(matrix)):
                raise LogFormatError("non-finite values", path, key)
            out[name] = matrix.ravel() if name == "D" else matrix
        return out
    finally:
        storage.release()


def _read_baseline_m(path: Path) -> float:
    """Stereo baseline [m] from a line such as ``Baseline of stereo cameras: 475.14 (mm)``."""
    text = _read_text(path)
    match = re.search(r"baseline[^:]*:\s*([-+0-9.eE]+)\s*\((mm|m)\)", text, re.IGNORECASE)
    if match is None:
        raise LogFormatError("no 'Baseline ...: <value> (mm)' line", path, "baseline")
    value = float(match.group(1)) * (1e-3 if match.group(2).lower() == "mm" else 1.0)
    if not 0.0 < value < 10.0:
        raise LogFormatError(f"baseline {value} m is not in (0, 10) m", path, "baseline")
    return value


def _read_extrinsic(path: Path) -> np.ndarray:
    """4x4 ``T_vehicle_from_sensor`` from the ``R: r11 ... r33`` and ``T: x y z`` lines of a
    ``Vehicle2*.txt`` file."""
    text = _read_text(path)
    R = _numbers_after(text, "R", 9, path).reshape(3, 3)
    t = _numbers_after(text, "T", 3, path)
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-3) or np.linalg.det(R) < 0:
        raise LogFormatError("R is not a rotation matrix", path, "R")
    return homogeneous(R, t)


def _numbers_after(text: str, key: str, count: int, path: Path) -> np.ndarray:
    match = re.search(rf"^\s*{key}\s*:(.*)$", text, re.MULTILINE)
    if match is None:
        raise LogFormatError(f"no '{key}:' line", path, key)
    try:
        values = np.array([float(v) for v in match.group(1).split()], dtype=np.float64)
    except ValueError as exc:
        raise LogFormatError(f"non-numeric value ({exc})", path, key) from exc
    if values.shape != (count,):
        raise LogFormatError(f"{values.size} numbers, expected {count}", path, key)
    return values


def _read_text(path: Path) -> str:
    try:
        return path.read_text(encoding="utf-8", errors="replace")
    except FileNotFoundError as exc:
        raise LogFormatError("calibration file missing", path) from exc
