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
    st: dict = {
        "headers": {},
        "hname": b"",
        "hval": b"",
        "part": None,
        "buf": None,
        "n": 0,
        "field_bytes": 0,
        "spool_left": MEMORY_SPOOL_BYTES,
    }

    def on_part_begin():
        st["headers"], st["part"], st["buf"] = {}, None, None
        st["n"] += 1
        if st["n"] > MAX_PARTS:
            raise invalid_input("too many multipart parts")

    def on_header_field(data, start, end):
        st["hname"] += data[start:end]

    def on_header_value(data, start, end):
        st["hval"] += data[start:end]

    def on_header_end():
        st["headers"][st["hname"].decode("latin-1").lower()] = _header_text(st["hval"])
        st["hname"], st["hval"] = b"", b""

    def on_headers_finished():
        name, filename = _disposition(st["headers"].get("content-disposition", ""))
        if not name:
            raise invalid_input("a multipart part has no name")
        if filename is not None:
            if sum(len(v) for v in form.files.values()) >= max_files:
                raise too_large(f"more than {max_files} files in one request")
            spool = min(SPOOL_PART_BYTES, st["spool_left"])
            st["spool_left"] -= spool
            part = FilePart(
                name,
                filename,
                st["headers"].get("content-type"),
                tempfile.SpooledTemporaryFile(max_size=spool) if spool > 0 else tempfile.TemporaryFile(),
            )
            form.files.setdefault(name, []).append(part)
            st["part"] = part
        else:
            st["buf"] = bytearray()
            form.fields.setdefault(name, [])
            st["name"] = name

    def on_part_data(data, start, end):
        n = end - start
        if st["part"] is not None:
            p = st["part"]
            p.size += n
            if p.size > max_file_bytes:
                raise too_large(f"file {p.filename!r} exceeds the limit of {max_file_bytes} bytes")
            p.file.write(data[start:end])
        else:
            # Counted over all fields, not per field: 1000 parts of just under the cap
            # each would otherwise hold a gigabyte in memory.
            st["field_bytes"] += n
            if st["field_bytes"] > MAX_FIELD_BYTES:
                raise too_large(f"form fields exceed {MAX_FIELD_BYTES} bytes in total (at {st['name']!r})")
            st["buf"] += data[start:end]

    def on_part_end():
        if st["part"] is not None:
            st["part"].file.seek(0)
        elif st["buf"] is not None:
            form.fields[st["name"]].append(st["buf"].decode("utf-8", "replace"))

    parser = MultipartParser(
        boundary,
        {
            "on_part_begin": on_part_begin,
            "on_header_field": on_header_field,
            "on_header_value": on_header_value,
            "on_header_end": on_header_end,
            "on_headers_finished": on_headers_finished,
            "on_part_data": on_part_data,
            "on_part_end": on_part_end,
        },
    )
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
