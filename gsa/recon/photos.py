"""Photo sets as people take them: EXIF-rotated JPEGs, portrait and landscape mixed, more than
one camera size, a few files that do not decode.

Every image is decoded as it is meant to be seen: the EXIF orientation applied (OpenCV's
IMREAD_COLOR does so for JPEG; IMREAD_UNCHANGED does not). A set whose images already share
one size and carry no EXIF rotation is used where it lies, as before. Any other set is
prepared once into a temporary folder, under the same file names, so that SfM and training
read the same pixels:

- the canvas is the most common size in the majority orientation (landscape or portrait);
- an image of the other orientation is turned by 90° (a pinhole image turned by 90° is the
  image of a camera rolled by 90°, and SfM recovers the roll);
- an image of another size is scaled to cover the canvas, keeping its aspect, and cropped
  about its centre (pixels stay square, the crop only moves the principal point);
- each camera size (long × short side, before scaling) is its own SfM camera: the portrait and
  landscape shots of one phone share one, a second phone gets its own (gsa.recon.sfm).

Files that do not decode are left out with one warning, as long as at least `min_images`
remain; otherwise the set is refused (ImageSetError, one line). So are a few blurred views
(camera shake, missed focus): an image whose sharpness (`sharpness`) is below BLUR_RATIO of the
set's median is left out with one warning, where at most MAX_BLURRED_SHARE of the set is and
`min_images` remain. The test is relative to the set itself, so a set that is soft throughout
(a small sensor, a dim room) loses nothing.
"""

from __future__ import annotations

import os
import shutil
import struct
import tempfile
import warnings
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from gsa.io.ply import ReaderWarning

# Flags that decode an image as it is meant to be seen: EXIF orientation applied, colour,
# 16-bit kept (alpha is dropped, grey expanded to three channels).
READ_FLAGS = cv2.IMREAD_COLOR | cv2.IMREAD_ANYDEPTH
JPEG_SUFFIXES = (".jpg", ".jpeg")
_WRITE_PARAMS = {
    ".jpg": [cv2.IMWRITE_JPEG_QUALITY, 98],
    ".jpeg": [cv2.IMWRITE_JPEG_QUALITY, 98],
    ".webp": [cv2.IMWRITE_WEBP_QUALITY, 101],  # lossless
}


# Sharpness is measured on a copy whose long side is SHARPNESS_SIDE pixels, so that sizes compare.
SHARPNESS_SIDE = 512
# A view is blurred when its sharpness is under this share of the set's median: a Gaussian blur
# of 2 px (at SHARPNESS_SIDE) takes the Laplacian's variance below 0.1 of a sharp view's, while
# sharp views of one object differ by a few times at most (less texture, more background).
BLUR_RATIO = 0.1
# At most this share of a set is left out as blurred: "a few" views; beyond it the set is
# what it is, and every view is kept.
MAX_BLURRED_SHARE = 1 / 3


class ImageSetWarning(ReaderWarning):
    """An image set used with changes (files left out); the CLI prints it as one line."""


@dataclass
class PreparedSet:
    """directory: where the images to use are (the original folder, or a temporary copy);
    names: the images used (sorted; unreadable files left out); width, height: one size for
    all; camera_groups: each image's SfM camera (None: one camera for all); notes: what was
    changed, by file name (for report.json); camera: what EXIF says took every photo used
    (exif_camera), None unless all name one camera."""

    directory: Path
    names: list[str]
    width: int
    height: int
    camera_groups: list[int] | None = None
    notes: dict = field(default_factory=dict)
    tmp: object | None = None
    camera: tuple | None = None


def _exif_tiff(path: str | os.PathLike) -> bytes | None:
    """The TIFF block of a JPEG's EXIF (APP1) segment, None when it has none or is not a JPEG."""
    if Path(path).suffix.lower() not in JPEG_SUFFIXES:
        return None
    try:
        with open(path, "rb") as fh:
            data = fh.read(1 << 16)  # APP1 comes first and is at most 64 KiB
    except OSError:
        return None
    if data[:2] != b"\xff\xd8":
        return None
    at = 2
    while at + 4 <= len(data) and data[at] == 0xFF:
        marker, size = data[at + 1], struct.unpack_from(">H", data, at + 2)[0]
        if marker == 0xE1 and data[at + 4 : at + 10] == b"Exif\x00\x00":
            tiff = data[at + 10 : at + 2 + size]
            return tiff if len(tiff) >= 8 and tiff[:2] in (b"II", b"MM") else None
        if marker in (0xDA, 0xD9):  # start of scan, end of image: no EXIF before the pixels
            return None
        at += 2 + size
    return None


# TIFF field types read here: their byte sizes.
_TIFF_SIZES = {1: 1, 2: 1, 3: 2, 4: 4, 5: 8, 7: 1}


