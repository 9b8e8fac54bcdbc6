"""One validator for zip archives that come from users (image sets), shared by the
library (gsa.recon.images.check_zip: `gsa align photos.zip`, `gsa reconstruct`) and
the service (service.jobs.inputs.validate_zip: uploads, multipart jobs, the worker).

Everything is checked before anything is extracted, and everything that is refused
raises one ZipArchiveError (a ValueError) with a one-line message, never zipfile's
own exceptions:

- the central directory: readable, at most `max_entries` entries;
- every name: not empty, no NUL, no backslash, not absolute, no drive, no `..`; no
  symbolic links; no name twice;
- every entry: not encrypted, a compression method zipfile can read, the declared
  sizes within `max_bytes` in total and not a suspicious compression ratio (above
  `ratio_floor` bytes, more than `max_ratio` x its compressed size);
- with verify (the default): every file entry's local header must say what the central
  directory says (name, method, encryption, CRC-32 and both sizes, or its data descriptor
  must), and the entry is read through, streaming: its data must decompress, and its size
  and CRC-32 must be the declared ones. An archive whose entries lie about their sizes
  is refused here, not half-way through an extraction. The work is bounded: no entry
  yields more than its declared size.

Stdlib only: the service imports this at start-up.
"""

from __future__ import annotations

import stat
import struct
import zipfile
from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path, PurePosixPath, PureWindowsPath
from typing import BinaryIO

from gsa.errors import GSAError

SUPPORTED_METHODS = frozenset({zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED, zipfile.ZIP_BZIP2, zipfile.ZIP_LZMA})
CHUNK = 1 << 20


class ZipArchiveError(GSAError, ValueError):
    """A zip archive refused. `limit` is True when it is well-formed but over a size
    limit (the service answers 413), False for a defect (422)."""

    def __init__(self, message: str, *, limit: bool = False):
        super().__init__(message)
        self.limit = limit


@dataclass(frozen=True)
class ZipLimits:
    max_entries: int = 2000
    max_bytes: int = 2 * 1024**3  # total uncompressed, as declared (and, with verify, as read)
    max_ratio: float = 200.0  # uncompressed / compressed per entry: zip bombs go far beyond
    ratio_floor: int = 1024  # entries up to this size are not held to the ratio


def unsafe_member_name(name: str) -> str | None:
    """Why an archive member name is unsafe to use anywhere near a file system, or None."""
    if not name:
        return "empty name"
    if "\x00" in name:
        return "NUL in name"
    if "\\" in name:
        return "backslash in name"
    p = PurePosixPath(name)
    if p.is_absolute() or PureWindowsPath(name).drive or PureWindowsPath(name).root or name[1:2] == ":":
        return "absolute path"
    if ".." in p.parts:
        return "'..' in path"
    return None


def _is_symlink(info: zipfile.ZipInfo) -> bool:
    return stat.S_ISLNK(info.external_attr >> 16)


def check_zip(
    path: str | Path,
    limits: ZipLimits = ZipLimits(),
    *,
    label: str | None = None,
    verify: bool = True,
    head_bytes: int = 0,
    on_file: Callable[[zipfile.ZipInfo, bytes], None] | None = None,
) -> list[zipfile.ZipInfo]:
    """Validate a zip archive without extracting it; returns its file entries (no
    directories) in archive order. label: how messages name the archive (default: the
    file name). With verify, on_file(info, head) is called for every file entry with its
    first head_bytes bytes (already checked for nothing but being readable so far; the
    rest of the entry is checked after the call)."""
    path = Path(path)
    label = label or path.name
    try:
        zf = zipfile.ZipFile(path)
    except MemoryError:
        raise
    # hostile bytes reach deep into zipfile (BadZipFile, OSError, ValueError, struct.error, ...),
    # whose failures are no closed set: every one must become a ZipArchiveError
    except Exception as exc:  # noqa: BLE001
        raise ZipArchiveError(f"{label}: not a readable zip archive ({_reason(exc)})") from None
    with zf:
        infos = zf.infolist()
        if len(infos) > limits.max_entries:
            raise ZipArchiveError(
                f"{label}: {len(infos)} entries exceeds the limit of {limits.max_entries}", limit=True
            )
        files: list[zipfile.ZipInfo] = []
        seen: set[str] = set()
        total = 0
        for info in infos:
            name = info.filename
            why = unsafe_member_name(info.orig_filename)  # zipfile cuts `filename` at a NUL
            if why:
                raise ZipArchiveError(f"{label}: unsafe path in archive ({why}): {name!r}")
            if _is_symlink(info):
                raise ZipArchiveError(f"{label}: symbolic link in archive: {name!r}")
            if name in seen:
                raise ZipArchiveError(f"{label}: two entries named {name!r}")
            seen.add(name)
            if info.is_dir():
                continue
            if info.flag_bits & 0x1:
                raise ZipArchiveError(f"{label}: entry {name!r} is encrypted")
            if info.compress_type not in SUPPORTED_METHODS:
                raise ZipArchiveError(
                    f"{label}: entry {name!r} uses unsupported compression method {info.compress_type}"
                )
            total += info.file_size
            if total > limits.max_bytes:
                raise ZipArchiveError(
                    f"{label}: uncompressed size exceeds the limit of {limits.max_bytes} bytes", limit=True
                )
            if info.file_size > limits.ratio_floor and info.file_size > limits.max_ratio * max(info.compress_size, 1):
                raise ZipArchiveError(
                    f"{label}: entry {name!r} has a suspicious compression ratio "
                    f"({info.file_size}/{info.compress_size})"
                )
            files.append(info)
        if verify:
            with open(path, "rb") as raw:
                for info in files:
                    _check_local_header(raw, info, label)
                    _verify_entry(zf, info, label, head_bytes, on_file)
    return files


