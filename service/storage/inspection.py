"""Validating an uploaded log with the engine's loader, in separate processes with bounds.

Loading parses the whole log (CPU-heavy, seconds for big logs; a malformed or hostile file could
grow without end or crash a native reader), so it never runs in the API process. Each upload is
inspected in a *lane*: one spawned process, used by one upload at a time. Per upload:

* memory: the child's resident size is held under ``memory_limit_mb`` (watchdog, and an
  address-space limit that turns one huge allocation into a MemoryError), see
  :class:`service.memory_watchdog.MemoryGuard`;
* time: past ``timeout_s`` the child is killed;
* decompressed size: a gzipped log that inflates past ``max_decompressed_bytes`` is refused before
  it is parsed.

A lane whose child died or was killed starts a fresh child for its next upload, so one upload's
failure never answers another's; ``lanes`` uploads are inspected at once (the others wait).

Fairness: one more lane, the *express lane*, takes only small uploads - at most ``express_bytes``
once inflated (:func:`inflated_size_hint`: the file's size, a gzip's own record of its inflated
size, a folder's total) - for at most ``express_timeout_s`` each. A small upload that finds every
regular lane busy (slow bombs being read to their limits) is inspected there instead of waiting up
to ``timeout_s`` behind them. A gzip is inflated up to the express size in the API process before it
is let in (:func:`inflates_beyond`: a lying size record is found in milliseconds, and the bomb waits
for a regular lane); one that still takes longer than its slice is stopped and inspected again in a
regular lane, so it can hold the express lane for one slice at most. A size rule rather than one
lane per client: the probe's attacker and victim share one address and one key, and a small upload is
cheap to read whoever sends it.
"""

from __future__ import annotations

import asyncio
import dataclasses
import gzip
import multiprocessing as mp
import os
import signal
import struct
import threading
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from service.http_errors import InvalidInput, PayloadTooLarge, UnsupportedFormat, shorten_tokens

GZIP_MAGIC = b"\x1f\x8b"
STARTUP_TIMEOUT_S = 120.0  # a fresh inspection process imports every loader (seconds on a busy machine)


@dataclass(frozen=True)
class InspectionLimits:
    """Bounds on one upload's inspection."""

    memory_limit_mb: int = 2048
    timeout_s: float = 120.0
    max_decompressed_bytes: int = 8 * 1024**3
    lanes: int = 2
    express_bytes: int = 4 * 1024**2  # uploads up to this size once inflated may use the express lane (0: none)
    express_timeout_s: float = 10.0  # the express lane's slice per upload [s]


def inflated_size_hint(path: Path) -> int:
    """What reading ``path`` will cost, in bytes, as far as it can be known without reading it: a
    gzip's recorded inflated size (its last 4 bytes, modulo 4 GiB and forgeable: the express lane's
    slice bounds a lie) or its own size if larger, a folder's total, else the file's size."""
    if path.is_dir():
        return sum(entry.stat().st_size for entry in path.rglob("*") if entry.is_file() and not entry.is_symlink())
    try:
        size = path.stat().st_size
        if size >= 18 and _is_gzip(path):
            with open(path, "rb") as handle:
                handle.seek(-4, os.SEEK_END)
                return max(size, struct.unpack("<I", handle.read(4))[0])
        return size
    except OSError:
        return 0


def gzip_size_exceeds(path: Path, limit_bytes: int) -> bool:
    """Whether the gzipped file at ``path`` inflates to more than ``limit_bytes`` (streamed, 1 MB at a time)."""
    total = 0
    try:
        with gzip.open(path, "rb") as handle:
            while block := handle.read(1 << 20):
                total += len(block)
                if total > limit_bytes:
                    return True
    except (OSError, EOFError, zlib.error):
        return False  # a broken stream: the loader reports it with its location
    return False


def inflates_beyond(path: Path, limit_bytes: int) -> bool:
    """Whether ``path``, a gzip, inflates past ``limit_bytes`` in fact (its size record can lie: six
    uploads whose record claimed 1000 bytes each held the express lane for a whole slice, and an honest
    upload waited 48 s behind them). Reads at most ``limit_bytes`` and a block (milliseconds for the
    express lane's 4 MB); a plain file or folder: False (its size is what it holds)."""
    return path.is_file() and _is_gzip(path) and gzip_size_exceeds(path, limit_bytes)


