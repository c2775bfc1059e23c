"""Drive-log formats: detect a log's format from its content, load it into a DriveLog, write one.

Each format lives in its own module (``carmen``, ``breezyslam``, ``thor``, ``ece276a_car``,
``rosbag``, ``drivelog``) with three functions: ``sniff(path) -> bool`` (does the content look like
this format?), ``load(path) -> DriveLog`` and ``write(log, out_dir) -> Path``. Modules are imported
only when used, so an optional heavy dependency (rosbags) costs nothing to the other formats.

A *log* is a file or a folder: a folder holding exactly one log file (as ``lidarmap simulate``
writes it, next to ``ground_truth.txt``) is loaded as that file.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType

import numpy as np

from slam_engine.errors import LogFormatError, UnknownFormatError
from slam_engine.model.drive_log import DriveLog


@dataclass(frozen=True)
class FormatInfo:
    """A supported drive-log format as users see it."""

    name: str
    description: str
    extensions: tuple[str, ...]
    can_write: bool


_FORMATS: tuple[FormatInfo, ...] = (
    FormatInfo("carmen", "CARMEN text log (.clf/.log, optionally gzipped): ODOM, FLASER/RLASER, "
               "ROBOTLASER1, RAWLASER1-4, PARAM", (".clf", ".log", ".clf.gz", ".log.gz", ".gz"), True),
    FormatInfo("breezyslam", "BreezySLAM / CoreSLAM .dat: microsecond stamps, cumulative wheel ticks, "
               "Hokuyo URG-04LX ranges in mm", (".dat",), True),
    FormatInfo("thor", "UPenn ESE650 (.mat) / UCSD ECE276A (.npz) THOR skid-steer robot: "
               "EncodersNN, imuNN, HokuyoNN, KinectNN in one folder", (".mat", ".npz"), True),
    FormatInfo("ece276a-car", "UCSD ECE276A car: sensor_data/{encoder,fog,lidar}.csv, param/*.txt, "
               "stereo_images/", ("",), True),
    FormatInfo("rosbag", "ROS 2 bag (sqlite3 or MCAP storage): LaserScan, Odometry, Imu, tf_static",
               (".mcap", ".db3"), True),
    FormatInfo("drivelog", "lidarmap drive-log archive: zip with manifest.json and .npy columns",
               (".drivelog", ".zip"), True),
)
_MODULES = {
    "carmen": "slam_engine.formats.carmen",
    "breezyslam": "slam_engine.formats.breezyslam",
    "thor": "slam_engine.formats.thor",
    "ece276a-car": "slam_engine.formats.ece276a_car",
    "rosbag": "slam_engine.formats.rosbag",
    "drivelog": "slam_engine.formats.drivelog",
}
# Most specific first: folder formats, then archives, then text formats with loose sniffers.
_DETECTION_ORDER = ("drivelog", "rosbag", "thor", "ece276a-car", "carmen", "breezyslam")
# Side files that lidarmap simulate / products write next to a log; never a log themselves.
_SIDE_FILES = {"ground_truth.txt", "ground_texture.json", "README.md", "config.json"}


def list_formats() -> list[FormatInfo]:
    """Every supported format, in a stable order."""
    return list(_FORMATS)


def format_info(name: str) -> FormatInfo:
    """The FormatInfo of ``name``; UnknownFormatError when there is none."""
    for info in _FORMATS:
        if info.name == name:
            return info
    known = ", ".join(f.name for f in _FORMATS)
    raise UnknownFormatError(f"unknown format {name!r}; known formats: {known}")


def _module(name: str) -> ModuleType:
    format_info(name)
    return importlib.import_module(_MODULES[name])


def _installed_modules() -> dict[str, ModuleType]:
    """Format modules that exist in this build, in detection order."""
    found = {}
    for name in _DETECTION_ORDER:
        try:
            found[name] = importlib.import_module(_MODULES[name])
        except ModuleNotFoundError as error:
            if error.name != _MODULES[name]:
                raise
    return found


def _sniff(path: Path) -> str | None:
    for name, module in _installed_modules().items():
        if module.sniff(path):
            return name
    return None


def detect_format(path: str | Path) -> str:
    """Name of the format of the log at ``path`` (file or folder), judged from its content.

    A folder that is not itself a log (a THOR set folder, a car log, a ROS 2 bag) but holds exactly
    one log file is detected as that file's format.
    """
    return _resolve(Path(path))[0]


def _resolve(path: Path) -> tuple[str, Path]:
    """(format, path to hand to its loader)."""
    if not path.exists():
        raise LogFormatError("no such file or folder", path=str(path))
    name = _sniff(path)
    if name is not None:
        return name, path
    if path.is_dir():
        candidates = []
        for child in sorted(path.iterdir()):
            if child.name in _SIDE_FILES or child.suffix == ".relations" or child.name.startswith("."):
                continue
            child_format = _sniff(child)
            if child_format is not None:
                candidates.append((child_format, child))
        if len(candidates) == 1:
            return candidates[0]
        if len(candidates) > 1:
            listed = ", ".join(f"{c.name} ({f})" for f, c in candidates)
            raise UnknownFormatError(f"folder holds several logs, name one of them: {listed}", path=str(path))
    known = ", ".join(f.name for f in _FORMATS)
    raise UnknownFormatError(f"content matches none of the supported formats ({known})", path=str(path))


def load_log(path: str | Path, format: str = "auto") -> DriveLog:
    """Read the drive log at ``path`` into a DriveLog (units normalised, streams sorted by time).

    ``format="auto"`` detects it from the content. Raises LogFormatError (with the file and the
    record) for anything unreadable, and for values no real drive holds (:meth:`DriveLog.check_values`).
    """
    path = Path(path)
    if format == "auto":
        format, path = _resolve(path)
    elif not path.exists():
        raise LogFormatError("no such file or folder", path=str(path))
    log = _module(format).load(path)
    log.check_values()
    return log


# The formats whose writers keep each scan's own start angle (ScanStream.angle_offset_rad).
PER_SCAN_GEOMETRY_FORMATS = ("carmen", "drivelog", "rosbag")


def write_log(log: DriveLog, format: str, out_dir: str | Path) -> Path:
    """Write ``log`` in ``format`` into ``out_dir`` (created); returns the log's path (file or folder).

    Raises LogFormatError when the log lacks what the format needs (e.g. THOR needs four wheels).
    """
    info = format_info(format)
    if not info.can_write:
        raise LogFormatError(f"format {format!r} cannot be written")
    for name in ("scans", "encoders", "gyro", "odometry"):
        stream = getattr(log, name)
        if stream is not None and not np.isfinite(np.asarray(stream.t_s, dtype=np.float64)).all():
            raise LogFormatError(f"cannot write a log whose {name} have non-finite timestamps", location=name)
    if log.scans is not None and log.scans.angle_offset_rad is not None and format not in PER_SCAN_GEOMETRY_FORMATS:
        raise LogFormatError(f"format {format!r} cannot store a start angle that changes from scan to scan; "
                             f"formats that can: {', '.join(PER_SCAN_GEOMETRY_FORMATS)}", location="scans")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    return _module(format).write(log, out_dir)


__all__ = ["FormatInfo", "detect_format", "format_info", "list_formats", "load_log", "write_log"]
