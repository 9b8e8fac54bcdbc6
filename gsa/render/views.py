"""PNG renders people look at: before/after overlays, side-by-side, feature maps,
and synchronized views of several models from shared cameras (paper App. B).

Images are written with OpenCV (BGR on disk); everything here is no-grad rendering.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import torch

from gsa.model import GaussianModel
from gsa.render import render_model
from gsa.render.cameras import Cameras, cameras_around
from gsa.render.output import RenderOutput
from gsa.sim3 import Sim3

WHITE = (1.0, 1.0, 1.0)


def write_png(path: str | Path, rgb: np.ndarray) -> Path:
    """Write an (H, W, 3) RGB float image in [0, 1] (or uint8) as PNG."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    img = np.asarray(rgb)
    if img.dtype != np.uint8:
        img = np.nan_to_num(img if img.dtype.kind == "f" else img.astype(np.float32), nan=0.0, posinf=1.0, neginf=0.0)
        img = (np.clip(img, 0.0, 1.0, out=img) * 255.0 + 0.5).astype(np.uint8)
    if not cv2.imwrite(str(path), np.ascontiguousarray(img[..., ::-1])):
        raise OSError(f"could not write {path}")
    return path


def features_to_rgb(features: np.ndarray, alpha: np.ndarray, background=WHITE) -> np.ndarray:
    """(H, W, D) feature map -> (H, W, 3) RGB. D == 3 is shown as is (GSA features lie in
    [0, 1]); other D are projected on their first 3 principal components and stretched.
    Pixels with no coverage get `background`."""
    f = np.asarray(features, np.float64)
    a = np.asarray(alpha, np.float64).reshape(f.shape[:2] + (1,))
    h, w, d = f.shape
    fg = a[..., 0] > 0.05
    # un-premultiply so faint edges do not darken the colours
    f = f / np.maximum(a, 1e-6) * fg[..., None]
    if d == 3:
        rgb = f
    else:
        x = f[fg]
        if len(x) < 2:
            rgb = np.zeros((h, w, 3))
        else:
            mu = x.mean(0)
            _, _, vt = np.linalg.svd(x - mu, full_matrices=False)
            basis = np.zeros((3, d))
            basis[: min(3, vt.shape[0])] = vt[:3]
            y = (f - mu) @ basis.T
            lo, hi = np.percentile(y[fg], 2, axis=0), np.percentile(y[fg], 98, axis=0)
            rgb = (y - lo) / np.maximum(hi - lo, 1e-9)
    rgb = np.clip(rgb, 0, 1)
    return rgb * a + np.asarray(background) * (1 - a)


# Views rendered per renderer call, at most this many views x Gaussians: the renderer holds
# every Gaussian's projection and colour in every view of a call, so the 3 views of a 3M-Gaussian
# source took 1.7 GB above the job's other peaks; each view composites alone (the same pixels).
VIEW_GAUSSIANS_PER_CALL = 1_200_000


