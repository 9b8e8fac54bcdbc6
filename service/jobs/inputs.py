"""Job inputs: validating uploads (3DGS PLY headers, image-set zips, images) and,
on the worker, loading them as models (load_input).

All checks read headers / central directories only: nothing is decoded or
extracted before it has passed the limits, so a hostile upload (zip bomb,
`../` entry, a PLY claiming a billion Gaussians) costs almost nothing.
"""

from __future__ import annotations

import lzma
import re
import struct
import zipfile
import zlib
from collections.abc import Callable
from pathlib import Path, PurePosixPath

import numpy as np

from gsa.ziparchive import ZipArchiveError, ZipLimits, check_zip
from gsa.ziparchive import unsafe_member_name as unsafe_member_name  # re-exported: one rule for zip names
from service.backend import Backend
from service.models import InputRef, Job
from service.problems import Problem, invalid_input, too_large

IMAGE_EXTS = {".png", ".jpg", ".jpeg"}


def sniff(head: bytes) -> str | None:
    if head.startswith(b"ply"):
        return "ply"
    if head.startswith((b"PK\x03\x04", b"PK\x05\x06")):
        return "zip"
    if head.startswith(b"\x89PNG\r\n\x1a\n"):
        return "png"
    if head.startswith(b"\xff\xd8"):
        return "jpeg"
    return None


def validate_ply(path: Path, max_gaussians: int, display_name: str) -> int:
    """Header-level check of a 3DGS PLY; returns the Gaussian count.

    Uses the library's own header parser so the service accepts exactly what
    the workers can read, without loading the body (which may be gigabytes).
    """
    from gsa.io import ply as plymod  # lazy: keeps the library off API start-up

    try:
        with open(path, "rb") as fh:
            fmt, header_len, elements = plymod._parse_header(path, fh)
        if not elements or elements[0][0] != "vertex":
            raise plymod.PlyError(path, "the first element must be 'vertex' (the Gaussians)")
        _, count, props = elements[0]
        if any(t == "list" for _, t in props):
            raise plymod.PlyError(path, "the vertex element has list properties; 3DGS vertices are scalar")
        plymod._sh_and_feature_layout(path, [n for n, _ in props])
        if count == 0:
            raise plymod.PlyError(path, "the file holds zero Gaussians")
        if count > max_gaussians:
            raise too_large(f"{display_name}: {count} Gaussians exceeds the limit of {max_gaussians}")
        if plymod.FORMATS[fmt] is None:
            plymod.read_ply(path, max_gaussians=max_gaussians)  # ASCII: only a full parse can tell
        else:
            # the reader's own rule: a body shorter or longer than the header's counts say is refused
            # here, not accepted and failed in the worker
            plymod.check_body_length(path, path.stat().st_size - header_len, elements)
            _check_ply_values(path, fmt, header_len, int(count), props)
        return int(count)
    except plymod.PlyError as exc:
        raise invalid_input(f"{display_name}: {exc.problem}") from None


def _check_ply_values(path: Path, fmt: str, header_len: int, count: int, props) -> None:
    """Refuse NaN/Inf in a binary PLY's body as the reader (read_ply) would, chunk by chunk:
    the body is read through the reader's own chunker and every chunk is checked by
    GaussianModel.validate, so the API never holds more than one chunk of a large file.
    Infinite opacity logits and log-scales are let through: the reader clamps them."""
    from gsa.io import ply as plymod
    from gsa.model import GaussianModel, ModelError

    names = [n for n, _ in props]
    degree, feat_dim = plymod._sh_and_feature_layout(path, names)
    index = {n: i for i, n in enumerate(names)}
    dtype = np.dtype([(n, plymod.FORMATS[fmt] + t) for n, t in props])
    k = plymod.sh_coeff_count(degree)
    rest_keys = [f"f_rest_{i}" for i in range(3 * (k - 1))]
    feat_keys = [f"semantic_{i}" for i in range(feat_dim)]
    for lo, hi, cols in plymod._binary_chunks(path, header_len, dtype, count, props, index):
        n = hi - lo
        sh = np.empty((n, k, 3), np.float32)
        sh[:, 0, :] = cols(["f_dc_0", "f_dc_1", "f_dc_2"])
        if k > 1:  # channel-major in the file
            sh[:, 1:, :] = cols(rest_keys).reshape(n, 3, k - 1).transpose(0, 2, 1)
        opacity = np.asarray(cols(["opacity"])[:, 0], np.float32)
        log_scales = np.asarray(cols(["scale_0", "scale_1", "scale_2"]), np.float32)
        chunk = GaussianModel(
            means=np.asarray(cols(["x", "y", "z"]), np.float32),
            quats=np.asarray(cols(["rot_0", "rot_1", "rot_2", "rot_3"]), np.float32),
            log_scales=np.where(np.isinf(log_scales), 0.0, log_scales).astype(np.float32),  # clamped on read
            opacity_logits=np.where(np.isinf(opacity), 0.0, opacity).astype(np.float32),  # clamped on read
            sh=sh,
            features=np.asarray(cols(feat_keys), np.float32) if feat_dim else None,
        )
        if "filter_3D" in index:
            f3d = cols(["filter_3D"])[:, 0]
            if not np.isfinite(f3d).all() or (f3d < 0).any():
                raise plymod.PlyError(path, "filter_3D holds negative, NaN or Inf values")
        try:
            chunk.validate(source="data")
        except ModelError as exc:
            raise plymod.PlyError(path, str(exc)) from None