def inspect_log(path: str, format_name: str, max_decompressed_bytes: int, hidden_prefix: str = "") -> dict[str, Any]:
    """Load the log at ``path``; ``{"summary": DriveLog.summary()}`` or ``{"error", "message", "location"}``.
    ``hidden_prefix`` (the server's folder of the upload) is cut from warnings and messages."""
    from slam_engine.errors import LogFormatError, SlamEngineError, UnknownFormatError
    from slam_engine.formats import load_log

    file = Path(path)
    if _is_gzip(file) and gzip_size_exceeds(file, max_decompressed_bytes):
        return {"error": "too_large", "message": f"the gzipped log inflates beyond the limit of "
                f"{max_decompressed_bytes} bytes", "location": None}
    try:
        log = load_log(file, format=format_name)
    except UnknownFormatError as exc:
        return _error("unknown_format", exc.message, exc.location, hidden_prefix)
    except LogFormatError as exc:
        return _error("log_format", exc.message, exc.location, hidden_prefix)
    except SlamEngineError as exc:
        return _error("log_format", str(exc), None, hidden_prefix)
    except MemoryError:
        return _error("memory", "", None)
    except Exception as exc:  # a loader bug on odd input is still the input's problem to the client
        return _error("log_format", f"the loader failed on this log ({type(exc).__name__})", None)
    from slam_engine.evaluation.memory_estimate import drive_figures

    summary = log.summary()
    summary["warnings"] = [_shown(w, hidden_prefix) for w in summary.get("warnings", [])]
    summary["memory_figures"] = dataclasses.asdict(drive_figures(log))  # for the job's memory estimate
    return {"summary": summary}


def inspect_bundle(path: str, max_decompressed_bytes: int, hidden_prefix: str = "") -> dict[str, Any]:
    """Read the map bundle at ``path``; ``{"summary": {...}}`` or ``{"error": "map_bundle", "message", ...}``.
    Its arrays' declared sizes are checked against ``max_decompressed_bytes`` and the bound on uploaded
    bundles (``MAX_UPLOADED_BUNDLE_BYTES``, 256 MiB) before any is read."""
    from slam_engine.errors import SlamEngineError
    from slam_engine.products.map_bundle import MAX_UPLOADED_BUNDLE_BYTES, check_bundle_size, read_bundle

    try:
        check_bundle_size(path, min(max_decompressed_bytes, MAX_UPLOADED_BUNDLE_BYTES))
        bundle = read_bundle(path)
    except SlamEngineError as exc:  # the message without the upload's temporary file name
        return _error("map_bundle", str(exc).removeprefix(f"{path}: "), None, hidden_prefix)
    except MemoryError:
        return _error("memory", "", None)
    return {"summary": {"key_frames": len(bundle), "drives": bundle.drives, "resolution_m": bundle.resolution_m,
                        "scans": int(len(bundle.trajectory)), "rays": int(len(bundle.ends_v))}}


def _shown(text: str, hidden_prefix: str) -> str:
    """``text`` without the server's folders and with long tokens cut."""
    return shorten_tokens(text.replace(hidden_prefix, "") if hidden_prefix else text)


def _is_gzip(path: Path) -> bool:
    if not path.is_file():
        return False
    with open(path, "rb") as handle:
        return handle.read(2) == GZIP_MAGIC


def _error(kind: str, message: str, location: str | None, hidden_prefix: str = "") -> dict[str, Any]:
    """An error result with every long token cut (a quoted 1 GB line must not travel back)."""
    return {"error": kind, "message": _shown(message, hidden_prefix),
            "location": location and _shown(location, hidden_prefix)}


def is_log_file(path: str, format_name: str) -> dict[str, Any]:
    """Whether the file itself is a log (e.g. a drive-log archive is a zip, yet no zipped folder)."""
    from slam_engine.errors import SlamEngineError
    from slam_engine.formats import detect_format

    try:
        detected = detect_format(Path(path))
    except SlamEngineError:
        return {"is_log": False}
    return {"is_log": format_name in ("auto", detected)}


