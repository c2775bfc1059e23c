"""Reading camera frames: file paths are read lazily with OpenCV, arrays are used as given.

Colour images are returned as RGB (H, W, 3) uint8 (files are converted from OpenCV's BGR; arrays
must already be RGB); single-channel images as (H, W) with their own dtype (disparity is uint16).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from slam_engine.errors import LogFormatError

# Physical 2x2 filter layout (top-left first) of OpenCV's ``COLOR_BAYER_<pattern>2RGB`` names.
BAYER_LAYOUTS = {"BG": "RGGB", "GB": "GRBG", "RG": "BGGR", "GR": "GBRG"}


def read_frame(source: str | Path | np.ndarray, what: str) -> np.ndarray:
    """An image from a path or an array; ``what`` names it in errors (e.g. ``"stereo left frame 12"``)."""
    import cv2  # imported when used: OpenCV (~15 MB) only for camera data
    if isinstance(source, np.ndarray):
        image = source
    else:
        path = Path(source)
        if not path.is_file():
            raise LogFormatError("image file missing", path, what)
        loaded = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if loaded is None:
            raise LogFormatError("not a readable image", path, what)
        image = loaded
        if image.ndim == 3 and image.shape[2] == 4:
            image = cv2.cvtColor(image, cv2.COLOR_BGRA2RGB)
        elif image.ndim == 3:
            image = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    if image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] != 3) or image.size == 0:
        raise LogFormatError(f"image of shape {image.shape}, expected (H, W) or (H, W, 3)", None, what)
    return image


def to_uint8(image: np.ndarray) -> np.ndarray:
    """8-bit copy of an image, scaling integer types by their range and floats from [0, 1]."""
    if image.dtype == np.uint8:
        return image
    if np.issubdtype(image.dtype, np.integer):
        return (image.astype(np.float64) * (255.0 / np.iinfo(image.dtype).max)).round().astype(np.uint8)
    return np.clip(np.rint(image.astype(np.float64) * 255.0), 0, 255).astype(np.uint8)


def demosaic(image: np.ndarray, bayer_pattern: str | None) -> np.ndarray:
    """RGB image from a raw Bayer frame (OpenCV pattern name), or the image itself when
    ``bayer_pattern`` is None or the frame already has three channels."""
    import cv2  # imported when used: OpenCV (~15 MB) only for camera data
    if bayer_pattern is None or image.ndim == 3:
        return image
    if bayer_pattern not in BAYER_LAYOUTS:
        raise LogFormatError(f"unknown Bayer pattern {bayer_pattern!r}, expected one of "
                             f"{sorted(BAYER_LAYOUTS)}", None, "stereo.calibration.bayer_pattern")
    return cv2.cvtColor(to_uint8(image), getattr(cv2, f"COLOR_BAYER_{bayer_pattern}2RGB"))


def mosaic(rgb: np.ndarray, bayer_pattern: str) -> np.ndarray:
    """Raw single-channel Bayer frame (OpenCV pattern name) from an RGB image: the inverse of
    :func:`demosaic` up to interpolation."""
    layout = BAYER_LAYOUTS[bayer_pattern]
    raw = np.empty(rgb.shape[:2], dtype=rgb.dtype)
    channel = {"R": 0, "G": 1, "B": 2}
    for k, letter in enumerate(layout):
        r, c = divmod(k, 2)
        raw[r::2, c::2] = rgb[r::2, c::2, channel[letter]]
    return raw