def render_views(model: GaussianModel, cams: Cameras, **kw) -> RenderOutput:
    """render_model over `cams`, a few views a call for a large model (VIEW_GAUSSIANS_PER_CALL);
    no depth unless asked (depth=True): the images people look at never show it, and compositing
    it and dividing it out cost a small job's renders a third of their time."""
    kw.setdefault("depth", False)
    step = max(1, VIEW_GAUSSIANS_PER_CALL // max(len(model), 1))
    if step >= len(cams):
        return render_model(model, cams, **kw)
    parts = [render_model(model, cams[i : i + step], **kw) for i in range(0, len(cams), step)]

    def cat(name):
        got = [getattr(p, name) for p in parts]
        return None if got[0] is None else torch.cat(got)

    return RenderOutput(cat("colors"), cat("features"), cat("alpha"), cat("depth"))


def _cameras_for(points: list[np.ndarray], n: int, size: int, seed: int) -> Cameras:
    pts = np.concatenate([p[:: max(1, len(p) // 20000)] for p in points])
    return cameras_around(pts, n, size, seed=seed)


def _hstack(images: list[np.ndarray], gap: int = 4) -> np.ndarray:
    h = images[0].shape[0]
    sep = np.ones((h, gap, 3), images[0].dtype)
    parts = []
    for i, im in enumerate(images):
        if i:
            parts.append(sep)
        parts.append(im)
    return np.concatenate(parts, axis=1)


def _vstack(rows: list[np.ndarray], gap: int = 4) -> np.ndarray:
    w = max(r.shape[1] for r in rows)
    rows = [np.pad(r, ((0, 0), (0, w - r.shape[1]), (0, 0)), constant_values=1.0) for r in rows]
    sep = np.ones((gap, w, 3))
    out = []
    for i, r in enumerate(rows):
        if i:
            out.append(sep)
        out.append(r)
    return np.concatenate(out, axis=0)


def _overlay(src: np.ndarray, tgt: np.ndarray, src_alpha: np.ndarray, tgt_alpha: np.ndarray) -> np.ndarray:
    """Source tinted orange over target tinted blue: misalignment shows as doubled, two-tone edges.
    In the renders' own precision (float32): float64 temporaries made this a fifth of a small
    job's outputs."""
    dt = np.result_type(src, tgt, np.float32)
    third = np.full(3, 1 / 3, dt)  # a product, not .mean(-1): the mean over 3 channels is 20x slower
    tint_s = (src @ third)[..., None] * np.array([0.65, 0.3575, 0.065], dt) + dt.type(0.35)
    tint_t = (tgt @ third)[..., None] * np.array([0.065, 0.2925, 0.65], dt) + dt.type(0.35)
    a_s = src_alpha[..., None].astype(dt) * dt.type(0.6)
    a_t = tgt_alpha[..., None].astype(dt) * dt.type(0.6)
    out = 1 + a_t * (tint_t - 1)  # white, then the target over it, then the source
    return out + a_s * (tint_s - out)


def write_alignment_renders(
    source: GaussianModel,
    target: GaussianModel,
    transform_before: Sim3,
    transform_after: Sim3,
    out_dir: str | Path,
    n_novel: int = 3,
    size: int = 256,
    cameras: Cameras | None = None,
    backend: str = "auto",
) -> dict[str, Path]:
    """Before/after renders of source (mapped by each transform) against the target.

    Views: `cameras` (e.g. the fine stage's, re-rendered at `size`) followed by
    `n_novel` orbit cameras framing all three. Per view k writes
      before_k.png / after_k.png: [source | target | overlay] colour,
      features_k.png (when both models have features): rows before/after, [source | target] feature maps.
    Returns {name: path}.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    pts = [target.means, transform_before.apply(source.means), transform_after.apply(source.means)]
    cams = []
    if cameras is not None and len(cameras):
        cams.append(cameras.resized(size, max(1, round(cameras.height * size / cameras.width))))
    if n_novel > 0:
        novel = _cameras_for(pts, n_novel, size, seed=12345)
        if cams and (novel.width, novel.height) != (cams[0].width, cams[0].height):
            novel = novel.resized(cams[0].width, cams[0].height)
        cams.append(novel)
    if not cams:
        raise ValueError("no views to render: pass cameras or n_novel > 0")
    cams = Cameras.concat(cams)
    with_features = (
        source.features is not None and target.features is not None and source.feature_dim == target.feature_dim
    )
    tgt = render_views(target, cams, features=with_features, background=WHITE, backend=backend)
    renders = {}
    for phase, transform in (("before", transform_before), ("after", transform_after)):
        renders[phase] = render_views(
            source, cams, features=with_features, background=WHITE, backend=backend, sim3=transform
        )
    paths: dict[str, Path] = {}
    ta = tgt.alpha[..., 0].numpy()
    for k in range(len(cams)):
        tc = tgt.colors[k].numpy()
        feature_rows = []
        for phase in ("before", "after"):
            r = renders[phase]
            sc, sa = r.colors[k].numpy(), r.alpha[k, ..., 0].numpy()
            img = _hstack([sc, tc, _overlay(sc, tc, sa, ta[k])])
            paths[f"{phase}_{k}"] = write_png(out / f"{phase}_{k}.png", img)
            if with_features:
                feature_rows.append(
                    _hstack(
                        [features_to_rgb(r.features[k].numpy(), sa), features_to_rgb(tgt.features[k].numpy(), ta[k])]
                    )
                )
        if feature_rows:
            paths[f"features_{k}"] = write_png(out / f"features_{k}.png", _vstack(feature_rows))
    return paths


def render_model_views(
    model: GaussianModel,
    out_dir: str | Path,
    views: int = 8,
    features: bool = False,
    size: int = 256,
    backend: str = "auto",
    seed: int = 0,
) -> dict[str, Path]:
    """Orbit renders of one model: view_k.png (colour), view_k_features.png (if `features`),
    and contact_sheet.png with all of them."""
    if features and model.features is None:
        raise ValueError("the model has no features to render")
    out = Path(out_dir)
    cams = cameras_around(model.means, views, size, seed=seed)
    r = render_views(model, cams, features=features, background=WHITE, backend=backend)
    paths: dict[str, Path] = {}
    tiles = []
    for k in range(len(cams)):
        col = r.colors[k].numpy()
        paths[f"view_{k}"] = write_png(out / f"view_{k}.png", col)
        tile = [col]
        if features:
            fimg = features_to_rgb(r.features[k].numpy(), r.alpha[k, ..., 0].numpy())
            paths[f"view_{k}_features"] = write_png(out / f"view_{k}_features.png", fimg)
            tile.append(fimg)
        tiles.append(_vstack(tile))
    per_row = min(4, len(tiles))
    rows = [_hstack(tiles[i : i + per_row]) for i in range(0, len(tiles), per_row)]
    paths["contact_sheet"] = write_png(out / "contact_sheet.png", _vstack(rows))
    return paths


def write_synchronized_renders(
    models: list[GaussianModel],
    out_dir: str | Path,
    transforms: list[Sim3] | None = None,
    views: int = 4,
    size: int = 256,
    features: bool = False,
    backend: str = "auto",
    seed: int = 0,
) -> dict[str, Path]:
    """Several (aligned) models rendered from the same shared cameras (paper App. B).

    transforms[i] maps models[i] into the shared frame (identity if omitted). Writes
    synchronized.png (one row per model, one column per view) and, with `features`,
    synchronized_features.png. Returns {name: path}.
    """
    if not models:
        raise ValueError("need at least one model")
    transforms = transforms or [Sim3.identity()] * len(models)
    if len(transforms) != len(models):
        raise ValueError("need one transform per model")
    cams = _cameras_for([t.apply(m.means) for m, t in zip(models, transforms)], views, size, seed)
    use_feat = features and all(m.features is not None for m in models) and len({m.feature_dim for m in models}) == 1
    rows, frows = [], []
    for m, t in zip(models, transforms):
        r = render_views(m, cams, features=use_feat, background=WHITE, backend=backend, sim3=t)
        rows.append(_hstack([r.colors[k].numpy() for k in range(len(cams))]))
        if use_feat:
            frows.append(
                _hstack([features_to_rgb(r.features[k].numpy(), r.alpha[k, ..., 0].numpy()) for k in range(len(cams))])
            )
    out = Path(out_dir)
    paths = {"synchronized": write_png(out / "synchronized.png", _vstack(rows))}
    if frows:
        paths["synchronized_features"] = write_png(out / "synchronized_features.png", _vstack(frows))
    return paths
