"""Compact previews of an alignment for the browser viewer: `.splat` files.

The `.splat` layout (32 bytes per Gaussian, little endian, no header) is the web
viewers' common denominator (antimatter15's splat viewer; Spark reads it):
position float32×3, scale float32×3 (linear, not log), colour RGBA uint8 (DC colour,
alpha = opacity), rotation uint8×4 (w, x, y, z mapped from [-1, 1] to [0, 255]).
View-dependent colour (SH bands 1–3) is dropped: a preview is for judging the fit.

Large models are cut to `max_gaussians` by a seeded uniform sample with each kept
Gaussian enlarged by (N / cap)^(1/3) (at most 2×), so the surface stays covered
where a pick by size or opacity would drop all the fine detail.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from gsa.io.atomic import mkstemp_for
from gsa.model import GaussianModel

DEFAULT_MAX_GAUSSIANS = 300_000
SPLAT_DTYPE = np.dtype([("position", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rotation", "u1", 4)])
# Public artifact names (relative to an output folder), in the order the viewer wants them.
PREVIEW_NAMES = {"source": "preview/source.splat", "target": "preview/target.splat", "aligned": "preview/aligned.splat"}


def downsample(model: GaussianModel, max_gaussians: int = DEFAULT_MAX_GAUSSIANS, seed: int = 0) -> GaussianModel:
    """At most `max_gaussians` of the model's visible Gaussians (alpha ≥ 1/255)."""
    if max_gaussians < 1:
        raise ValueError(f"max_gaussians must be >= 1, got {max_gaussians}")
    visible = model.opacities >= 1.0 / 255.0
    if not visible.all():
        model = model.subset(visible)
    n = len(model)
    if n <= max_gaussians:
        return model
    keep = np.sort(np.random.default_rng(seed).choice(n, max_gaussians, replace=False))
    out = model.subset(keep)
    grow = min((n / max_gaussians) ** (1.0 / 3.0), 2.0)
    out.log_scales = (out.log_scales + np.float32(np.log(grow))).astype(np.float32)
    return out


def splat_bytes(model: GaussianModel) -> bytes:
    """The model as `.splat` records."""
    rec = np.zeros(len(model), SPLAT_DTYPE)
    rec["position"] = model.means
    rec["scale"] = model.scales
    rgba = np.empty((len(model), 4))
    rgba[:, :3] = model.base_colors
    rgba[:, 3] = model.opacities
    rec["rgba"] = np.clip(np.rint(rgba * 255.0), 0, 255)
    q = model.quats.astype(np.float64)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    rec["rotation"] = np.clip(np.rint(q * 128.0 + 128.0), 0, 255)
    return rec.tobytes()


def write_splat(model: GaussianModel, path: str | os.PathLike) -> Path:
    """Atomic write (temp file + rename) of the model as a `.splat` file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = mkstemp_for(path)  # 0666 & ~umask, not mkstemp's 0600
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(splat_bytes(model))
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def read_splat(path: str | os.PathLike) -> np.ndarray:
    """A `.splat` file's records (structured array with SPLAT_DTYPE fields)."""
    data = Path(path).read_bytes()
    if len(data) % SPLAT_DTYPE.itemsize:
        raise ValueError(f"{path}: {len(data)} bytes is not a whole number of 32-byte splat records")
    return np.frombuffer(data, SPLAT_DTYPE)


def write_previews(
    source: GaussianModel,
    target: GaussianModel,
    transform,
    out_dir: str | os.PathLike,
    max_gaussians: int = DEFAULT_MAX_GAUSSIANS,
) -> dict[str, Path]:
    """source (its own frame), target and the aligned source (target frame) as `.splat`
    files under out_dir/preview/; returns {artifact name: path}. The aligned preview is
    the same sample as the source's, moved, so the two views show the same Gaussians."""
    out = Path(out_dir)
    small_source = downsample(source, max_gaussians)
    models = {
        "source": small_source,
        "target": downsample(target, max_gaussians),
        "aligned": small_source.transformed(transform),
    }
    return {PREVIEW_NAMES[k]: write_splat(m, out / PREVIEW_NAMES[k]) for k, m in models.items()}
