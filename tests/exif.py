"""JPEGs whose EXIF names the camera that took them, written by hand (no EXIF writer among the
dependencies): Make, Model, LensModel, FocalLength, FocalLengthIn35mmFilm, Orientation."""

from __future__ import annotations

import struct

import cv2
import numpy as np

IPHONE = ("Apple", "iPhone 7", "iPhone 7 back camera 3.99mm f/1.8", 3.99, 28, None)


def _ascii(text: str) -> bytes:
    return text.encode() + b"\x00"


def camera_jpeg(path, make="Apple", model="iPhone 7", lens="iPhone 7 back camera 3.99mm f/1.8", focal=(399, 100),
                focal_35mm=28, orientation=None, size=(24, 32), little_endian=False, image=None):  # fmt: skip
    """A small JPEG whose EXIF names its camera: Make, Model (IFD0), LensModel, FocalLength,
    FocalLengthIn35mmFilm (the Exif sub-IFD), as a phone writes them; ASCII values stored after
    the directories, as TIFF asks for values over 4 bytes. image: BGR uint8 pixels (else grey)."""
    o = "<" if little_endian else ">"
    ifd0 = [(0x010F, 2, _ascii(make)), (0x0110, 2, _ascii(model))]
    if orientation is not None:
        ifd0.append((0x0112, 3, struct.pack(o + "HH", orientation, 0)))
    sub = [
        (0xA434, 2, _ascii(lens)),
        (0x920A, 5, struct.pack(o + "II", *focal)),
        (0xA405, 3, struct.pack(o + "HH", focal_35mm, 0)),
    ]
    ifd0_at = 8
    sub_at = ifd0_at + 2 + 12 * (len(ifd0) + 1) + 4
    data_at = sub_at + 2 + 12 * len(sub) + 4
    blob = b""

    def directory(entries, extra=()):
        nonlocal blob
        out = struct.pack(o + "H", len(entries) + len(extra))
        for tag, kind, value in list(entries) + list(extra):
            count = len(value) if kind == 2 else 1
            if len(value) > 4:
                out += struct.pack(o + "HHII", tag, kind, count, data_at + len(blob))
                blob += value
            else:
                out += struct.pack(o + "HHI", tag, kind, count) + value.ljust(4, b"\x00")
        return out + bytes(4)

    head = directory(ifd0, [(0x8769, 4, struct.pack(o + "I", sub_at))])
    body = directory(sub)
    tiff = (b"II*\x00" if little_endian else b"MM\x00*") + struct.pack(o + "I", ifd0_at) + head + body + blob
    pixels = np.full((*size, 3), 128, np.uint8) if image is None else image
    ok, buf = cv2.imencode(".jpg", pixels, [cv2.IMWRITE_JPEG_QUALITY, 95])
    payload = b"Exif\x00\x00" + tiff
    data = buf.tobytes()
    path.write_bytes(data[:2] + b"\xff\xe1" + struct.pack(">H", len(payload) + 2) + payload + data[2:])
    return path
