"""Model artifacts in a requested 3DGS format (GET .../artifacts/aligned.ply?format=spz).

Conversions run on request in the API process, through the library's readers and writers
(gsa.io.formats): the stored artifact is read, mapped into the internal convention and
written in the requested format's own axes. Served whole (no byte ranges).
"""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path, PurePosixPath

from service.backend import Backend
from service.inputs import model_content_type
from service.models import Artifact
from service.problems import invalid_input

CHUNK = 1 << 20


def converted_artifact(b: Backend, art: Artifact, fmt: str) -> tuple[Iterator[bytes], int, str, str, Callable]:
    """(body chunks, size, file name, content type, clean-up) of a model artifact in format
    `fmt`. The converted file is streamed from a temp folder, so a scene-size conversion never
    holds its output whole in memory; the caller runs clean-up once the response is over
    (the body removes the folder too when it has been read or closed)."""
    from gsa.io.formats import EXTENSIONS, FORMATS, format_for_path, read_model, write_model
    from gsa.io.ply import PlyError  # FormatError's base: read_model raises it for PLY files

    if fmt not in FORMATS:
        raise invalid_input(f"format {fmt!r} is not one of {', '.join(FORMATS)}")
    if format_for_path(art.name) is None:
        raise invalid_input(f"{art.name} is not a 3DGS model artifact; only models convert")
    stem = PurePosixPath(art.name).name
    for ext in sorted(EXTENSIONS.values(), key=len, reverse=True):
        if stem.lower().endswith(ext):
            stem = stem[: -len(ext)]
            break
    tmp = Path(tempfile.mkdtemp(prefix="gsa-convert-"))
    try:
        src = b.storage.download(art.key, tmp / "model")
        try:
            # The service wrote this file: a merged model is a source plus the target, each
            # within max_gaussians, so it may hold up to twice that many.
            model = read_model(src, max_gaussians=2 * b.settings.max_gaussians)
        except PlyError as exc:
            raise invalid_input(f"{art.name}: {exc.problem}") from None
        out = write_model(model, tmp / f"out{EXTENSIONS[fmt]}", fmt)
        del model
        src.unlink()
        size = out.stat().st_size
        return (
            _stream(out, tmp),
            size,
            f"{stem}{EXTENSIONS[fmt]}",
            model_content_type(fmt),
            lambda: shutil.rmtree(tmp, ignore_errors=True),
        )
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def _stream(path: Path, tmp: Path) -> Iterator[bytes]:
    try:
        with open(path, "rb") as fh:
            while chunk := fh.read(CHUNK):
                yield chunk
    finally:  # also when the client goes away mid-body (the generator is closed)
        shutil.rmtree(tmp, ignore_errors=True)
