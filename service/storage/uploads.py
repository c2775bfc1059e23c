"""Receiving uploads: a multipart body streamed straight to disk (hashed and size-checked as it
arrives, never held in memory), and safe extraction of zipped folder formats."""

from __future__ import annotations

import hashlib
import os
import re
import shutil
import stat
import tempfile
import zipfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import TYPE_CHECKING, Any

from python_multipart.exceptions import MultipartParseError
from python_multipart.multipart import MultipartParser, parse_options_header
from starlette.requests import ClientDisconnect, Request

from service.http_errors import BadRequest, InvalidInput, PayloadTooLarge, UnsupportedFormat
from service.storage.disk_space import CHECK_EVERY_BYTES, disk_full_error

if TYPE_CHECKING:
    from python_multipart.multipart import MultipartCallbacks

MULTIPART_OVERHEAD_BYTES = 64 * 1024  # headers and boundaries around the file part
MAX_FIELD_BYTES = 1024
FILE_FIELD = "file"
_SAFE_SUFFIX = re.compile(r"^\.[a-z0-9]{1,10}$")

UPLOAD_OPENAPI = {
    "requestBody": {
        "required": True,
        "content": {"multipart/form-data": {"schema": {
            "type": "object", "required": [FILE_FIELD],
            "properties": {
                FILE_FIELD: {"type": "string", "format": "binary",
                             "description": "The drive log, or a .zip of a folder format."},
                "format": {"type": "string", "description": "Format name (default: auto-detect)."},
            }}}},
    }
}


@dataclass
class ReceivedFile:
    """The file part of an upload, saved under the data folder's tmp/."""

    path: Path
    filename: str
    size_bytes: int
    sha256: str
    fields: dict[str, str] = field(default_factory=dict)


class _PartCollector:
    """python-multipart callbacks: the file part goes to a temp file, small text fields to memory."""

    def __init__(self, tmp_dir: Path, max_bytes: int, space: Callable[[int], None] | None = None):
        self.tmp_dir = tmp_dir
        self.max_bytes = max_bytes
        self.space = space  # raises 507 when this many more bytes would eat into the disk reserve
        self._checked_at = 0
        self.fields: dict[str, str] = {}
        self.file: ReceivedFile | None = None
        self._handle: Any = None
        self._hash = hashlib.sha256()
        self._header_field = b""
        self._header_value = b""
        self._headers: dict[bytes, bytes] = {}
        self._name: str | None = None
        self._receiving: ReceivedFile | None = None  # the file part now arriving (None: a text field)
        self._field_buf = bytearray()

    def callbacks(self) -> MultipartCallbacks:
        return {
            "on_part_begin": self._part_begin, "on_header_field": self._header_field_cb,
            "on_header_value": self._header_value_cb, "on_header_end": self._header_end,
            "on_headers_finished": self._headers_finished, "on_part_data": self._part_data,
            "on_part_end": self._part_end,
        }

    def _part_begin(self) -> None:
        self._headers, self._name, self._receiving = {}, None, None
        self._field_buf = bytearray()

    def _header_field_cb(self, data: bytes, start: int, end: int) -> None:
        self._header_field += data[start:end]

    def _header_value_cb(self, data: bytes, start: int, end: int) -> None:
        self._header_value += data[start:end]

    def _header_end(self) -> None:
        self._headers[self._header_field.lower()] = self._header_value
        self._header_field, self._header_value = b"", b""

    def _headers_finished(self) -> None:
        _, params = parse_options_header(self._headers.get(b"content-disposition", b""))
        self._name = params.get(b"name", b"").decode("utf-8", "replace")
        filename = params.get(b"filename")
        if self._name == FILE_FIELD and filename is not None:
            if self.file is not None:
                raise BadRequest("only one file per upload", {"field": FILE_FIELD})
            fd, tmp = tempfile.mkstemp(dir=self.tmp_dir, prefix="upload-")
            self._handle = os.fdopen(fd, "wb")
            self.file = self._receiving = ReceivedFile(path=Path(tmp), size_bytes=0, sha256="",
                                                       filename=filename.decode("utf-8", "replace")[:255])

    def _part_data(self, data: bytes, start: int, end: int) -> None:
        if (received := self._receiving) is not None:
            piece = data[start:end]
            received.size_bytes += len(piece)
            if received.size_bytes > self.max_bytes:
                raise PayloadTooLarge(f"upload larger than the limit of {self.max_bytes} bytes",
                                      {"limit_bytes": self.max_bytes})
            if self.space is not None and received.size_bytes - self._checked_at >= CHECK_EVERY_BYTES:
                self._checked_at = received.size_bytes
                self.space(CHECK_EVERY_BYTES)
            self._hash.update(piece)
            try:
                self._handle.write(piece)
            except OSError as exc:
                raise disk_full_error(exc, "the upload") or exc from None
        else:
            self._field_buf += data[start:end]
            if len(self._field_buf) > MAX_FIELD_BYTES:
                raise BadRequest(f"form field {self._name!r} is longer than {MAX_FIELD_BYTES} bytes")

    def _part_end(self) -> None:
        if (received := self._receiving) is not None:
            try:
                self._handle.close()  # flushes the last buffered bytes
            except OSError as exc:
                self._handle = None
                raise disk_full_error(exc, "the upload") or exc from None
            self._handle = None
            received.sha256 = self._hash.hexdigest()
        elif self._name:
            self.fields[self._name] = self._field_buf.decode("utf-8", "replace")

    def discard(self) -> None:
        if self._handle is not None:
            self._handle.close()
        if self.file is not None:
            self.file.path.unlink(missing_ok=True)