def model_format(head: bytes, size: int, path: Path | None = None) -> str | None:
    """The 3DGS format of an upload from its first bytes (gsa.io.formats.sniff_bytes), or None.
    A zip is a SOG model only when it holds meta.json (else it is an image set)."""
    from gsa.io.formats import sniff_bytes  # lazy: keeps the library off API start-up

    fmt = sniff_bytes(head, size)
    if fmt == "sog":
        if path is None:
            return None
        try:
            with zipfile.ZipFile(path) as zf:
                return "sog" if "meta.json" in zf.namelist() else None
        except MemoryError:
            raise
        # hostile bytes fail in zipfile in no closed set of ways (BadZipFile, OSError, ValueError,
        # ...): not a SOG, and validate_zip then says why
        except Exception:  # noqa: BLE001
            return None
    return fmt


MODEL_CONTENT_TYPES = {
    "ply": "application/x-ply",
    "compressed-ply": "application/x-ply",
    "glb": "model/gltf-binary",
    "sog": "application/zip",
}


def model_content_type(fmt: str) -> str:
    return MODEL_CONTENT_TYPES.get(fmt, "application/octet-stream")


def validate_model(path: Path, max_gaussians: int, display_name: str) -> int:
    """Full check of a 3DGS model in a format other than INRIA PLY (these are compressed:
    decoding is the only complete check, and the formats' readers refuse lying headers
    before decoding); returns the Gaussian count."""
    from gsa.io.formats import FormatError, read_model

    try:
        return len(read_model(path, max_gaussians=max_gaussians))
    except FormatError as exc:
        if "exceeds the limit" in exc.problem:
            raise too_large(f"{display_name}: {exc.problem}") from None
        raise invalid_input(f"{display_name}: {exc.problem}") from None


def image_size(head: bytes) -> tuple[int, int] | None:
    """(width, height) from a PNG IHDR or JPEG SOF marker, without decoding."""
    if head.startswith(b"\x89PNG\r\n\x1a\n") and len(head) >= 24:
        w, h = struct.unpack(">II", head[16:24])
        return w, h
    if head.startswith(b"\xff\xd8"):
        i = 2
        while i + 9 < len(head):
            if head[i] != 0xFF:
                i += 1
                continue
            marker = head[i + 1]
            if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:
                i += 2
                continue
            seg = struct.unpack(">H", head[i + 2 : i + 4])[0]
            if marker in (
                0xC0,
                0xC1,
                0xC2,
                0xC3,
                0xC5,
                0xC6,
                0xC7,
                0xC9,
                0xCA,
                0xCB,
                0xCD,
                0xCE,
                0xCF,
            ):
                h, w = struct.unpack(">HH", head[i + 5 : i + 9])
                return w, h
            i += 2 + seg
    return None


def check_image(head: bytes, name: str, settings) -> None:
    if sniff(head) not in ("png", "jpeg"):
        raise invalid_input(f"{name}: not a PNG or JPEG image")
    wh = image_size(head)
    if wh is None:
        raise invalid_input(f"{name}: cannot read the image dimensions")
    if wh[0] * wh[1] > settings.max_image_pixels:
        raise too_large(f"{name}: {wh[0]}x{wh[1]} exceeds the limit of {settings.max_image_pixels} pixels")


def zip_limits(settings) -> ZipLimits:
    return ZipLimits(
        max_entries=settings.max_zip_entries,
        max_bytes=settings.max_zip_uncompressed_bytes,
        max_ratio=settings.max_zip_ratio,
    )


def _zip_problem(exc: ZipArchiveError) -> Problem:
    return too_large(str(exc)) if exc.limit else invalid_input(str(exc))


def validate_zip(path: Path, settings, display_name: str) -> int:
    """Check an image-set zip with the library's validator (gsa.ziparchive: directory,
    names, sizes, and every entry read through), plus the service's image limits;
    returns the image count. Every defect is a 422 (a limit passed: 413)."""
    images = 0

    def on_file(info: zipfile.ZipInfo, head: bytes) -> None:
        nonlocal images
        if PurePosixPath(info.filename).suffix.lower() in IMAGE_EXTS:
            images += 1
            if images > settings.max_images:
                raise too_large(f"{display_name}: more than {settings.max_images} images (the limit)")
            check_image(head, f"{display_name}:{info.filename}", settings)  # dimensions from the first 64 KiB

    try:
        check_zip(path, zip_limits(settings), label=display_name, head_bytes=65536, on_file=on_file)
    except ZipArchiveError as exc:
        raise _zip_problem(exc) from None
    if images == 0:
        raise invalid_input(f"{display_name}: the archive holds no PNG/JPEG images")
    return images


