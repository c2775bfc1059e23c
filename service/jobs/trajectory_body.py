"""A trajectory's API answer (``{"job_id", "kind", "count", "poses"}``) served straight from the
trajectory file the job wrote, in blocks: the file's ``"poses"`` list is already the API's list of poses
(the same field names), so the answer is a short head, that list's bytes, and ``}``. Its size is known
from the file (HEAD never builds the body) and the API process holds one block per request, however long
the trajectory. Files of the first trajectory format (other field names) are converted as before."""

from __future__ import annotations

import json
import os
import threading
from collections import OrderedDict
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

BLOCK_BYTES = 1024**2
HEAD_BYTES = 1024**2  # the file's header (format, units, the configuration) lies within this
POSES_KEY = b'"poses": ['  # json.dumps writes it so; inside a string its quotes would be escaped
POSE_TIME_KEY = b'"t_s":'
_SPANS_KEPT = 256


@dataclass(frozen=True)
class PosesSpan:
    """Where a trajectory file's poses list lies: bytes [start, end) (``[`` .. ``]``), and how many poses."""

    start: int
    end: int
    count: int


@dataclass(frozen=True)
class TrajectoryBody:
    """The answer for one trajectory file, open (so that a live file replaced meanwhile is not mixed in):
    head bytes, then the file's bytes [start, end), then ``}``."""

    handle: BinaryIO
    head: bytes
    span: PosesSpan

    @property
    def size_bytes(self) -> int:
        return len(self.head) + (self.span.end - self.span.start) + 1

    def blocks(self) -> Iterator[bytes]:
        """The body, one block at a time; closes the file."""
        with self.handle:
            yield self.head
            self.handle.seek(self.span.start)
            left = self.span.end - self.span.start
            while left > 0:
                block = self.handle.read(min(BLOCK_BYTES, left))
                if not block:
                    raise OSError("the trajectory file was cut short while it was read")
                left -= len(block)
                yield block
            yield b"}"

    def close(self) -> None:
        self.handle.close()


_spans: OrderedDict[tuple[int, int, int, int], PosesSpan | None] = OrderedDict()
_spans_lock = threading.Lock()


def poses_span(handle: BinaryIO) -> PosesSpan | None:
    """The poses list of the open version-2 trajectory file (None for another layout), remembered per
    file version; found by reading the file once in blocks (never parsed whole)."""
    stat = os.fstat(handle.fileno())
    key = (stat.st_dev, stat.st_ino, stat.st_size, stat.st_mtime_ns)
    with _spans_lock:
        if key in _spans:
            _spans.move_to_end(key)
            return _spans[key]
    span = _find_span(handle, stat.st_size)
    with _spans_lock:
        _spans[key] = span
        while len(_spans) > _SPANS_KEPT:
            _spans.popitem(last=False)
    return span


def _find_span(handle: BinaryIO, size: int) -> PosesSpan | None:
    handle.seek(0)
    key_at = handle.read(HEAD_BYTES).find(POSES_KEY)  # the header (format, frame, config) comes first
    handle.seek(max(size - 64, 0))
    tail = handle.read()
    close = tail.rfind(b"]")
    if key_at < 0 or close < 0 or tail[close + 1:].strip() != b"}":
        return None
    start, end = key_at + len(POSES_KEY) - 1, max(size - 64, 0) + close + 1  # "[" .. past "]"
    if end <= start:
        return None
    handle.seek(start)
    count, carry, left = 0, b"", end - start
    while left > 0:  # count the poses a block at a time
        block = handle.read(min(BLOCK_BYTES, left))
        if not block:
            return None
        left -= len(block)
        data = carry + block
        count += data.count(POSE_TIME_KEY)
        carry = data[-(len(POSE_TIME_KEY) - 1):]  # too short to hold a whole key: nothing counted twice
    if count == 0:
        handle.seek(start + 1)
        if handle.read(min(end - start - 2, 64)).strip():
            return None  # poses with other field names (the first format)
    return PosesSpan(start=start, end=end, count=count)


def trajectory_body(path: Path, job_id: str, kind: str) -> TrajectoryBody | None:
    """The streamed answer for the trajectory file at ``path`` (open: call ``blocks()`` or ``close()``);
    None when the file is not laid out as version 2 writes it (then the caller converts it)."""
    handle = open(path, "rb")  # noqa: SIM115 (closed by blocks() or close())
    try:
        span = poses_span(handle)
    except BaseException:
        handle.close()
        raise
    if span is None:
        handle.close()
        return None
    head = (json.dumps({"job_id": job_id, "kind": kind, "count": span.count})[:-1] + ', "poses": ').encode()
    return TrajectoryBody(handle=handle, head=head, span=span)
