"""Where files live under the data folder. Every path is built from server-made ids and fixed
names, never from client input (except the members of an uploaded zip, which uploads.py checks).

    <data>/lidarmap.sqlite3          job store
    <data>/uploads/<log_id>/log<ext> an uploaded single-file log (ext from a short whitelist pattern)
    <data>/uploads/<log_id>/tree/    an uploaded zip, extracted
    <data>/chunks/<session_id>/<seq>.json
    <data>/jobs/<job_id>/            products; live/ holds the snapshot of a running job
    <data>/tmp/                      partial uploads
    <data>/spare                     1 MB given up when a job's status meets a full disk (disk_space.py)
"""

from __future__ import annotations

import shutil
import tempfile
import uuid
from pathlib import Path

from slam_engine.products.files import write_bytes_atomic


class DataDir:
    """Paths under the service's data folder."""

    def __init__(self, root: Path):
        self.root = Path(root).resolve()

    def create(self) -> None:
        for sub in ("uploads", "chunks", "jobs", "tmp"):
            (self.root / sub).mkdir(parents=True, exist_ok=True)

    @property
    def database(self) -> Path:
        return self.root / "lidarmap.sqlite3"

    @property
    def spare(self) -> Path:
        return self.root / "spare"

    @property
    def tmp(self) -> Path:
        return self.root / "tmp"

    def upload_dir(self, log_id: str) -> Path:
        return self.root / "uploads" / _checked_id(log_id)

    def chunk_dir(self, session_id: str) -> Path:
        return self.root / "chunks" / _checked_id(session_id)

    def chunk_file(self, session_id: str, seq: int) -> Path:
        return self.chunk_dir(session_id) / f"{int(seq):010d}.json"

    def job_dir(self, job_id: str) -> Path:
        return self.root / "jobs" / _checked_id(job_id)

    def live_dir(self, job_id: str) -> Path:
        return self.job_dir(job_id) / "live"

    def resolve(self, relative: str) -> Path:
        """A stored relative path, checked to stay inside the data folder."""
        path = (self.root / relative).resolve()
        if not path.is_relative_to(self.root):
            raise ValueError(f"stored path escapes the data folder: {relative!r}")
        return path

    def relative(self, path: Path) -> str:
        return str(Path(path).resolve().relative_to(self.root))

    def remove(self, path: Path) -> None:
        shutil.rmtree(path, ignore_errors=True)

    def remove_stale_temp_files(self) -> int:
        """Delete what tmp/ holds (partial uploads of a service that stopped mid-upload) and the staging
        folders of job attempts (``jobs/<id>/.staging-<pid>``) a crash left; call only at start-up,
        before uploads arrive and jobs run. Returns how many entries were removed."""
        removed = 0
        stale = list(self.tmp.iterdir()) if self.tmp.is_dir() else []
        stale += list((self.root / "jobs").glob("*/.staging-*"))
        for entry in stale:
            if entry.is_dir() and not entry.is_symlink():
                shutil.rmtree(entry, ignore_errors=True)
            else:
                entry.unlink(missing_ok=True)
            removed += 1
        return removed

    def remove_orphans(self, stored: dict[str, set[str]], uploads_and_chunks: bool = True) -> int:
        """Delete job folders (and, when ``uploads_and_chunks``, upload and chunk folders) whose id the
        store no longer knows: what a crash in the middle of a delete left. Call at start-up only.
        Returns how many folders were removed."""
        kinds = [("jobs", stored["jobs"])]
        if uploads_and_chunks:
            kinds += [("uploads", stored["logs"]), ("chunks", stored["sessions"])]
        removed = 0
        for sub, known in kinds:
            folder = self.root / sub
            for entry in folder.iterdir() if folder.is_dir() else []:
                if entry.name not in known and entry.is_dir() and not entry.is_symlink():
                    shutil.rmtree(entry, ignore_errors=True)
                    removed += 1
        return removed

    def writable(self) -> bool:
        try:
            with tempfile.NamedTemporaryFile(dir=self.tmp):
                return True
        except OSError:
            return False

    def free_bytes(self) -> int:
        return shutil.disk_usage(self.root).free


def _checked_id(value: str) -> str:
    """Ids are UUIDs made by the service; anything else is a bug, never a path."""
    return str(uuid.UUID(value))


def write_atomic(path: Path, data: bytes) -> None:
    """Write ``data`` so readers see the old file or the new one, never a partial one."""
    write_bytes_atomic(path, data)