def safe_extract(path: Path, dest: Path, settings) -> Path:
    """Extract the images of a zip that passed validate_zip (checked again here).

    Files are flattened to numbered names: the reconstruction reads one folder,
    and no archive path is ever used as a filesystem path."""
    display_name = path.name
    validate_zip(path, settings, display_name)
    dest.mkdir(parents=True, exist_ok=True)
    root = dest.resolve()
    n = 0
    with zipfile.ZipFile(path) as zf:
        for info in zf.infolist():
            name = PurePosixPath(info.filename)
            if info.is_dir() or name.suffix.lower() not in IMAGE_EXTS:
                continue
            if name.name.startswith("."):  # macOS resource forks and other hidden files
                continue
            out = root / f"{n:05d}{name.suffix.lower()}"
            n += 1
            try:
                with zf.open(info) as src, open(out, "wb") as dst:
                    remaining = info.file_size + 1
                    while chunk := src.read(1 << 20):
                        remaining -= len(chunk)
                        if remaining < 0:  # the directory lied about the size
                            raise invalid_input(f"{display_name}: {info.filename!r} is larger than its declared size")
                        dst.write(chunk)
            except (zipfile.BadZipFile, EOFError, zlib.error, lzma.LZMAError) as exc:
                # validated just above: only an archive changed since could get here
                raise invalid_input(f"{display_name}: entry {info.filename!r} is corrupt ({exc})") from None
    return dest


# ------------------------------------------------ loading a job's inputs (worker side)
def load_input(
    backend: Backend,
    ref: InputRef,
    workdir: Path,
    name: str,
    progress: Callable[[str, float], None],
    reconstructions: dict | None = None,
    recon_iterations: int | None = None,
    calibration=None,
):
    """A job input as a GaussianModel: a PLY as is, an image set through gsa.recon
    (its summary and model file are recorded in `reconstructions`; `calibration`, another
    input's intrinsics, is held fixed where its EXIF names the same camera)."""
    reconstructions = {} if reconstructions is None else reconstructions
    from gsa.io.formats import read_model  # lazy: keeps the library off API start-up

    s = backend.settings
    if ref.kind == "ply":  # a 3DGS model in any format (sniffed; the file name does not matter)
        path = backend.storage.download(ref.key, workdir / f"{name}.ply")
        return read_model(path, max_gaussians=s.max_gaussians)
    if ref.kind == "images":
        # lazy: SfM and 3DGS training load OpenCV, pycolmap and torch
        from gsa.recon import ImageSetError, MaskError, SfMError, reconstruct

        archive = backend.storage.download(ref.key, workdir / f"{name}.zip")
        images = safe_extract(archive, workdir / f"{name}-images", s)
        preset = "gpu" if s.worker_device.startswith("cuda") else "cpu"
        try:
            res = reconstruct(
                images,
                workdir / f"{name}-recon",
                preset=preset,
                progress=lambda st, f: progress(f"recon:{st}", f),
                iterations=recon_iterations,
                calibration=calibration,
            )
        except (ImageSetError, SfMError, MaskError) as exc:
            raise Problem(
                422,
                "reconstruction-failed",
                "Reconstruction failed",
                f"{name} images: {exc}",
            ) from None
        summary = {k: v for k, v in res.summary().items() if k not in ("model", "cameras")}
        reconstructions[name] = (summary, Path(res.model_path))
        return res.model
    raise invalid_input(f"unknown input kind {ref.kind!r}")


# ------------------------------------------- worker paths out of client-facing errors
# A job's inputs live in a worker temp folder (service.worker.execution: tempfile prefix "gsa-job-")
# as <role>.ply, <role>.zip, <role>-images/..., <role>-recon/... (load_input above), role
# "target" or "source<i>". Library errors name those paths; clients know their files by name.
_WORK_PATH = re.compile(r"(?:/[\w.-]+)*/gsa-job-[\w.-]+((?:/[\w.-]+)*)")
_ROLE = re.compile(r"^/(target|source(\d+))(\.ply|\.zip|-images|-recon)?(?=/|$)(/.*)?$")


def asset_label(ref: InputRef) -> str:
    return ref.filename or ref.asset_id


def redact_work_paths(text: str, job: Job) -> str:
    """`text` with every worker temp path replaced by the name of the asset it came from
    (an image set's member keeps its name inside: `photos.zip/00003.png`)."""

    def repl(m: re.Match) -> str:
        rest = m.group(1)
        r = _ROLE.match(rest)
        if r is None:
            return rest.rsplit("/", 1)[-1] or "job workspace"
        role, index, kind, inner = r.groups()
        ref = job.target if role == "target" else (job.sources[int(index)] if int(index) < len(job.sources) else None)
        label = asset_label(ref) if ref is not None else role
        if kind == "-images" and inner:
            return f"{label}{inner}"
        return label

    return _WORK_PATH.sub(repl, text)


def redact_problem(problem: dict, job: Job) -> dict:
    """A job's problem details with worker paths replaced by asset names (every string member)."""
    return {k: redact_work_paths(v, job) if isinstance(v, str) else v for k, v in problem.items()}
