"""Every 3DGS file format in and out: sniffing, reading into the internal convention, writing.

`read_model` detects the format from the bytes (magic numbers and headers, never the
extension), reads it, maps its axes into the internal convention (gsa.io.frames) and
records `metadata["format"]`. `write_model` maps back and writes atomically. Every problem
is one `FormatError` (a PlyError, so existing handlers catch it) naming the file.
"""

from __future__ import annotations

import os
import struct
from dataclasses import replace
from pathlib import Path

import numpy as np

from gsa.io import frames
from gsa.io.atomic import mkstemp_for
from gsa.io.ply import (
    DEFAULT_MAX_GAUSSIANS,
    LOG_SCALE_BOUND,
    MAX_HEADER_BYTES,
    MAX_OPACITY_LOGIT,
    PlyError,
    clamp_infinite,
    read_ply,
    write_ply,
)
from gsa.model import GaussianModel, ModelError

FORMATS = ("ply", "compressed-ply", "splat", "ksplat", "spz", "sog", "glb")
EXTENSIONS = {
    "ply": ".ply",
    "compressed-ply": ".compressed.ply",
    "splat": ".splat",
    "ksplat": ".ksplat",
    "spz": ".spz",
    "sog": ".sog",
    "glb": ".glb",
}
# Highest SH degree each format stores (a higher one is truncated on write).
MAX_SH_DEGREE = {"ply": 3, "compressed-ply": 3, "splat": 0, "ksplat": 2, "spz": 3, "sog": 3, "glb": 3}
# Largest round-trip error per attribute each format is held to (tests/test_formats.py;
# measured values in docs/formats.md): position relative to the bounding-box diagonal,
# rotation in degrees, |Δ log scale|, opacity and colour on [0, 1], SH coefficients.
# SOG's codebooks (256 entries) and SH palette (gsa/io/sog.py: 4096 k-means entries, exact up to
# 4096 Gaussians) depend on the data: its bounds are loose (SH 0.27 measured at 1M, random SH).
ROUNDTRIP_BOUNDS = {
    "ply": dict(position_rel=0, rotation_deg=1e-3, log_scale=0, opacity=1e-7, colour=0, sh_rest=0),
    "glb": dict(position_rel=0, rotation_deg=1e-3, log_scale=1e-6, opacity=1e-6, colour=0, sh_rest=0),
    "splat": dict(position_rel=0, rotation_deg=1.0, log_scale=1e-6, opacity=1 / 255, colour=1 / 255),
    "ksplat": dict(position_rel=0, rotation_deg=1e-3, log_scale=1e-6, opacity=1 / 255, colour=1 / 255, sh_rest=1e-6),
    "compressed-ply": dict(
        position_rel=1e-3, rotation_deg=0.5, log_scale=0.01, opacity=1 / 255, colour=1 / 255, sh_rest=0.017
    ),
    "spz": dict(position_rel=1e-4, rotation_deg=0.5, log_scale=0.032, opacity=1 / 255, colour=0.01, sh_rest=0.07),
    "sog": dict(position_rel=1e-4, rotation_deg=1.5, log_scale=0.1, opacity=0.01, colour=0.02, sh_rest=0.3),
}


# Formats that store alpha in 8 bits. Stored 0 and 255 are read as ALPHA_EPS and 1 − ALPHA_EPS
# in all of them (gaussforge's decoders give ±Inf for SPZ, alpha clamped to [0.001, 0.999] for
# compressed PLY, [1e-6, 1 − 1e-6] for .ksplat), and counted in the reader's warning.
EIGHT_BIT_ALPHA = ("compressed-ply", "splat", "ksplat", "spz", "sog")
_SATURATED_LOGIT = float(np.log(254.5 / 0.5))  # beyond it, the stored alpha was 0 or 255


class FormatError(PlyError):
    """A model file that is not readable in any supported format; one line naming the file."""


