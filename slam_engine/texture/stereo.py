"""Stereo depth: rectify with the calibration, disparity with OpenCV's StereoSGBM, depth
``z = f * b / d`` and back-projection into the *rectified* left optical frame.

Once the ground height is known, only the rows the texture can use are rectified and matched
(:class:`GroundWindow`): those whose rays meet the ground band within the depth range, with a
margin of context for the matcher. On the car's cameras (1280 x 560, 1.58 m up, ground seen from
4 to 10 m) that is 219 of 560 rows. The rows are then matched at ``TextureConfig.stereo_width_scale`` of
their width (columns averaged): far ground is sampled densely across the drive, sparsely along it.

The rectified left optical frame differs from the left camera's optical frame by the rectification
rotation ``R_left`` (``X_rect = R_left @ X_cam``); :attr:`StereoRectifier.T_vehicle_from_rectified`
places it in the vehicle frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from slam_engine.config import TextureConfig
from slam_engine.errors import LogFormatError
from slam_engine.model.drive_log import StereoCalibration
from slam_engine.texture.calibration import homogeneous
from slam_engine.texture.images import demosaic, to_uint8


@dataclass(frozen=True)
class FramePoints:
    """Points seen in one camera frame: ``points_camera`` (N, 3) [m] in the frame that
    ``T_vehicle_from_camera`` places, with their ``colors`` (N, 3) RGB or (N,) gray uint8."""

    points_camera: np.ndarray
    colors: np.ndarray
    T_vehicle_from_camera: np.ndarray


@dataclass(frozen=True)
class GroundWindow:
    """The rows ``row_start:row_stop`` [px] of a rectified image pair worth matching for ground texture."""

    row_start: int
    row_stop: int


# Rows of context kept above and below the rows that can see the ground, beyond the block's half
# width: StereoSGBM's cost aggregation runs along image paths, so pixels next to a cut see less context.
WINDOW_MARGIN_ROWS = 16


class StereoRectifier:
    """Undistortion + rectification maps of one calibrated stereo pair (computed once)."""

    def __init__(self, calibration: StereoCalibration):
        import cv2  # imported when used: OpenCV (~15 MB) only for camera data
        self.calibration = calibration
        size = tuple(int(v) for v in calibration.image_size_wh)
        self._maps = [
            cv2.initUndistortRectifyMap(K, D, R, P[:, :3], size, cv2.CV_32FC1)
            for K, D, R, P in ((calibration.K_left, calibration.D_left, calibration.R_left, calibration.P_left),
                               (calibration.K_right, calibration.D_right, calibration.R_right, calibration.P_right))
        ]
        P = calibration.P_left
        self.fx_px, self.fy_px, self.cx_px, self.cy_px = float(P[0, 0]), float(P[1, 1]), float(P[0, 2]), float(P[1, 2])
        self.T_vehicle_from_rectified = calibration.T_vehicle_from_camera @ homogeneous(calibration.R_left.T, (0, 0, 0))

    def rectify(self, left: np.ndarray, right: np.ndarray, what: str = "stereo frame",
                rows: tuple[int, int] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Rectified (left, right) images, demosaiced to RGB first for raw Bayer cameras; only the
        rectified rows ``rows`` = (start, stop) when given."""
        import cv2  # imported when used: OpenCV (~15 MB) only for camera data
        w, h = self.calibration.image_size_wh
        start, stop = (0, h) if rows is None else rows
        out = []
        for side, image, (map_x, map_y) in (("left", left, self._maps[0]), ("right", right, self._maps[1])):
            if image.shape[:2] != (h, w):
                raise LogFormatError(f"{side} image is {image.shape[1]}x{image.shape[0]}, the calibration "
                                     f"says {w}x{h}", None, what)
            image = demosaic(to_uint8(image), self.calibration.bayer_pattern)
            out.append(cv2.remap(image, map_x[start:stop], map_y[start:stop], cv2.INTER_LINEAR,
                                 borderMode=cv2.BORDER_CONSTANT))
        return out[0], out[1]

    def ground_window(self, ground_z_m: float, config: TextureConfig) -> GroundWindow | None:
        """The rows (with the margin) where ground points (within ``config.ground_band_m`` of
        ``ground_z_m`` [m, vehicle frame], at depths ``config.min_depth_m`` .. ``max_depth_m``) can
        appear in the rectified left image; None when no pixel can see such a point."""
        w, h = (int(v) for v in self.calibration.image_size_wh)
        v, u = np.mgrid[0:h, 0:w].astype(np.float64)
        # a pixel's ray, per metre of depth, in the vehicle frame: only its height matters here
        R = self.T_vehicle_from_rectified[:3, :3]
        rise = R[2, 0] * (u - self.cx_px) / self.fx_px + R[2, 1] * (v - self.cy_px) / self.fy_px + R[2, 2]
        height0 = float(self.T_vehicle_from_rectified[2, 3])
        lo, hi = ground_z_m - config.ground_band_m, ground_z_m + config.ground_band_m
        # depths at which the ray is within the band, intersected with the depth range
        with np.errstate(divide="ignore", invalid="ignore"):
            a = (lo - height0) / rise
            b = (hi - height0) / rise
        near = np.maximum(np.minimum(a, b), config.min_depth_m)
        far = np.minimum(np.maximum(a, b), config.max_depth_m)
        level = np.abs(rise) < 1e-12  # a ray parallel to the ground: in the band at every depth or none
        inside = (height0 >= lo) & (height0 <= hi)
        near = np.where(level, config.min_depth_m if inside else np.inf, near)
        far = np.where(level, config.max_depth_m if inside else -np.inf, far)
        sees = near <= far
        if not sees.any():
            return None
        seen_rows = np.flatnonzero(sees.any(axis=1))
        margin = WINDOW_MARGIN_ROWS + config.sgbm_block_size // 2
        return GroundWindow(row_start=max(0, int(seen_rows[0]) - margin),
                            row_stop=min(h, int(seen_rows[-1]) + 1 + margin))


