"""Files an alignment produces: result JSON, aligned and merged models, renders.

The CLI and the service worker both write their artifacts through here.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from gsa.align.contract import transform_contract
from gsa.align.pipeline import AlignmentResult
from gsa.io import frames
from gsa.io.atomic import mkstemp_for
from gsa.io.formats import EXTENSIONS, write_model
from gsa.io.ply import write_ply
from gsa.merge import merge_plan
from gsa.model import GaussianModel, merge_models
from gsa.sim3 import Sim3

OUTPUTS = ("result", "aligned", "merged", "renders", "preview")


def write_json(data: dict, path: Path) -> Path:
    """Atomic JSON write (temp file + rename): readers never see half a file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = mkstemp_for(path)  # 0666 & ~umask, not mkstemp's 0600
    try:
        with os.fdopen(fd, "w") as fh:
            json.dump(data, fh, indent=2)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def result_dict(result: AlignmentResult, source: GaussianModel, target: GaussianModel) -> dict:
    """result.json's content: the alignment's own fields with the transform contract
    (docs/formats.md) stated in the two models' file formats (metadata "format", PLY when unset)."""
    data = result.to_dict()
    source_format = source.metadata.get("format", "ply")
    target_format = target.metadata.get("format", "ply")
    data.update(transform_contract(result.transform, source_format, target_format))
    # Alternatives keep `transform` in align()'s internal frame (what --init RESULT --alternative N
    # and the service's refine read); `file_transform` states each one as `transform` is stated,
    # in the files' own coordinates (an SPZ or GLB input differs by a 180° turn).
    metrics = data.get("metrics")
    if isinstance(metrics, dict) and metrics.get("alternatives"):
        alternatives = []
        for alt in metrics["alternatives"]:
            if isinstance(alt, dict) and "transform" in alt:
                internal = Sim3.from_matrix(np.asarray(alt["transform"], np.float64))
                file = frames.file_transform(internal, source_format, target_format).matrix().tolist()
                alt = {**alt, "file_transform": file}  # a copy: the result's verdict stays as align() made it
            alternatives.append(alt)
        data["metrics"] = {**metrics, "alternatives": alternatives}
    return data


def write_outputs(
    result: AlignmentResult,
    source: GaussianModel,
    target: GaussianModel,
    out_dir: str | os.PathLike,
    outputs: set[str] | frozenset[str] = frozenset({"result", "aligned", "merged"}),
    extra: dict | None = None,
    model_format: str = "ply",
    merge_mode: str = "concat",
) -> dict[str, Path]:
    """Write the requested outputs into out_dir; returns {artifact name: path}. Models are
    written as `model_format` (aligned.ply, aligned.spz, ...); `merge_mode` "dedup" drops
    Gaussians duplicated between the aligned source and the target (gsa.merge)."""
    unknown = set(outputs) - set(OUTPUTS)
    if unknown:
        raise ValueError(f"unknown outputs {sorted(unknown)}; choose from {', '.join(OUTPUTS)}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths: dict[str, Path] = {}
    aligned = None
    if "aligned" in outputs or "merged" in outputs:
        aligned = source.transformed(result.transform)
    ext = EXTENSIONS[model_format]
    merge_report = None
    if "aligned" in outputs:
        paths[f"aligned{ext}"] = write_model(aligned, out / f"aligned{ext}", model_format)
    if "merged" in outputs:
        keep, removed = merge_plan(aligned, target, merge_mode)
        count = sum(len(m) if k is None else int(np.count_nonzero(k)) for m, k in zip((aligned, target), keep))
        merge_report = {"mode": merge_mode, "removed": removed, "gaussians": count}
        if model_format == "ply":
            # Written from its parts, chunk by chunk: a scene-size merged model is never held whole.
            paths[f"merged{ext}"] = write_ply((aligned, target), out / f"merged{ext}", keep=keep)
        else:
            merged = merge_models(aligned, target, keep=keep)
            paths[f"merged{ext}"] = write_model(merged, out / f"merged{ext}", model_format)
    if "renders" in outputs:
        from gsa.render.views import write_alignment_renders  # lazy: loads torch, only renders need it

        renders = write_alignment_renders(source, target, Sim3.identity(), result.transform, out / "renders")
        paths.update({f"renders/{p.name}": p for p in renders.values()})
    if "preview" in outputs:
        from gsa.viewer.preview import write_previews  # the browser viewer's downsampled .splat files

        paths.update(write_previews(source, target, result.transform, out))
    if "result" in outputs:
        data = result_dict(result, source, target)
        if merge_report:
            data["merge"] = merge_report
        if extra:
            data.update(extra)
        data["artifacts"] = sorted(paths)
        paths["result.json"] = write_json(data, out / "result.json")
    return paths
