"""Model artifacts in a requested 3DGS format (GET .../artifacts/aligned.ply?format=spz).

Conversions run on request in the API process, through the library's readers and writers
(gsa.io.formats): the stored artifact is read, mapped into the internal convention and
written in the requested format's own axes. Served whole (no byte ranges).
"""

from __future__ import annotations

import tempfile
from pathlib import Path, PurePosixPath

from service.backend import Backend
from service.inputs import model_content_type
from service.models import Artifact
from service.problems import invalid_input


def converted_artifact(b: Backend, art: Artifact, fmt: str) -> tuple[bytes, str, str]:
    """(body, file name, content type) of a model artifact in format `fmt`."""
    from gsa.io.formats import EXTENSIONS, FORMATS, FormatError, format_for_path, read_model, write_model

    if fmt not in FORMATS:
        raise invalid_input(f"format {fmt!r} is not one of {', '.join(FORMATS)}")
    if format_for_path(art.name) is None:
        raise invalid_input(f"{art.name} is not a 3DGS model artifact; only models convert")
    stem = PurePosixPath(art.name).name
    for ext in sorted(EXTENSIONS.values(), key=len, reverse=True):
        if stem.lower().endswith(ext):
            stem = stem[: -len(ext)]
            break
    with tempfile.TemporaryDirectory(prefix="gsa-convert-") as tmp:
        src = b.storage.download(art.key, Path(tmp) / "model")
        try:
            model = read_model(src, max_gaussians=b.settings.max_gaussians)
        except FormatError as exc:
            raise invalid_input(f"{art.name}: {exc.problem}") from None
        out = write_model(model, Path(tmp) / f"out{EXTENSIONS[fmt]}", fmt)
        return out.read_bytes(), f"{stem}{EXTENSIONS[fmt]}", model_content_type(fmt)
