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

from gsa.ziparchive import ZipArchiveError, ZipLimits
from gsa.ziparchive import check_zip as _check_zip

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")
MIN_IMAGES = 3
MAX_ZIP_ENTRIES = 2000
MAX_ZIP_BYTES = 2 * 1024**3  # total uncompressed
MAX_ZIP_RATIO = 200.0  # uncompressed / compressed per entry: zip bombs go far beyond
MAX_IMAGE_PIXELS = 64_000_000


class ImageSetError(ValueError):
    """An image set that cannot be reconstructed (too few, unreadable, mixed sizes, unsafe archive)."""


@dataclass
class ImageSet:
    """Images sharing one size. directory: where the files are (a temp dir for zips);
    names: file names relative to it (sorted); width, height: pixels."""

    directory: Path
    names: list[str]
    width: int
    height: int
    _tmp: object | None = field(default=None, repr=False)  # keeps an extracted zip alive

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
    """(H, W, 3) float32 RGB in [0, 1]; alpha is dropped, grey is expanded."""
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ImageSetError(f"{Path(path).name}: not a readable image")
    if img.dtype == np.uint16:
        img = (img / 257.0).astype(np.uint8)
    if img.ndim == 2:
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)
    elif img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)
    else:
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
    not something silently skipped, so that a user learns what was used.
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
    sizes: dict[tuple[int, int], list[str]] = {}
    for n in names:
        # Decode fully: a truncated or mislabelled file must fail here, not inside SfM.
        img = cv2.imread(str(directory / n), cv2.IMREAD_UNCHANGED)
        if img is None or img.size == 0:
            raise ImageSetError(f"{n}: not a readable image")
        h, w = img.shape[:2]
        if h * w > max_pixels:
            raise ImageSetError(f"{n}: {w}x{h} exceeds the {max_pixels}-pixel limit")
        sizes.setdefault((w, h), []).append(n)
    if len(sizes) > 1:
        desc = "; ".join(f"{w}x{h}: {len(v)} (e.g. {v[0]})" for (w, h), v in sizes.items())
        raise ImageSetError(f"images have mixed sizes ({desc}); all images must share one size")
    ((w, h),) = sizes.keys()
    return ImageSet(directory, names, w, h, tmp)
