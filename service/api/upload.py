"""Streaming multipart/form-data parsing with per-file and per-request limits.

Starlette's form parser only learns a file's size after spooling all of it;
this one counts bytes as they arrive and answers 413 as soon as one file (or
the whole body, chunked or not) passes its limit. File parts go to temporary
files (never whole in memory); the caller streams them on into storage.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass, field
from email.message import Message
from email.utils import collapse_rfc2231_value
from typing import BinaryIO

from python_multipart.multipart import MultipartParser
from starlette.requests import Request

from service.problems import invalid_input, too_large

MAX_FIELD_BYTES = 1 << 20  # all non-file fields of one request together (they are held in memory)
MAX_PARTS = 1000
# File parts are kept in memory up to this much per request in all (then on disk):
# a request of 1000 small files must not hold 1000 spool buffers of a MiB each.
MEMORY_SPOOL_BYTES = 4 << 20
SPOOL_PART_BYTES = 1 << 20


@dataclass
class FilePart:
    name: str
    filename: str | None
    content_type: str | None
    file: BinaryIO  # in memory while small (SpooledTemporaryFile), else a temp file
    size: int = 0


@dataclass
class Form:
    fields: dict[str, list[str]] = field(default_factory=dict)
    files: dict[str, list[FilePart]] = field(default_factory=dict)

    def field(self, name: str) -> str | None:
        v = self.fields.get(name)
        return v[-1] if v else None

    def close(self) -> None:
        for parts in self.files.values():
            for p in parts:
                p.file.close()


def _header_text(raw: bytes) -> str:
    """A part header's value: clients (browsers, httpx, curl) send file names as raw
    UTF-8 (RFC 7578 §4.2, HTML's form encoding); Latin-1 only for bytes that are not UTF-8."""
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError:
        return raw.decode("latin-1")


def _disposition(value: str) -> tuple[str | None, str | None]:
    """(name, filename) of a part's Content-Disposition. An RFC 5987/2231 `filename*`
    (charset'lang'percent-encoded) wins over a plain `filename` (RFC 6266 §4.3)."""
    m = Message()
    m["content-disposition"] = value
    name = m.get_param("name", header="content-disposition")
    plain = extended = None
    for key, v in m.get_params(header="content-disposition") or []:
        if key != "filename":
            continue
        if isinstance(v, tuple):  # filename*: (charset, language, value)
            extended = collapse_rfc2231_value(v)
        elif plain is None:
            plain = v
    if isinstance(name, tuple):
        name = collapse_rfc2231_value(name)
    return name, extended if extended is not None else plain


async def parse_multipart(request: Request, max_file_bytes: int, max_files: int) -> Form:
    ctype = request.headers.get("content-type", "")
    m = Message()
    m["content-type"] = ctype
    boundary = m.get_param("boundary")
    if m.get_content_type() != "multipart/form-data" or not boundary:
        raise invalid_input("expected multipart/form-data with a boundary")
    form = Form()
    parser = MultipartParser(boundary, _FormBuilder(form, max_file_bytes, max_files).callbacks())
    try:
        async for chunk in request.stream():
            parser.write(chunk)
        parser.finalize()
    except BaseException as exc:
        form.close()
        if type(exc).__name__ in ("MultipartParseError", "FormParserError"):
            raise invalid_input(f"malformed multipart body: {exc}") from None
        raise
    return form


class _FormBuilder:
    """The parser's callbacks: fill `form` part by part, within the limits."""

    def __init__(self, form: Form, max_file_bytes: int, max_files: int) -> None:
        self.form = form
        self.max_file_bytes = max_file_bytes
        self.max_files = max_files
        self.headers: dict[str, str] = {}
        self.hname = b""
        self.hval = b""
        self.part: FilePart | None = None  # the file part being received
        self.buf: bytearray | None = None  # the field being received
        self.name: str | None = None  # that field's name
        self.n = 0
        self.field_bytes = 0
        self.spool_left = MEMORY_SPOOL_BYTES

    def callbacks(self) -> dict:
        return {
            "on_part_begin": self.on_part_begin,
            "on_header_field": self.on_header_field,
            "on_header_value": self.on_header_value,
            "on_header_end": self.on_header_end,
            "on_headers_finished": self.on_headers_finished,
            "on_part_data": self.on_part_data,
            "on_part_end": self.on_part_end,
        }

    def on_part_begin(self) -> None:
        self.headers, self.part, self.buf = {}, None, None
        self.n += 1
        if self.n > MAX_PARTS:
            raise invalid_input("too many multipart parts")

    def on_header_field(self, data, start, end) -> None:
        self.hname += data[start:end]

    def on_header_value(self, data, start, end) -> None:
        self.hval += data[start:end]

    def on_header_end(self) -> None:
        self.headers[self.hname.decode("latin-1").lower()] = _header_text(self.hval)
        self.hname, self.hval = b"", b""

    def on_headers_finished(self) -> None:
        name, filename = _disposition(self.headers.get("content-disposition", ""))
        if not name:
            raise invalid_input("a multipart part has no name")
        if filename is None:
            self.buf = bytearray()
            self.form.fields.setdefault(name, [])
            self.name = name
            return
        if sum(len(v) for v in self.form.files.values()) >= self.max_files:
            raise too_large(f"more than {self.max_files} files in one request")
        spool = min(SPOOL_PART_BYTES, self.spool_left)
        self.spool_left -= spool
        part = FilePart(
            name,
            filename,
            self.headers.get("content-type"),
            tempfile.SpooledTemporaryFile(max_size=spool) if spool > 0 else tempfile.TemporaryFile(),
        )
        self.form.files.setdefault(name, []).append(part)
        self.part = part

    def on_part_data(self, data, start, end) -> None:
        n = end - start
        if self.part is not None:
            p = self.part
            p.size += n
            if p.size > self.max_file_bytes:
                raise too_large(f"file {p.filename!r} exceeds the limit of {self.max_file_bytes} bytes")
            p.file.write(data[start:end])
        else:
            # Counted over all fields, not per field: 1000 parts of just under the cap
            # each would otherwise hold a gigabyte in memory.
            self.field_bytes += n
            if self.field_bytes > MAX_FIELD_BYTES:
                raise too_large(f"form fields exceed {MAX_FIELD_BYTES} bytes in total (at {self.name!r})")
            self.buf += data[start:end]

    def on_part_end(self) -> None:
        if self.part is not None:
            self.part.file.seek(0)
        elif self.buf is not None:
            self.form.fields[self.name].append(self.buf.decode("utf-8", "replace"))
