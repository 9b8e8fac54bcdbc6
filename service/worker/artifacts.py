"""A job's output files: their public names, content types and upload to storage."""

from __future__ import annotations

import mimetypes
import re
from collections.abc import Callable
from pathlib import Path

from service.backend import Backend
from service.models import Artifact, Job


def content_type(name: str) -> str:
    if name.endswith(".ply"):
        return "application/x-ply"
    if name.endswith(".json"):
        return "application/json"
    return mimetypes.guess_type(name)[0] or "application/octet-stream"


def collect_outputs(paths: dict, prefix: str) -> list[tuple[str, Path]]:
    """write_outputs' {artifact name: path} -> (public name, file); names may hold
    one folder level ("renders/before.png"), served as artifacts/renders/before.png."""

    def clean(n: str) -> str:
        return "/".join(re.sub(r"[^A-Za-z0-9._-]", "_", seg).lstrip("._-") or "x" for seg in n.split("/"))

    out = []
    for name, p in sorted(paths.items()):
        p, name = Path(p), clean(name)
        if p.is_dir():
            out += [(f"{prefix}{name}/{f.name}", f) for f in sorted(p.iterdir()) if f.is_file()]
        else:
            out.append((prefix + name, p))
    return out


def synchronized_renders(backend: Backend, job: Job, target, transforms, work: Path, notes: list) -> list:
    """Paper App. B: every model in the reference frame, seen from the same cameras."""
    # lazy: the renderer loads torch
    from gsa.io.formats import read_model
    from gsa.render.views import write_synchronized_renders
    from gsa.sim3 import Sim3

    if any(ref.kind != "ply" for ref in job.sources):
        notes.append("synchronized renders skipped: they need every source as a 3DGS model file")
        return []
    models = [target] + [
        read_model(work / f"source{i}.ply", max_gaussians=backend.settings.max_gaussians)
        for i in range(len(job.sources))
    ]
    feats = all(m.features is not None for m in models)
    paths = write_synchronized_renders(models, work / "sync", transforms=[Sim3.identity(), *transforms], features=feats)
    return [(f"synchronized/{Path(p).name}", Path(p)) for _, p in sorted(paths.items())]


def store_artifacts(
    backend: Backend, files: list[tuple[str, Path]], prefix: str, progress: Callable[[str, float], None] | None = None
) -> list[Artifact]:
    """Upload (public name, file) pairs under `prefix` and describe them as artifacts.
    `progress("storing", fraction)` before each: a scene's merged model is gigabytes, so
    storing it (to S3 above all) is a stage of its own that a cancel can stop."""
    artifacts = []
    total = sum(path.stat().st_size for _, path in files) or 1
    done = 0
    for name, path in files:
        if progress is not None:
            progress("storing", done / total)
        done += path.stat().st_size
        key = f"{prefix}/{name}"
        with open(path, "rb") as fh:
            size = backend.storage.put(key, fh)
        artifacts.append(Artifact(name=name, key=key, size=size, content_type=content_type(name)))
    return artifacts