def check_local_headers(raw: BinaryIO, infos: list[zipfile.ZipInfo], label: str) -> None:
    """Every entry's local header against the central directory (see _check_local_header), for
    archives read as something else than an image set (a SOG model: gsa.io.packed)."""
    for info in infos:
        _check_local_header(raw, info, label)


_LOCAL = struct.Struct("<4sHHHHHIIIHH")  # a local file header up to its name and extra field
_DESCRIPTOR_SIG = b"PK\x07\x08"


def _check_local_header(raw: BinaryIO, info: zipfile.ZipInfo, label: str) -> None:
    """The entry's local header must say what the central directory says: zipfile reads an entry
    by the directory's sizes and CRC and never looks at the local header's, but other unzip tools
    (and the extraction of other services) go by the local one, so an archive whose two disagree
    holds different files for different readers. With a data descriptor (flag bit 3) the local
    fields may be 0 and the descriptor after the data must agree instead."""
    name = info.filename

    def differs(what: str, local, central) -> ZipArchiveError:
        return ZipArchiveError(
            f"{label}: entry {name!r}: its local header says {what} {local}, the central directory {central}"
        )

    raw.seek(info.header_offset)
    head = raw.read(_LOCAL.size)
    if len(head) != _LOCAL.size or head[:4] != b"PK\x03\x04":
        raise ZipArchiveError(f"{label}: entry {name!r} has no local file header where the directory points")
    _, _, flags, method, _, _, crc, csize, usize, name_len, extra_len = _LOCAL.unpack(head)
    if method != info.compress_type:
        raise differs("compression method", method, info.compress_type)
    if (flags ^ info.flag_bits) & 0x1:
        raise differs("encryption flag", flags & 0x1, info.flag_bits & 0x1)
    raw.seek(name_len, 1)
    extra = raw.read(extra_len)
    zip64 = _zip64_sizes(extra) if 0xFFFFFFFF in (csize, usize) else None
    if zip64 is not None:
        usize, csize = zip64
    described = flags & 0x8
    for what, local, central in (
        ("CRC-32", crc, info.CRC),
        ("compressed size", csize, info.compress_size),
        ("size", usize, info.file_size),
    ):
        if local != central and not (described and local == 0):
            raise differs(what, local, central)
    if described:
        raw.seek(info.header_offset + _LOCAL.size + name_len + extra_len + info.compress_size)
        tail = raw.read(28)
        if not _descriptor_agrees(tail, info):
            raise ZipArchiveError(
                f"{label}: entry {name!r}: its data descriptor does not say what the central directory says "
                f"(CRC-32 {info.CRC:#010x}, {info.compress_size} bytes compressed, {info.file_size} bytes)"
            )


def _zip64_sizes(extra: bytes) -> tuple[int, int] | None:
    """(size, compressed size) from a local header's zip64 extra field (id 1), if it has both."""
    i = 0
    while i + 4 <= len(extra):
        tag, size = struct.unpack_from("<HH", extra, i)
        if tag == 1 and size >= 16 and i + 4 + 16 <= len(extra):
            return struct.unpack_from("<QQ", extra, i + 4)
        i += 4 + size
    return None


def _descriptor_agrees(tail: bytes, info: zipfile.ZipInfo) -> bool:
    """A data descriptor (CRC-32, compressed size, size) after the entry's data that matches the
    directory: with or without its optional signature, with 4- or 8-byte sizes (zip64)."""
    want = (info.CRC, info.compress_size, info.file_size)
    for start in (4, 0) if tail[:4] == _DESCRIPTOR_SIG else (0,):
        for fmt in ("<III", "<IQQ"):
            if len(tail) >= start + struct.calcsize(fmt) and struct.unpack_from(fmt, tail, start) == want:
                return True
    return False


def _verify_entry(zf: zipfile.ZipFile, info: zipfile.ZipInfo, label: str, head_bytes: int, on_file) -> None:
    """Read one entry through: local header, decompression, size and CRC (zipfile checks
    the CRC once the declared size has been read, and never yields more than that)."""
    name = info.filename
    with _reading(label, name):
        fh = zf.open(info)
    try:
        with _reading(label, name):
            head = fh.read(head_bytes) if head_bytes else b""
        if on_file is not None:  # its own errors are the caller's, not the archive's
            on_file(info, head)
        n = len(head)
        with _reading(label, name):
            while chunk := fh.read(CHUNK):
                n += len(chunk)
    finally:
        fh.close()
    if n != info.file_size:
        raise ZipArchiveError(f"{label}: entry {name!r} declares {info.file_size} bytes but holds {n}")


@contextmanager
def _reading(label: str, name: str):
    try:
        yield
    except MemoryError:
        raise
    # BadZipFile (CRC, header), EOFError, zlib.error, LZMAError, OSError (bz2), ...: as above,
    # every failure to read hostile bytes must become a ZipArchiveError
    except Exception as exc:  # noqa: BLE001
        raise ZipArchiveError(
            f"{label}: entry {name!r} is corrupt or does not hold what the archive declares ({_reason(exc)})"
        ) from None


def _reason(exc: BaseException) -> str:
    text = str(exc).strip() or type(exc).__name__
    return text if len(text) <= 200 else text[:200] + "..."