def compute_disparity(left_rect: np.ndarray, right_rect: np.ndarray, config: TextureConfig,
                      num_disparities: int | None = None) -> np.ndarray:
    """(H, W) float32 disparity [px] of rectified images with StereoSGBM; NaN where invalid.
    ``num_disparities`` (a multiple of 16) overrides ``config.sgbm_num_disparities``."""
    import cv2  # imported when used: OpenCV (~15 MB) only for camera data
    left_gray = _gray(left_rect)
    right_gray = _gray(right_rect)
    block = config.sgbm_block_size
    matcher = cv2.StereoSGBM.create(  # the same binding as the legacy cv2.StereoSGBM_create
        minDisparity=0,
        numDisparities=num_disparities or config.sgbm_num_disparities,
        blockSize=block,
        P1=8 * block * block,
        P2=32 * block * block,
        disp12MaxDiff=1,
        uniquenessRatio=config.sgbm_uniqueness_ratio,
        speckleWindowSize=config.sgbm_speckle_window,
        speckleRange=config.sgbm_speckle_range,
        mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY,
    )
    raw = matcher.compute(left_gray, right_gray)  # int16, disparity * 16
    disparity = raw.astype(np.float32) / 16.0
    disparity[raw <= 0] = np.nan
    return disparity


def depth_from_disparity(disparity_px: np.ndarray, focal_px: float, baseline_m: float) -> np.ndarray:
    """Depth along the optical axis ``z = f * b / d`` [m]; NaN where the disparity is invalid."""
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = (focal_px * baseline_m) / disparity_px
    depth[~(disparity_px > 0)] = np.nan
    return depth


def back_project(depth_m: np.ndarray, fx: float, fy: float, cx: float, cy: float, row0: int = 0) -> np.ndarray:
    """(H, W, 3) points [m] in the optical frame of a pinhole camera from a depth image whose first
    row is image row ``row0``."""
    h, w = depth_m.shape
    v, u = np.mgrid[row0:row0 + h, 0:w]
    return np.stack(((u - cx) * depth_m / fx, (v - cy) * depth_m / fy, depth_m), axis=-1)


def stereo_frame_points(left: np.ndarray, right: np.ndarray, rectifier: StereoRectifier, config: TextureConfig,
                        what: str = "stereo frame", window: GroundWindow | None = None) -> FramePoints:
    """Coloured 3-D points of one stereo pair within the configured depth range, in the rectified
    left optical frame; colours come from the rectified left image (gray for gray cameras). With a
    ``window`` (:meth:`StereoRectifier.ground_window`) only its rows are rectified and matched.
    With ``config.stereo_width_scale`` below 1 the rectified pair is narrowed (neighbouring columns
    averaged) before matching: one point per narrowed pixel."""
    rows = None if window is None else (window.row_start, window.row_stop)
    left_rect, right_rect = rectifier.rectify(left, right, what, rows)
    # pixel column u of the narrowed pair covers full-width column (u + 0.5) / scale - 0.5
    left_rect, right_rect, scale = _narrowed(left_rect, right_rect, config.stereo_width_scale)
    num_disparities = 16 * math.ceil(config.sgbm_num_disparities * scale / 16)
    disparity = compute_disparity(left_rect, right_rect, config, num_disparities) / scale  # full-width pixels
    depth = depth_from_disparity(disparity, rectifier.fx_px, rectifier.calibration.baseline_m)
    keep = (depth >= config.min_depth_m) & (depth <= config.max_depth_m)
    points = back_project(depth, rectifier.fx_px * scale, rectifier.fy_px, (rectifier.cx_px + 0.5) * scale - 0.5,
                          rectifier.cy_px, 0 if rows is None else rows[0])
    return FramePoints(points_camera=points[keep], colors=left_rect[keep],
                       T_vehicle_from_camera=rectifier.T_vehicle_from_rectified)


def _narrowed(left: np.ndarray, right: np.ndarray, scale: float) -> tuple[np.ndarray, np.ndarray, float]:
    """The pair narrowed to ``scale`` of its width (pixels averaged), and the scale it got (whole pixels)."""
    width = left.shape[1]
    narrow = max(1, round(width * scale))
    if narrow == width:
        return left, right, 1.0
    import cv2  # imported when used: OpenCV (~15 MB) only for camera data
    size = (narrow, left.shape[0])
    return (cv2.resize(left, size, interpolation=cv2.INTER_AREA), cv2.resize(right, size, interpolation=cv2.INTER_AREA),
            narrow / width)


def _gray(image: np.ndarray) -> np.ndarray:
    import cv2  # imported when used: OpenCV (~15 MB) only for camera data
    return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image
