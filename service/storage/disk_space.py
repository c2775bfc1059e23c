"""Keeping a reserve of free disk space: uploads and chunks that would eat into it answer 507
(Insufficient Storage) and store nothing, so the job store and running jobs keep room to write."""

from __future__ import annotations

from pathlib import Path

from service.http_errors import InsufficientStorage, is_disk_full
from service.storage.data_dir import DataDir

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