async def receive_upload(request: Request, tmp_dir: Path, max_bytes: int,
                         space: Callable[[int], None] | None = None) -> ReceivedFile:
    """Stream a multipart body's ``file`` part to ``tmp_dir`` (413 as soon as it passes ``max_bytes``).
    ``space(n)`` raises (507) when ``n`` more bytes would not fit: called with the declared length
    first, then every few MB as the body arrives; a full disk while writing is a 507 too."""
    content_type, params = parse_options_header(request.headers.get("content-type", ""))
    if content_type != b"multipart/form-data" or b"boundary" not in params:
        raise UnsupportedFormat("send the log as multipart/form-data in the form field 'file'",
                                {"content_type": request.headers.get("content-type")})
    declared = request.headers.get("content-length")
    if declared and declared.isdigit() and int(declared) > max_bytes + MULTIPART_OVERHEAD_BYTES:
        raise PayloadTooLarge(f"upload of {declared} bytes is larger than the limit of {max_bytes} bytes",
                              {"limit_bytes": max_bytes})
    if space is not None:
        space(int(declared) if declared and declared.isdigit() else 0)
    collector = _PartCollector(tmp_dir, max_bytes, space)
    parser = MultipartParser(params[b"boundary"], collector.callbacks())
    try:
        async for piece in request.stream():
            parser.write(piece)
        parser.finalize()
    except MultipartParseError as exc:
        collector.discard()
        raise BadRequest(f"malformed multipart body: {exc}") from None
    except ClientDisconnect:
        collector.discard()
        raise BadRequest("the client disconnected during the upload") from None
    except BaseException:
        collector.discard()
        raise
    if collector._handle is not None:
        collector.discard()
        raise BadRequest("the multipart body ended inside the file part (truncated upload?)")
    if collector.file is None:
        collector.discard()
        raise InvalidInput("missing form field 'file' (the drive log)", {"field": FILE_FIELD})
    collector.file.fields = collector.fields
    return collector.file


def safe_suffix(filename: str) -> str:
    """The file's extension when it is short and plain (it helps format detection), else ''."""
    suffix = PurePosixPath(filename.replace("\\", "/")).suffix.lower()
    return suffix if _SAFE_SUFFIX.match(suffix) else ""


def is_zip_upload(received: ReceivedFile) -> bool:
    """A .zip is a zipped folder format (an .npz is also a zip inside, but a log in its own right)."""
    return safe_suffix(received.filename) == ".zip"


MAX_NAME_BYTES = 255  # one path component, as most file systems allow
MAX_ZIP_RATIO = 100  # extracted size / zip size past which a zip is a bomb (real logs compress ~2-20 times)
RATIO_FLOOR_BYTES = 64 * 1024**2  # extracting less than this is never refused for its ratio
MAX_PATH_CHARS = 1024


