"""Keeping a reserve of free disk space: uploads and chunks that would eat into it answer 507
(Insufficient Storage) and store nothing, so the job store and running jobs keep room to write.
Another writer can still fill the disk: a spare file (:func:`keep_spare`) is given up when a job's
status cannot be written for a full disk (:func:`write_status`), so that the job still ends saying so."""

from __future__ import annotations

import logging
import os
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

from service.http_errors import InsufficientStorage, is_disk_full
from service.storage.data_dir import DataDir

logger = logging.getLogger("lidarmap.storage")
T = TypeVar("T")

CHECK_EVERY_BYTES = 8 * 1024**2  # while an upload streams in, free space is checked this often


def ensure_free_space(data: DataDir, reserve_bytes: int, incoming_bytes: int = 0) -> None:
    """507 unless ``incoming_bytes`` more still leave ``reserve_bytes`` free under the data folder."""
    free = data.free_bytes()
    if free - incoming_bytes < reserve_bytes:
        raise InsufficientStorage(
            f"not enough disk space: {free} bytes free, {incoming_bytes} bytes arriving and {reserve_bytes} bytes "
            "kept in reserve; nothing was stored, retry later",
            {"free_bytes": free, "incoming_bytes": incoming_bytes, "reserve_bytes": reserve_bytes})


def free_bytes_at(path: Path) -> int:
    return DataDir(path).free_bytes()


def disk_full_error(exc: OSError, what: str) -> InsufficientStorage | None:
    """The 507 for an ENOSPC/EDQUOT ``exc`` while writing ``what``; None for other OS errors."""
    if not is_disk_full(exc):
        return None
    return InsufficientStorage(f"the server's disk is full while writing {what}; nothing was stored, retry later",
                               {"errno": exc.errno})


SPARE_BYTES = 1024**2  # the spare file: room for a few hundred job status writes (SQLite pages of 4 kB)


def keep_spare(data: DataDir) -> bool:
    """Create the data folder's spare file unless it exists or fewer than 4 spares' worth of bytes are
    free (it never takes the last space); whether it is there afterwards."""
    path = data.spare
    if path.exists():
        return True
    if data.free_bytes() < 4 * SPARE_BYTES:
        return False
    partial = data.tmp / f"spare.{os.getpid()}"  # tmp/ is emptied at start-up
    try:
        with open(partial, "wb") as out:
            out.write(b"\0" * SPARE_BYTES)  # written, not truncated: a sparse file would free nothing
            out.flush()
            os.fsync(out.fileno())
        os.replace(partial, path)
        return True
    except OSError:
        partial.unlink(missing_ok=True)
        return False


def release_spare(data: DataDir) -> bool:
    """Delete the spare file; whether there was one."""
    try:
        data.spare.unlink()
    except FileNotFoundError:
        return False
    logger.warning("the disk is full: the %d kB spare file was given up for job status writes", SPARE_BYTES // 1024)
    return True


def write_status(data: DataDir, write: Callable[[], T]) -> T:
    """``write()`` (a job store write); when it fails for a full disk, once more after giving up the
    spare file (if there is one). Raises what the last try raised."""
    try:
        return write()
    except Exception as exc:
        if not is_disk_full(exc, free_bytes=data.free_bytes()) or not release_spare(data):
            raise
    return write()