def _ifd(tiff: bytes, offset: int) -> dict:
    """{tag: value} of one TIFF directory: ASCII as str, SHORT/LONG as int, RATIONAL as float
    (the first value of each; other types and entries beyond the block are skipped)."""
    order = "<" if tiff[:2] == b"II" else ">"
    values: dict = {}
    if offset + 2 > len(tiff):
        return values
    for i in range(struct.unpack_from(order + "H", tiff, offset)[0]):
        entry = offset + 2 + 12 * i
        if entry + 12 > len(tiff):
            break
        tag, kind, count = struct.unpack_from(order + "HHI", tiff, entry)
        if kind not in _TIFF_SIZES:
            continue
        size = _TIFF_SIZES[kind] * count
        at = entry + 8 if size <= 4 else struct.unpack_from(order + "I", tiff, entry + 8)[0]
        if at + max(size, _TIFF_SIZES[kind]) > len(tiff):
            continue
        if kind == 2:
            values[tag] = tiff[at : at + size].split(b"\x00")[0].decode("latin-1").strip()
        elif kind == 3:
            values[tag] = struct.unpack_from(order + "H", tiff, at)[0]
        elif kind == 4:
            values[tag] = struct.unpack_from(order + "I", tiff, at)[0]
        elif kind == 5:
            num, den = struct.unpack_from(order + "II", tiff, at)
            values[tag] = num / den if den else None
    return values


def exif_orientation(path: str | os.PathLike) -> int:
    """The EXIF orientation (1-8) of a JPEG, 1 when it has none or is not a JPEG."""
    tiff = _exif_tiff(path)
    if tiff is None:
        return 1
    order = "<" if tiff[:2] == b"II" else ">"
    value = _ifd(tiff, struct.unpack_from(order + "I", tiff, 4)[0]).get(0x0112)
    return value if isinstance(value, int) and 1 <= value <= 8 else 1


def exif_camera(path: str | os.PathLike) -> tuple | None:
    """What EXIF says took the photo: (make, model, lens, focal length in mm, 35 mm equivalent,
    digital zoom), None when it names neither the camera nor a focal length. Two photos with
    the same tuple share their intrinsics up to the size they were stored at (gsa.recon.calibration)."""
    tiff = _exif_tiff(path)
    if tiff is None:
        return None
    order = "<" if tiff[:2] == b"II" else ">"
    main = _ifd(tiff, struct.unpack_from(order + "I", tiff, 4)[0])
    sub = _ifd(tiff, main[0x8769]) if isinstance(main.get(0x8769), int) else {}
    focal = sub.get(0x920A)
    camera = (
        main.get(0x010F) or None,  # Make
        main.get(0x0110) or None,  # Model
        sub.get(0xA434) or None,  # LensModel: a phone's wide, tele and ultra-wide cameras
        round(focal, 3) if isinstance(focal, float) else None,  # FocalLength, a zoom lens's setting
        sub.get(0xA405) or None,  # FocalLengthIn35mmFilm: changes with a crop or digital zoom
        round(sub[0xA404], 3) if isinstance(sub.get(0xA404), float) else None,  # DigitalZoomRatio
    )
    return camera if (camera[1] or camera[3]) else None


def read_oriented(path: str | os.PathLike) -> np.ndarray | None:
    """(H, W, 3) BGR, 8 or 16 bit, EXIF orientation applied; None when it does not decode."""
    img = cv2.imread(str(path), READ_FLAGS)
    return None if img is None or img.size == 0 else img