def sniff_bytes(head: bytes, size: int) -> str | None:
    """The format of a file from its first bytes (≥ 4096 when the file has them) and size."""
    if head.startswith(b"ply"):
        end = head.find(b"end_header", 0, MAX_HEADER_BYTES)
        header = head[: end if end >= 0 else MAX_HEADER_BYTES]
        return "compressed-ply" if b"element chunk " in header else "ply"
    if head[:4] == b"glTF":
        return "glb"
    if head[:2] == b"\x1f\x8b" or head[:4] == b"NGSP":
        return "spz"
    if head[:4] == b"PK\x03\x04":
        return "sog"
    if len(head) >= 24 and head[0] == 0 and head[1] == 1 and size >= 4096:
        max_sections, sections, _, _, level = struct.unpack_from("<IIIIH", head, 4)
        if 1 <= max_sections <= 1 << 16 and sections <= max_sections and level <= 2:
            return "ksplat"
    if size > 0 and size % 32 == 0 and len(head) >= 32:
        from gsa.io.splat import SPLAT_DTYPE

        if _plausible_splat(np.frombuffer(head[: (len(head) // 32) * 32], SPLAT_DTYPE)):
            return "splat"
    return None


def _plausible_splat(first: np.ndarray) -> bool:
    """Headerless .splat: the first records must look like Gaussians (finite positions within
    1e6, sizes 0 or 1e-14..1e14 — writers keep them within e^±30 —, not all at one point), so that arbitrary bytes whose length is a
    multiple of 32 are not taken for one."""
    with np.errstate(invalid="ignore", over="ignore"):
        pos, scale = first["pos"].astype(np.float64), first["scale"].astype(np.float64)
        if not (np.isfinite(pos).all() and (np.abs(pos) < 1e6).all()):
            return False
        sized = ((scale == 0) | ((scale >= 1e-14) & (scale <= 1e14))).all(axis=1).mean()
    return bool(sized >= 0.9 and (len(first) == 1 or np.ptp(pos, axis=0).max() > 0))


def sniff(path: str | os.PathLike) -> str:
    """The format of a file, from its bytes. Raises FormatError when none fits."""
    path = Path(path)
    try:
        size = path.stat().st_size
        with open(path, "rb") as fh:
            head = fh.read(MAX_HEADER_BYTES)
    except OSError as exc:
        raise FormatError(path, f"cannot open: {exc.strerror or exc}") from None
    if size == 0:
        raise FormatError(path, "the file is empty")
    fmt = sniff_bytes(head, size)
    if fmt is None:
        raise FormatError(path, f"not a PLY nor any other supported 3DGS format ({', '.join(FORMATS[1:])})")
    return fmt


def read_model(path: str | os.PathLike, *, max_gaussians: int = DEFAULT_MAX_GAUSSIANS) -> GaussianModel:
    """Read any supported 3DGS file into the internal convention (metadata "format" says which)."""
    path = Path(path)
    fmt = sniff(path)
    if fmt == "ply":
        model = read_ply(path, max_gaussians=max_gaussians)
    else:
        model = _read_other(path, fmt, max_gaussians)
        model.metadata["source_path"] = str(path)
    model.metadata["format"] = fmt
    return frames.to_internal(model, fmt)


def _read_other(path: Path, fmt: str, max_gaussians: int) -> GaussianModel:
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise FormatError(path, f"cannot open: {exc.strerror or exc}") from None
    try:
        if fmt == "splat":
            from gsa.io.splat import SPLAT_DTYPE, decode_splat

            if len(data) // 32 > max_gaussians:
                raise FormatError(path, f"{len(data) // 32} Gaussians exceeds the limit of {max_gaussians}")
            model = decode_splat(np.frombuffer(data, SPLAT_DTYPE))
        elif fmt == "glb":
            from gsa.io.glb import decode_glb

            model = decode_glb(data)
        else:
            from gsa.io import packed

            packed.check_header(fmt, data, max_gaussians)
            model = packed.decode(fmt, data)
        if len(model) > max_gaussians:
            raise FormatError(path, f"{len(model)} Gaussians exceeds the limit of {max_gaussians}")
        # alpha stored as exactly 0 or 1 (an infinite logit), a scale of 0: finite, with a warning
        clamped = model.metadata.pop("clamped_opacity", 0)
        if fmt in EIGHT_BIT_ALPHA:
            clamped += _saturated_alpha(model)
        clamp_infinite(model, path, clamped_opacity=clamped)
        model.validate(source="data")
    except FormatError:
        raise
    except (ValueError, ModelError) as exc:  # GlbError, PackedError, ModelError
        raise FormatError(path, f"{fmt}: {exc}") from None
    except MemoryError:
        raise FormatError(path, f"{fmt}: too large to decode in the memory available") from None
    except Exception as exc:  # noqa: BLE001 - untrusted bytes: a decoder's surprise is the file's problem
        raise FormatError(path, f"{fmt}: cannot decode ({type(exc).__name__}: {exc})") from None
    model.quats = model.quats / np.linalg.norm(model.quats, axis=1, keepdims=True)  # buffers may be read-only
    return model


def _saturated_alpha(model: GaussianModel) -> int:
    """Opacity logits of alpha stored as 0 or 255 set to ±MAX_OPACITY_LOGIT, in place; their count."""
    logits = model.opacity_logits
    saturated = np.abs(logits) > _SATURATED_LOGIT  # ±Inf too (NaN is not: validate refuses it)
    count = int(np.count_nonzero(saturated))
    if count:
        if not logits.flags.writeable:
            logits = model.opacity_logits = logits.copy()
        logits[saturated] = np.copysign(MAX_OPACITY_LOGIT, logits[saturated])
    return count


def format_for_path(path: str | os.PathLike) -> str | None:
    """The format an output file name asks for by its extension, if any."""
    name = Path(path).name.lower()
    for fmt, ext in sorted(EXTENSIONS.items(), key=lambda kv: -len(kv[1])):
        if name.endswith(ext):
            return fmt
    return None


def write_model(
    model: GaussianModel, path: str | os.PathLike, fmt: str | None = None, *, sh_degree: int | None = None
) -> Path:
    """Write an internal-convention model as `fmt` (default: from the extension, else PLY), atomically."""
    path = Path(path)
    fmt = fmt or format_for_path(path) or "ply"
    if fmt not in FORMATS:
        raise ValueError(f"unknown format {fmt!r}; choose from {', '.join(FORMATS)}")
    degree = min(model.sh_degree if sh_degree is None else sh_degree, MAX_SH_DEGREE[fmt])
    if degree != model.sh_degree:
        model = model.with_sh_degree(degree)
    model = frames.from_internal(model, fmt)
    if fmt != "ply" and np.abs(model.log_scales).max(initial=0.0) > LOG_SCALE_BOUND:
        # Linear scales past e^±30 overflow float32 once squared (e^±89: the number itself);
        # every format but PLY (which stores the logarithm) gets them within ±LOG_SCALE_BOUND.
        model = replace(model, log_scales=np.clip(model.log_scales, -LOG_SCALE_BOUND, LOG_SCALE_BOUND))
    if fmt == "ply":
        return write_ply(model, path)
    if fmt == "splat":
        from gsa.io.splat import encode_splat

        data = encode_splat(model).tobytes()
    elif fmt == "glb":
        from gsa.io.glb import encode_glb

        data = encode_glb(model)
    else:
        from gsa.io import packed

        data = packed.encode(fmt, model)
    return _atomic_write(path, data)


def _atomic_write(path: Path, data: bytes | list) -> Path:
    """Write bytes, or a list of byte strings / buffers in order, via a temp file + rename."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = mkstemp_for(path)  # 0666 & ~umask, not mkstemp's 0600
    try:
        with os.fdopen(fd, "wb") as fh:
            for part in data if isinstance(data, list) else [data]:
                fh.write(part)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path