def extract_zip(zip_path: Path, dest: Path, max_entries: int, max_total_bytes: int,
                space: Callable[[int], None] | None = None, max_ratio: int = MAX_ZIP_RATIO) -> Path:
    """Extract ``zip_path`` into ``dest`` refusing absolute paths, '..', symlinks and special files,
    encrypted members, over-long names, members that clash (a file and a folder of one name),
    more than ``max_entries`` members or more than ``max_total_bytes``. The members' declared sizes are
    checked before any byte is written: 413 when they add up past ``max_total_bytes`` or to more than
    ``max_ratio`` times the zip's own size (past :data:`RATIO_FLOOR_BYTES`; a zip bomb); while writing,
    a member is never read past its declared size (zipfile stops there, and the CRC check then fails)
    and the total is counted again. ``space(n)`` raises (507) when ``n`` more bytes would eat into the
    disk reserve: called with the declared total, then every few MB as it is written.
    Returns the log's root: the single top folder if there is one."""
    try:
        archive = zipfile.ZipFile(zip_path)
    except (zipfile.BadZipFile, OSError) as exc:
        raise InvalidInput(f"not a readable zip archive: {exc}") from None
    with archive:
        members = [m for m in archive.infolist() if not m.filename.startswith("__MACOSX/")]
        if len(members) > max_entries:
            raise PayloadTooLarge(f"zip has {len(members)} entries; the limit is {max_entries}",
                                  {"limit_entries": max_entries})
        if not members:
            raise InvalidInput("the zip archive is empty")
        check_declared_sizes(members, zip_path.stat().st_size, max_total_bytes, max_ratio)
        dest.mkdir(parents=True, exist_ok=True)
        root = dest.resolve()
        if space is not None:
            space(sum(m.file_size for m in members))
        written, checked_at = 0, 0
        for member in members:
            target = _member_target(root, member)
            if member.flag_bits & 0x1:
                raise InvalidInput(f"zip member {member.filename!r} is encrypted; encrypted zips are not accepted")
            try:
                if member.is_dir():
                    target.mkdir(parents=True, exist_ok=True)
                    continue
                target.parent.mkdir(parents=True, exist_ok=True)
                with archive.open(member) as src, open(target, "xb") as out:
                    while block := src.read(1 << 20):
                        written += len(block)
                        if written > max_total_bytes:
                            raise PayloadTooLarge(f"zip expands beyond the limit of {max_total_bytes} bytes",
                                                  {"limit_bytes": max_total_bytes})
                        if space is not None and written - checked_at >= CHECK_EVERY_BYTES:
                            checked_at = written
                            space(CHECK_EVERY_BYTES)
                        out.write(block)
            except (FileExistsError, NotADirectoryError, IsADirectoryError):
                raise InvalidInput(f"zip member {member.filename!r} appears twice (the same name, or as both a "
                                   "file and a folder)") from None
            except (zipfile.BadZipFile, zipfile.LargeZipFile, NotImplementedError, EOFError, RuntimeError) as exc:
                raise InvalidInput(f"zip member {member.filename!r} cannot be read: {exc}") from None
            except OSError as exc:
                raise disk_full_error(exc, "the extracted zip") or InvalidInput(
                    f"zip member {member.filename!r} cannot be extracted: {exc.strerror}") from None
    entries = [p for p in root.iterdir()]
    return entries[0] if len(entries) == 1 and entries[0].is_dir() else root


def check_declared_sizes(members: list[zipfile.ZipInfo], zip_bytes: int, max_total_bytes: int,
                         max_ratio: int) -> None:
    """413 when the members declare more than ``max_total_bytes`` in all, or more than ``max_ratio``
    times the zip's size ``zip_bytes`` (and more than RATIO_FLOOR_BYTES): nothing is written then."""
    declared = sum(m.file_size for m in members)
    if declared > max_total_bytes:
        raise PayloadTooLarge(f"zip members declare {declared} bytes in all; the limit is {max_total_bytes} bytes",
                              {"limit_bytes": max_total_bytes, "declared_bytes": declared})
    if declared > max(RATIO_FLOOR_BYTES, max_ratio * zip_bytes):
        raise PayloadTooLarge(f"zip of {zip_bytes} bytes declares {declared} bytes once extracted, more than "
                              f"{max_ratio} times its size (a zip bomb?)",
                              {"limit_ratio": max_ratio, "declared_bytes": declared, "zip_bytes": zip_bytes})


def _member_target(root: Path, member: zipfile.ZipInfo) -> Path:
    name = member.filename
    mode = member.external_attr >> 16
    if stat.S_ISLNK(mode):
        raise InvalidInput(f"zip member {name!r} is a symbolic link; links are not accepted")
    if stat.S_IFMT(mode) and not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):
        raise InvalidInput(f"zip member {name!r} is not a regular file or folder")
    if len(name) > MAX_PATH_CHARS or any(len(p.encode()) > MAX_NAME_BYTES for p in name.split("/")):
        raise InvalidInput(f"zip member name {name!r} is too long ({len(name)} characters; at most "
                           f"{MAX_NAME_BYTES} bytes a part and {MAX_PATH_CHARS} characters in all)")
    if "\\" in name or "\x00" in name:
        raise InvalidInput(f"zip member name {name!r} contains a backslash or NUL")
    parts = PurePosixPath(name).parts
    if not parts or name.startswith("/") or ".." in parts or (parts[0].endswith(":")):
        raise InvalidInput(f"zip member {name!r} would be extracted outside its folder")
    target = (root / PurePosixPath(name)).resolve()
    if not target.is_relative_to(root) or target == root:
        raise InvalidInput(f"zip member {name!r} would be extracted outside its folder")
    return target


def move_into(src: Path, dest: Path) -> None:
    dest.parent.mkdir(parents=True, exist_ok=True)
    shutil.move(str(src), str(dest))