def prepare_photos(
    directory: Path, names: list[str], *, min_images: int, max_pixels: int, error: type[Exception]
) -> PreparedSet:
    """The set's images at one size (see the module's docstring); `error` is raised, one line,
    when the set cannot be used."""
    sizes: dict[str, tuple[int, int]] = {}
    sharp: dict[str, float] = {}
    rotated_by_exif, unreadable = [], []
    for n in names:
        # Decode fully: a truncated or mislabelled file must show here, not inside SfM.
        img = read_oriented(directory / n)
        if img is None:
            unreadable.append(n)
            continue
        h, w = img.shape[:2]
        if h * w > max_pixels:
            raise error(f"{n}: {w}x{h} exceeds the {max_pixels}-pixel limit")
        sizes[n] = (w, h)
        sharp[n] = sharpness(img)
        if exif_orientation(directory / n) != 1:
            rotated_by_exif.append(n)
    used = [n for n in names if n in sizes]
    if len(used) < min_images:
        bad = f"; not readable images: {_listing(unreadable)}" if unreadable else ""
        raise error(f"{len(used)} readable image(s) in {directory.name}; at least {min_images} are needed{bad}")
    notes: dict = {}
    if unreadable:
        notes["unreadable"] = unreadable
        warnings.warn(
            f"{directory.name}: {len(unreadable)} file(s) are not readable images and are left out: "
            f"{_listing(unreadable)}",
            ImageSetWarning,
            stacklevel=3,
        )
    blurred = blurred_views(sharp, min_images)
    if blurred:
        notes["blurred"] = blurred
        warnings.warn(
            f"{directory.name}: {len(blurred)} blurred view(s) left out (sharpness under {BLUR_RATIO:g} of the "
            f"set's median): {_listing(blurred)}",
            ImageSetWarning,
            stacklevel=3,
        )
        used = [n for n in used if n not in blurred]
        sizes = {n: sizes[n] for n in used}
        rotated_by_exif = [n for n in rotated_by_exif if n in sizes]
    cameras = {exif_camera(directory / n) for n in used}  # read on the originals: copies lose EXIF
    camera = next(iter(cameras)) if len(cameras) == 1 else None
    if len(set(sizes.values())) == 1 and not rotated_by_exif:
        ((w, h),) = set(sizes.values())
        return PreparedSet(directory, used, w, h, None, notes, camera=camera)

    # One canvas: the majority orientation, its most common size.
    landscape = sum(w > h for w, h in sizes.values()) >= sum(h > w for w, h in sizes.values())
    turn = {n: w != h and (w > h) != landscape for n, (w, h) in sizes.items()}
    upright = {n: (h, w) if turn[n] else (w, h) for n, (w, h) in sizes.items()}
    counts = Counter(upright.values())
    width, height = max(counts, key=lambda s: (counts[s], s[0] * s[1]))
    # One SfM camera per camera size (long x short side): turned shots share their camera.
    kinds = sorted({tuple(sorted(s, reverse=True)) for s in sizes.values()})
    groups = [kinds.index(tuple(sorted(sizes[n], reverse=True))) for n in used]

    tmp = tempfile.TemporaryDirectory(prefix="gsa-photos-")
    out = Path(tmp.name)
    turned, rescaled = [], []
    for n in used:
        if not turn[n] and upright[n] == (width, height) and n not in rotated_by_exif:
            shutil.copyfile(directory / n, out / n)
            continue
        img = read_oriented(directory / n)
        if turn[n]:
            img = cv2.rotate(img, cv2.ROTATE_90_CLOCKWISE)
            turned.append(n)
        if img.shape[1] != width or img.shape[0] != height:
            img = _cover(img, width, height)
            rescaled.append(n)
        if not cv2.imwrite(str(out / n), img, _WRITE_PARAMS.get(Path(n).suffix.lower(), [])):
            raise OSError(f"could not write a prepared copy of {n} in {out}")
    notes.update(
        {
            "size": [width, height],
            "cameras": len(kinds),
            "exif_rotated": rotated_by_exif,
            "turned_90": turned,
            "rescaled": rescaled,
        }
    )
    return PreparedSet(out, used, width, height, groups if len(kinds) > 1 else None, notes, tmp, camera)


def sharpness(img: np.ndarray) -> float:
    """Variance of the Laplacian of the image's grey levels (in [0, 1]) at SHARPNESS_SIDE pixels on
    its long side: how much fine detail it holds, which blur removes."""
    grey = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY).astype(np.float32)
    grey /= 65535.0 if img.dtype == np.uint16 else 255.0
    h, w = grey.shape
    s = SHARPNESS_SIDE / max(h, w)
    if s < 1:
        grey = cv2.resize(grey, (max(1, round(w * s)), max(1, round(h * s))), interpolation=cv2.INTER_AREA)
    return float(cv2.Laplacian(grey, cv2.CV_32F).var())


def blurred_views(sharp: dict[str, float], min_images: int) -> list[str]:
    """The views to leave out as blurred (sorted by name): sharpness under BLUR_RATIO of the
    median, where they are at most MAX_BLURRED_SHARE of the set and min_images remain."""
    if not sharp:
        return []
    limit = BLUR_RATIO * float(np.median(list(sharp.values())))
    blurred = sorted(n for n, v in sharp.items() if v < limit)
    if len(blurred) > MAX_BLURRED_SHARE * len(sharp) or len(sharp) - len(blurred) < min_images:
        return []
    return blurred


def _cover(img: np.ndarray, width: int, height: int) -> np.ndarray:
    """`img` scaled (aspect kept) to cover width x height, cropped about its centre."""
    h, w = img.shape[:2]
    s = max(width / w, height / h)
    sw, sh = max(width, round(w * s)), max(height, round(h * s))
    scaled = cv2.resize(img, (sw, sh), interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR)
    x0, y0 = (sw - width) // 2, (sh - height) // 2
    return np.ascontiguousarray(scaled[y0 : y0 + height, x0 : x0 + width])


def _listing(names: list[str], limit: int = 5) -> str:
    return ", ".join(names[:limit]) + (f" and {len(names) - limit} more" if len(names) > limit else "")