_CALLS: dict[str, Callable[..., Any]] = {"inspect_log": inspect_log, "is_log_file": is_log_file,
                                         "inspect_bundle": inspect_bundle}


def _child_main(conn: Any, memory_limit_mb: int) -> None:
    """A lane's process: run requests from ``conn`` under the memory bound until the pipe closes."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C goes to the server, which stops us
    from service.memory_watchdog import MB, MemoryGuard, resident_bytes
    from service.process_guard import die_with_parent

    die_with_parent()
    from slam_engine.formats import _installed_modules

    _installed_modules()  # every loader and its libraries mapped before the address-space bound is set
    conn.send("ready")
    retire_above = (resident_bytes() + memory_limit_mb * MB) // 2

    over = {"error": "memory", "message": "", "location": None}
    sending = threading.Lock()  # the watchdog's thread and this one may both answer: one answer per request
    answered = False

    def answer(message: dict[str, Any]) -> None:
        nonlocal answered
        with sending:
            if not answered:
                answered = True
                conn.send(message)

    while True:
        try:
            name, args = conn.recv()
        except (EOFError, OSError):
            return
        answered = False
        with MemoryGuard(memory_limit_mb, on_exceeded=lambda _reason: answer(over)):
            try:
                result = _CALLS[name](*args)
            except MemoryError:
                result = over
        retire = resident_bytes() > retire_above  # memory a big log left behind would count against the next
        answer({**result, "retire": retire})
        if retire:
            return


class _Lane:
    """One inspection process (started on first use, replaced after it dies or is killed)."""

    def __init__(self, memory_limit_mb: int):
        self.memory_limit_mb = memory_limit_mb
        self._process: Any = None
        self._conn: Any = None
        self._stopping = threading.Lock()  # the service's shutdown may stop a lane that is in use

    def call(self, name: str, args: tuple, timeout_s: float) -> dict[str, Any]:
        """Run ``name(*args)`` in the child; ``{"error": "timeout" | "crashed" | "memory"}`` when it failed.
        ``timeout_s`` counts from the request (a fresh child's start-up is not part of it)."""
        if self._process is not None and self._conn.poll(0):
            self.stop()  # an answer nobody waited for (the watchdog's, as it killed the child): start afresh
        if self._process is None or not self._process.is_alive():
            self.stop()
            if not self._start():
                return {"error": "crashed", "message": "", "location": None}
        try:
            self._conn.send((name, args))
            if not self._conn.poll(timeout_s):
                self.stop()
                return {"error": "timeout", "message": "", "location": None}
            result = self._conn.recv()
        except Exception:  # the child died mid-answer (EOF, broken pipe, a garbled message)
            return {"error": "memory" if self._killed() else "crashed", "message": "", "location": None}
        if result.pop("retire", False) or result.get("error") == "memory":
            self.stop()  # it is ending (or killing itself): the next upload gets a fresh process
        return result

    def _killed(self) -> bool:
        """Stop the child that died mid-request; whether SIGKILL ended it: its memory guard's own kill (when
        the answer it sent first did not get through: seen under load with a log that blows up in memory)
        or the kernel's out-of-memory killer."""
        process = self._process
        if process is not None:
            process.join(timeout=2.0)
        killed = process is not None and process.exitcode == -signal.SIGKILL
        self.stop()
        return killed

    def _start(self) -> bool:
        """A fresh child, ready (its libraries imported); False when it failed to start."""
        ctx = mp.get_context("spawn")
        parent, child = ctx.Pipe()
        process = ctx.Process(target=_child_main, args=(child, self.memory_limit_mb),
                              name="lidarmap-inspection", daemon=True)
        try:
            process.start()
        finally:
            child.close()
        self._process, self._conn = process, parent
        try:
            if parent.poll(STARTUP_TIMEOUT_S) and parent.recv() == "ready":
                return True
        except (EOFError, OSError):
            pass
        self.stop()
        return False

    def stop(self) -> None:
        """Kill the child (if any) and forget it; safe to call from two threads at once."""
        with self._stopping:
            process, conn = self._process, self._conn
            self._process = self._conn = None
        if process is None:
            return
        if process.is_alive():
            process.kill()
        process.join(timeout=5.0)
        conn.close()


class LogInspector:
    """Inspects uploads in ``limits.lanes`` bounded processes, one lane per upload at a time, plus the
    express lane for small uploads (see the module docstring)."""

    def __init__(self, limits: InspectionLimits | None = None) -> None:
        self.limits = limits or InspectionLimits()
        self._lanes = [_Lane(self.limits.memory_limit_mb) for _ in range(self.limits.lanes)]
        self._express = _Lane(self.limits.memory_limit_mb) if self.limits.express_bytes else None
        self._idle = list(self._lanes)
        self._lock = threading.Lock()
        self._free: asyncio.Semaphore | None = None
        self._express_free: asyncio.Semaphore | None = None

    async def _run(self, name: str, args: tuple, path: Path) -> dict[str, Any]:
        if self._free is None or self._express_free is None:
            self._free, self._express_free = asyncio.Semaphore(self.limits.lanes), asyncio.Semaphore(1)
        if self._express is not None and self._free.locked():  # every regular lane busy
            size = await asyncio.to_thread(inflated_size_hint, path)
            if size <= self.limits.express_bytes and not await asyncio.to_thread(
                    inflates_beyond, path, self.limits.express_bytes):
                async with self._express_free:
                    result = await asyncio.to_thread(self._express.call, name, args, self.limits.express_timeout_s)
                if result.get("error") != "timeout":
                    return result
                # longer than its slice: read again in a regular lane, with the full time limit
        async with self._free:
            with self._lock:
                lane = self._idle.pop()
            try:
                return await asyncio.to_thread(lane.call, name, args, self.limits.timeout_s)
            finally:
                with self._lock:
                    self._idle.append(lane)

    async def summary(self, path: Path, format_name: str, hidden_prefix: str = "") -> dict[str, Any]:
        """The log's summary, or 415 (unknown format) / 422 (corrupt, with the loader's message; or past
        the memory or time bound) / 413 (inflates past the limit). ``hidden_prefix`` is cut from texts."""
        result = await self._run("inspect_log", (str(path), format_name, self.limits.max_decompressed_bytes,
                                                 hidden_prefix), path)
        if "summary" in result:
            return result["summary"]
        raise self._failure(result)

    async def bundle_summary(self, path: Path, hidden_prefix: str = "") -> dict[str, Any]:
        """An uploaded map bundle's summary (key frames, drives, cell size), or 422 with what is wrong (not a
        bundle, another format version, damaged, arrays past the decompression limit)."""
        result = await self._run("inspect_bundle", (str(path), self.limits.max_decompressed_bytes, hidden_prefix),
                                 path)
        if "summary" in result:
            return result["summary"]
        raise self._failure(result)

    async def is_log_file(self, path: Path, format_name: str) -> bool:
        """Whether the uploaded file is itself a log (else a .zip is a zipped folder to extract)."""
        result = await self._run("is_log_file", (str(path), format_name), path)
        if "is_log" in result:
            return result["is_log"]
        raise self._failure(result)

    def _failure(self, result: dict[str, Any]) -> Exception:
        kind, detail = result["error"], {"location": result.get("location")}
        if kind == "unknown_format":
            return UnsupportedFormat(result["message"], detail)
        if kind == "too_large":
            return PayloadTooLarge(result["message"], {"limit_bytes": self.limits.max_decompressed_bytes})
        if kind == "memory":
            err = InvalidInput(f"reading this log needs more than the inspection memory limit of "
                               f"{self.limits.memory_limit_mb} MB", {"limit_mb": self.limits.memory_limit_mb})
            err.code = "inspection_limit"
            return err
        if kind == "timeout":
            err = InvalidInput(f"reading this log took longer than the inspection time limit of "
                               f"{self.limits.timeout_s:g} s", {"limit_s": self.limits.timeout_s})
            err.code = "inspection_limit"
            return err
        if kind == "crashed":
            return InvalidInput("the log crashed the loader process", detail)
        if kind == "map_bundle":
            err = InvalidInput(result["message"], detail)
            err.code = "map_bundle"
            return err
        err = InvalidInput(result["message"], detail)
        err.code = "log_format"
        return err

    def shutdown(self) -> None:
        with self._lock:
            for lane in [*self._lanes, *([self._express] if self._express is not None else [])]:
                lane.stop()
