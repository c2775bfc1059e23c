"""Checks every loader applies: time axes, range values, file opening. Errors name file and record."""

from __future__ import annotations

import gzip
import io
from collections.abc import Callable
from pathlib import Path

import numpy as np

from slam_engine.errors import LogFormatError
from slam_engine.model.drive_log import MAX_RANGE_M, MAX_TIME_S, first_beyond

# More than this share of backward steps means the stamps are not a time axis: refuse, do not sort.
MAX_BACKWARD_SHARE = 0.1


def record_label(what: str) -> Callable[[int], str]:
    """Default record naming: ``"<what> record <i>"`` (0-based)."""
    return lambda i: f"{what} record {i}"


def time_order(
    t_s: np.ndarray,
    path: str | Path,
    what: str,
    warnings: list[str],
    location_of: Callable[[int], str] | None = None,
) -> np.ndarray:
    """Indices that put the records of one stream in strictly increasing time order.

    NaN/inf stamps and stamps beyond +-``MAX_TIME_S`` are refused. Exact duplicates are dropped (first
    kept) and a few out-of-order records are sorted, each with a warning appended to ``warnings``; when more than
    ``MAX_BACKWARD_SHARE`` of the steps go backwards the stamps are refused.
    """
    location_of = location_of or record_label(what)
    t_s = np.asarray(t_s, dtype=np.float64)
    bad = np.flatnonzero(~np.isfinite(t_s))
    if bad.size:
        raise LogFormatError(f"timestamp is {t_s[bad[0]]}", path=str(path), location=location_of(int(bad[0])))
    absurd = first_beyond(t_s, MAX_TIME_S)
    if absurd is not None:
        raise LogFormatError(f"timestamp is {t_s[absurd]:g} s, beyond +-{MAX_TIME_S:g} s", path=str(path),
                             location=location_of(absurd))
    if t_s.size < 2:
        return np.arange(t_s.size)
    steps = np.diff(t_s)
    backward = np.flatnonzero(steps < 0)
    if backward.size > MAX_BACKWARD_SHARE * steps.size:
        first = int(backward[0]) + 1
        raise LogFormatError(
            f"{what} timestamps are not in time order ({backward.size} of {steps.size} steps go backwards, "
            f"first {t_s[first - 1]:.6f} -> {t_s[first]:.6f}); refusing to guess their order",
            path=str(path), location=location_of(first))
    order = np.argsort(t_s, kind="stable")
    if backward.size:
        first = int(backward[0]) + 1
        warnings.append(f"{path}: {what}: {backward.size} records out of time order (first at "
                        f"{location_of(first)}); sorted by timestamp")
    sorted_t = t_s[order]
    keep = np.concatenate([[True], np.diff(sorted_t) > 0])
    if not keep.all():
        first = int(order[np.flatnonzero(~keep)[0]])
        warnings.append(f"{path}: {what}: {int((~keep).sum())} records repeat an earlier timestamp (first at "
                        f"{location_of(first)}); kept the first of each")
    return order[keep]


def clean_ranges(
    ranges: np.ndarray,
    path: str | Path,
    what: str,
    no_return_at_or_above_m: float | None = None,
    zero_is_no_return: bool = True,
    location_of: Callable[[int], str] | None = None,
) -> np.ndarray:
    """(N, B) float32 ranges [m] with ``inf`` for no return; NaN, negative values and finite values
    beyond ``MAX_RANGE_M`` are refused.

    Values of zero (when ``zero_is_no_return``), values at or above ``no_return_at_or_above_m`` and
    +inf become ``inf``.
    """
    location_of = location_of or record_label(what)
    ranges = np.asarray(ranges, dtype=np.float64)
    if ranges.ndim != 2:
        raise LogFormatError(f"ranges must be a 2-D array (scans, beams), got shape {ranges.shape}",
                             path=str(path), location=what)
    nan_rows = np.flatnonzero(np.isnan(ranges).any(axis=1))
    if nan_rows.size:
        raise LogFormatError(f"range is NaN ({nan_rows.size} scans affected)", path=str(path),
                             location=location_of(int(nan_rows[0])))
    negative = ranges < 0
    if negative.any():
        row = int(np.flatnonzero(negative.any(axis=1))[0])
        beam = int(np.flatnonzero(negative[row])[0])
        raise LogFormatError(f"negative range {ranges[row, beam]} at beam {beam}", path=str(path),
                             location=location_of(row))
    absurd = np.isfinite(ranges) & (ranges > MAX_RANGE_M)
    if absurd.any():
        row = int(np.flatnonzero(absurd.any(axis=1))[0])
        beam = int(np.flatnonzero(absurd[row])[0])
        raise LogFormatError(f"range {ranges[row, beam]:g} m at beam {beam} is beyond {MAX_RANGE_M:g} m",
                             path=str(path), location=location_of(row))
    out = ranges.astype(np.float32)
    if zero_is_no_return:
        out[ranges == 0] = np.inf
    if no_return_at_or_above_m is not None:
        out[ranges >= no_return_at_or_above_m] = np.inf
    return out


def open_text(path: Path) -> io.TextIOBase:
    """Open a text file for reading, transparently un-gzipping it (judged by its magic bytes)."""
    with open(path, "rb") as raw:
        magic = raw.read(2)
    if magic == b"\x1f\x8b":
        return io.TextIOWrapper(gzip.open(path, "rb"), encoding="utf-8", errors="replace")
    return open(path, encoding="utf-8", errors="replace")


def head_lines(path: Path, max_bytes: int = 65536) -> list[str]:
    """The first lines (up to ``max_bytes`` of text) of a possibly gzipped file; [] if unreadable."""
    if not path.is_file():
        return []
    try:
        with open_text(path) as handle:
            text = handle.read(max_bytes)
    except (OSError, EOFError, UnicodeDecodeError):
        return []
    lines = text.splitlines()
    if len(text) == max_bytes and lines:
        lines = lines[:-1]  # the last one is probably cut
    return lines


def is_number(token: str) -> bool:
    """Whether ``token`` parses as a float."""
    try:
        float(token)
    except ValueError:
        return False
    return True
