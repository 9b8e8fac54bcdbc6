"""Load an image set from a directory or a zip archive, with clear errors.

Zip archives are checked before anything is extracted (entry count, total
uncompressed size, per-entry compression ratio, absolute or `..` paths,
symlinks), because they come from users of the service.
"""

from __future__ import annotations

import os
import tempfile
import zipfile
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath

import cv2
import numpy as np

from gsa.errors import GSAError
from gsa.ziparchive import ZipArchiveError, ZipLimits
from gsa.ziparchive import check_zip as _check_zip

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")
MIN_IMAGES = 3
MAX_ZIP_ENTRIES = 2000
MAX_ZIP_BYTES = 2 * 1024**3  # total uncompressed
MAX_ZIP_RATIO = 200.0  # uncompressed / compressed per entry: zip bombs go far beyond
MAX_IMAGE_PIXELS = 64_000_000


class ImageSetError(GSAError, ValueError):
    """An image set that cannot be reconstructed (too few readable images, an image over the pixel limit, unsafe archive)."""


@dataclass
class ImageSet:
    """Images sharing one size. directory: where the files are (a temp dir for zips, or for a
    set prepared by gsa.recon.photos: EXIF-rotated, mixed orientations or sizes); names: file
    names relative to it (sorted); width, height: pixels; camera_groups: each image's SfM
    camera (None: one camera); notes: what preparing the set changed (report.json); camera:
    what EXIF says took every image (gsa.recon.photos.exif_camera), None unless one camera."""

    directory: Path
    names: list[str]
    width: int
    height: int
    _tmp: object | None = field(default=None, repr=False)  # keeps an extracted zip alive
    camera_groups: list[int] | None = None
    notes: dict = field(default_factory=dict)
    _prepared: object | None = field(default=None, repr=False)  # keeps a prepared copy alive
    camera: tuple | None = None

    def __len__(self) -> int:
        return len(self.names)

    def paths(self) -> list[Path]:
        return [self.directory / n for n in self.names]

    def read(self, i: int) -> np.ndarray:
        """(H, W, 3) float32 RGB in [0, 1]."""
        return read_rgb(self.directory / self.names[i])

    def read_all(self) -> np.ndarray:
        """(C, H, W, 3) float32 RGB in [0, 1]."""
        return np.stack([self.read(i) for i in range(len(self))])


def read_rgb(path: str | os.PathLike) -> np.ndarray:
    """(H, W, 3) float32 RGB in [0, 1], as the image is meant to be seen (EXIF orientation
    applied); alpha is dropped, grey is expanded."""
    img = cv2.imread(str(path), cv2.IMREAD_COLOR | cv2.IMREAD_ANYDEPTH)
    if img is None:
        raise ImageSetError(f"{Path(path).name}: not a readable image")
    if img.dtype == np.uint16:
        img = (img / 257.0).astype(np.uint8)
    img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    return img.astype(np.float32) / 255.0


def write_rgb(path: str | os.PathLike, rgb: np.ndarray) -> None:
    """Write (H, W, 3) float RGB in [0, 1] as an 8-bit image."""
    bgr = cv2.cvtColor((np.clip(rgb, 0, 1) * 255.0 + 0.5).astype(np.uint8), cv2.COLOR_RGB2BGR)
    if not cv2.imwrite(str(path), bgr):
        raise OSError(f"could not write {path}")


def check_zip(
    path: Path, *, max_entries: int = MAX_ZIP_ENTRIES, max_bytes: int = MAX_ZIP_BYTES, max_ratio: float = MAX_ZIP_RATIO
) -> list[zipfile.ZipInfo]:
    """Validate a zip archive without extracting it (gsa.ziparchive: the one validator,
    shared with the service; every entry is read through); returns its file entries."""
    try:
        return _check_zip(Path(path), ZipLimits(max_entries=max_entries, max_bytes=max_bytes, max_ratio=max_ratio))
    except ZipArchiveError as exc:
        raise ImageSetError(str(exc)) from None


def _is_hidden(name: str) -> bool:
    return any(p.startswith(".") or p == "__MACOSX" for p in PurePosixPath(name).parts)


def load_image_set(
    path: str | os.PathLike, *, min_images: int = MIN_IMAGES, max_pixels: int = MAX_IMAGE_PIXELS
) -> ImageSet:
    """Open a directory (flat; sub-directories are ignored) or a .zip of images.

    Every non-hidden file must be an image: a stray non-image file is an error,
    not something silently skipped, so that a user learns what was used. Photo sets as
    people take them (EXIF rotation, portrait and landscape, several camera sizes, a few
    files that do not decode) are brought to one size by gsa.recon.photos.
    """
    path = Path(path)
    tmp = None
    if not path.exists():
        raise ImageSetError(f"{path}: no such file or directory")
    if path.is_file():
        if not zipfile.is_zipfile(path):
            raise ImageSetError(f"{path.name}: expected a directory of images or a .zip archive")
        infos = check_zip(path)
        tmp = tempfile.TemporaryDirectory(prefix="gsa-images-")
        directory = Path(tmp.name)
        with zipfile.ZipFile(path) as zf:
            for info in infos:
                if _is_hidden(info.filename):
                    continue
                # Flatten: names keep only their base name; duplicates are an error.
                target = directory / PurePosixPath(info.filename.replace("\\", "/")).name
                if target.exists():
                    raise ImageSetError(f"{path.name}: two entries named {target.name}")
                with zf.open(info) as src, open(target, "wb") as dst:
                    dst.write(src.read(info.file_size + 1))
    else:
        directory = path
    names = sorted(p.name for p in directory.iterdir() if p.is_file() and not _is_hidden(p.name))
    bad = [n for n in names if Path(n).suffix.lower() not in IMAGE_SUFFIXES]
    if bad:
        raise ImageSetError(
            f"not image files (by extension): {', '.join(bad[:5])}"
            + (f" and {len(bad) - 5} more" if len(bad) > 5 else "")
        )
    if len(names) < min_images:
        raise ImageSetError(f"{len(names)} image(s) found in {path.name}; at least {min_images} are needed")
    from gsa.recon.photos import prepare_photos

    ready = prepare_photos(directory, names, min_images=min_images, max_pixels=max_pixels, error=ImageSetError)
    return ImageSet(
        ready.directory,
        ready.names,
        ready.width,
        ready.height,
        tmp,
        ready.camera_groups,
        ready.notes,
        ready.tmp,
        ready.camera,
    )
