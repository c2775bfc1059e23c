"""Exception hierarchy of the engine: one root, one subclass per concern.

The service and the CLI turn these into HTTP 4xx answers and one-line messages (exit code 2).
"""

from __future__ import annotations

import os


class SlamEngineError(Exception):
    """Root of every error the engine raises on purpose."""


class LogFormatError(SlamEngineError):
    """A drive log cannot be read: unknown format, truncated file, bad values, missing calibration.

    ``path`` names the file, ``location`` the record, line or array (e.g. ``"line 42"``,
    ``"Encoders.counts"``), ``message`` what is wrong.
    """

    def __init__(self, message: str, path: str | os.PathLike[str] | None = None, location: str | None = None):
        self.message = message
        self.path = None if path is None else str(path)
        self.location = location
        where = ", ".join(part for part in (self.path, self.location) if part)
        super().__init__(f"{where}: {message}" if where else message)


class UnknownFormatError(LogFormatError):
    """The content matches none of the supported drive-log formats."""


class ConfigError(SlamEngineError):
    """A configuration value is out of range or inconsistent with the log."""


class Cancelled(SlamEngineError):
    """A run was asked to stop (raised from the progress callback or a stop check)."""


class TrajectoryFormatError(LogFormatError):
    """A trajectory file (lidarmap JSON or TUM) cannot be read; ``message`` names the expected format."""


class TileOutOfRangeError(SlamEngineError):
    """A map tile outside the pyramid: zoom level or x/y index out of bounds (HTTP 404)."""


class MapBundleError(SlamEngineError):
    """A map bundle cannot be read (not a bundle, damaged, or of another format version), or a drive or
    map cannot be placed in it."""
