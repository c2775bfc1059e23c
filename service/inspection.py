"""Validating an uploaded log with the engine's loader, in a separate process.

Loading parses the whole log (CPU-heavy, seconds for big logs, and a malformed file could even
crash a native reader), so it runs in a one-process spawn pool, never in the event loop. The child
returns plain data, the parent turns it into the HTTP answer.
"""

from __future__ import annotations

import asyncio
import multiprocessing as mp
import threading
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path
from typing import Any

from service.errors import InvalidInput, UnsupportedFormat


def inspect_log(path: str, format_name: str) -> dict[str, Any]:
    """Load the log at ``path``; ``{"summary": DriveLog.summary()}`` or ``{"error": ...}``."""
    from slam_engine.errors import LogFormatError, SlamEngineError, UnknownFormatError
    from slam_engine.formats import load_log

    try:
        log = load_log(Path(path), format=format_name)
    except UnknownFormatError as exc:
        return {"error": "unknown_format", "message": exc.message, "location": exc.location}
    except LogFormatError as exc:
        return {"error": "log_format", "message": exc.message, "location": exc.location}
    except SlamEngineError as exc:
        return {"error": "log_format", "message": str(exc), "location": None}
    except Exception as exc:  # a loader bug on odd input is still the input's problem to the client
        return {"error": "log_format", "message": f"the loader failed: {type(exc).__name__}: {exc}",
                "location": None}
    return {"summary": log.summary()}


def is_log_file(path: str, format_name: str) -> bool:
    """Whether the file itself is a log (e.g. a drive-log archive is a zip, yet no zipped folder)."""
    from slam_engine.errors import SlamEngineError
    from slam_engine.formats import detect_format

    try:
        detected = detect_format(Path(path))
    except SlamEngineError:
        return False
    return format_name in ("auto", detected)


class LogInspector:
    """A lazily started single worker process that runs :func:`inspect_log`."""

    def __init__(self) -> None:
        self._pool: ProcessPoolExecutor | None = None
        self._lock = threading.Lock()

    def _executor(self) -> ProcessPoolExecutor:
        with self._lock:
            if self._pool is None:
                self._pool = ProcessPoolExecutor(max_workers=1, mp_context=mp.get_context("spawn"))
            return self._pool

    async def summary(self, path: Path, format_name: str) -> dict[str, Any]:
        """The log's summary, or 415 (unknown format) / 422 (corrupt, with the loader's message)."""
        pool = self._executor()
        try:
            result = await asyncio.wrap_future(pool.submit(inspect_log, str(path), format_name))
        except BrokenProcessPool:
            with self._lock:
                if self._pool is pool:
                    self._pool = None
            pool.shutdown(wait=False, cancel_futures=True)
            raise InvalidInput("the log crashed the loader process", {"location": None}) from None
        if "summary" in result:
            return result["summary"]
        detail = {"location": result["location"]}
        if result["error"] == "unknown_format":
            raise UnsupportedFormat(result["message"], detail)
        err = InvalidInput(result["message"], detail)
        err.code = "log_format"
        raise err

    async def is_log_file(self, path: Path, format_name: str) -> bool:
        """Whether the uploaded file is itself a log (else a .zip is a zipped folder to extract)."""
        pool = self._executor()
        try:
            return await asyncio.wrap_future(pool.submit(is_log_file, str(path), format_name))
        except BrokenProcessPool:
            with self._lock:
                if self._pool is pool:
                    self._pool = None
            return False

    def shutdown(self) -> None:
        with self._lock:
            if self._pool is not None:
                self._pool.shutdown(wait=True, cancel_futures=True)
                self._pool = None
