"""Broken zip archives of images, one per defect, built by patching the bytes of a valid
one: used by the library's (tests/test_ziparchive.py) and the service's
(tests/service/test_zip_uploads.py) tests of the one zip validator, gsa.ziparchive."""

from __future__ import annotations

import io
import stat
import struct
import zipfile

import numpy as np


def png(w: int = 32, h: int = 24, seed: int = 0) -> bytes:
    import cv2

    img = np.random.default_rng(seed).integers(0, 255, (h, w, 3), dtype=np.uint8)
    return cv2.imencode(".png", img)[1].tobytes()


def build(entries: dict[str, bytes], method=zipfile.ZIP_DEFLATED) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", method) as z:
        for n, b in entries.items():
            z.writestr(n, b)
    return buf.getvalue()


def good(n: int = 3, method=zipfile.ZIP_DEFLATED) -> bytes:
    return build({f"v{i}.png": png(seed=i) for i in range(n)}, method)


# Offsets of fields in the local file header (PK\3\4) and the central directory entry (PK\1\2).
LOCAL = {"flags": 6, "method": 8, "crc": 14, "csize": 18, "usize": 22}
CENTRAL = {"flags": 8, "method": 10, "crc": 16, "csize": 20, "usize": 24}


def _patch(data: bytes, sig: bytes, fields: dict[str, int], which: str, value: int, width: int, nth: int) -> bytes:
    out = bytearray(data)
    at = -1
    for _ in range(nth + 1):
        at = out.index(sig, at + 1)
    fmt = "<H" if width == 2 else "<I"
    struct.pack_into(fmt, out, at + fields[which], value)
    return bytes(out)


def _get(data: bytes, sig: bytes, fields: dict[str, int], which: str, nth: int = 0) -> int:
    at = -1
    for _ in range(nth + 1):
        at = data.index(sig, at + 1)
    return struct.unpack_from("<I", data, at + fields[which])[0]


def set_both(data: bytes, which: str, value: int, nth: int = 0) -> bytes:
    """Set a 4-byte field in the nth entry's local header and its central directory entry."""
    data = _patch(data, b"PK\x03\x04", LOCAL, which, value, 4, nth)
    return _patch(data, b"PK\x01\x02", CENTRAL, which, value, 4, nth)


def set_local(data: bytes, which: str, value: int, nth: int = 0) -> bytes:
    """Set a 4-byte field in the nth entry's local header only: the central directory, which
    zipfile reads by, keeps the truth."""
    return _patch(data, b"PK\x03\x04", LOCAL, which, value, 4, nth)


def set_both16(data: bytes, which: str, value: int, nth: int = 0) -> bytes:
    data = _patch(data, b"PK\x03\x04", LOCAL, which, value, 2, nth)
    return _patch(data, b"PK\x01\x02", CENTRAL, which, value, 2, nth)


def declared_size(data: bytes, nth: int = 0) -> int:
    return _get(data, b"PK\x01\x02", CENTRAL, "usize", nth)


def _symlink() -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        for i in range(3):
            z.writestr(f"v{i}.png", png(seed=i))
        info = zipfile.ZipInfo("link.png")
        info.external_attr = (stat.S_IFLNK | 0o777) << 16
        z.writestr(info, "/etc/passwd")
    return buf.getvalue()


def _header_name_differs() -> bytes:
    data = bytearray(good())
    at = data.index(b"PK\x03\x04")
    data[at + 30 : at + 32] = b"x0"  # the local header names 'x0.png', the directory 'v0.png'
    return bytes(data)


def cases() -> dict[str, bytes]:
    """Defect name -> archive bytes; every one must be refused (422 / one CLI line)."""
    g = good()
    size = declared_size(g)
    stored = good(method=zipfile.ZIP_STORED)
    return {
        "header-name-differs": _header_name_differs(),
        "size-smaller-than-data": set_both(g, "usize", size - 100),
        "size-larger-than-data": set_both(g, "usize", size + 100),
        "stored-size-lies": set_both(set_both(stored, "usize", size - 7), "csize", size - 7),
        "compressed-size-lies": set_both(g, "csize", 40),
        "bad-crc": set_both(g, "crc", 0x12345678),
        "local-size-differs": set_local(g, "usize", size + 5000),
        "local-compressed-size-differs": set_local(g, "csize", 40, nth=1),
        "local-crc-differs": set_local(g, "crc", 0x12345678, nth=2),
        "local-method-differs": _patch(g, b"PK\x03\x04", LOCAL, "method", 0, 2, 0),
        "truncated": g[: len(g) // 2] + g[-22:],
        "encrypted-flag": set_both16(g, "flags", 0x1),
        "unknown-method": set_both16(g, "method", 99),
        "symlink": _symlink(),
        "backslash-name": build({"a\\v0.png": png(), "v1.png": png(seed=1), "v2.png": png(seed=2)}),
        "nul-name": build({"v0.pngX.txt": png(), "v1.png": png(seed=1)}).replace(b"v0.pngX", b"v0.png\0"),
        "dot-dot": build({"../v0.png": png(), "v1.png": png(seed=1)}),
        "duplicate-names": _duplicates(),
        "bomb-just-over-1kib": build({"v0.png": b"\0" * 300_000, "v1.png": png(seed=1)}),
        "not-a-zip-after-the-magic": b"PK\x03\x04" + b"\xff" * 200,
    }


def _duplicates() -> bytes:
    import warnings

    buf = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with zipfile.ZipFile(buf, "w") as z:
            z.writestr("v0.png", png())
            z.writestr("v0.png", png(seed=1))
            z.writestr("v1.png", png(seed=2))
    return buf.getvalue()
