"""Lift 2D feature maps onto an existing 3DGS model, and prune background Gaussians.

Lifting is the second half of each GSA training step on its own: geometry, opacities and
colours stay fixed, only per-Gaussian features (N,3) are optimised so that the rendered
feature maps match the extracted ones (L1, Adam). Rendering is linear in the features, so
we start from the blend-weighted back-projection  f_i = Σ_p w_ip t_p / Σ_p w_ip  (one
renderer backward pass gives both sums) and let Adam remove the blur that averaging leaves.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field

import numpy as np
import torch
from scipy.spatial import cKDTree

from gsa.features.extractors import FeatureExtractor
from gsa.model import GaussianModel, ModelError
from gsa.render import cameras_around, rasterize, render_model
from gsa.render.steps import between_steps

Progress = Callable[[str, float], None]

# A Gaussian counts as seen when its blend weights over all lifting views add up to at
# least this many pixels; below it the optimisation has (almost) nothing to go on.
MIN_VISIBLE_WEIGHT = 0.5


@dataclass
class LiftReport:
    extractor: str
    gaussians: int
    views: int
    image_size: int
    iterations: int
    visible: int  # Gaussians with blend weight >= MIN_VISIBLE_WEIGHT px over all views
    filled_from_neighbours: int  # the rest: they take their nearest visible neighbour's feature
    initial_loss: float  # mean L1 over all views after the back-projection initialisation
    final_loss: float  # mean L1 over all views after optimisation
    loss_curve: list[float] = field(default_factory=list)  # per iteration, on that iteration's view batch
    render_seconds: float = 0.0
    extract_seconds: float = 0.0
    optimise_seconds: float = 0.0
    seconds_per_iteration: float = 0.0
    total_seconds: float = 0.0

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class LiftResult:
    """What lifting produced, for callers that need more than the model."""

    model: GaussianModel
    report: LiftReport
    targets: np.ndarray  # (C,H,W,3) extracted feature maps
    masks: np.ndarray  # (C,H,W) rendered alpha > 0.5
    cameras: object
    visibility: np.ndarray  # (N,) summed blend weight (pixels) over all views


def _render_features(model: GaussianModel, feats: torch.Tensor, cameras, backend: str) -> torch.Tensor:
    """(C,H,W,D) features rendered with fixed geometry; gradients flow to `feats` only."""
    out = rasterize(
        model.means,
        model.quats,
        model.log_scales,
        model.opacity_logits,
        None,
        feats,
        cameras,
        depth=False,
        backend=backend,
        feature_background=np.zeros(feats.shape[1]),
    )
    return out.features


def back_project(
    model: GaussianModel,
    maps: torch.Tensor,
    cameras,
    batch_views: int = 4,
    backend: str = "auto",
    tick: Callable[[float], None] | None = None,
    channels_per_pass: int | None = None,
):
    """(C,H,W,k) per-pixel maps -> (N, k+1) float64: per Gaussian, Σ_p w_ip [m_p, 1] over every
    pixel p it is blended into with weight w_ip; the last column is its visibility (pixels).
    It is d/df of Σ_p <render(f)_p, [m_p, 1]>, so one backward pass of the renderer per batch.
    `channels_per_pass` of the k+1 columns a pass (None: all): the renderer materialises every
    channel per view and Gaussian, and each channel's gradient is computed alone (the same
    bits), so a large model is lifted in column groups at a fraction of the memory.
    `tick(fraction of the views done)` after each pass, and within it between the renderer's
    steps (gsa.render.steps: a pass of a 3M-Gaussian model takes seconds), where a cancelled job
    stops."""
    n, k = len(model), maps.shape[-1]
    acc = torch.zeros(n, k + 1, dtype=torch.float64)
    group = max(1, channels_per_pass or k + 1)
    done = lambda sl, cols: (sl.start + (sl.stop - sl.start) * cols / (k + 1)) / len(maps)  # noqa: E731
    for sl in _chunks(len(maps), batch_views):
        weights = torch.cat([maps[sl], torch.ones_like(maps[sl][..., :1])], -1)
        for cols in _chunks(k + 1, group):
            with between_steps(None if tick is None else functools.partial(tick, done(sl, cols.start))):
                probe = torch.zeros(n, cols.stop - cols.start, requires_grad=True)
                rendered = _render_features(model, probe, cameras[sl], backend)
                (grad,) = torch.autograd.grad(rendered, probe, grad_outputs=weights[..., cols].contiguous())
            del rendered, probe  # the graph's saved projections go before the next pass builds its own
            acc[:, cols] += grad
            del grad
            if tick is not None:
                tick(done(sl, cols.stop))
    return acc


def _chunks(n: int, size: int):
    for i in range(0, n, size):
        yield slice(i, min(n, i + size))


def lift_features_full(
    model: GaussianModel,
    extractor: FeatureExtractor,
    *,
    views: int = 24,
    image_size: int = 128,
    iterations: int = 150,
    lr: float = 0.02,
    batch_views: int = 4,
    seed: int = 0,
    backend: str = "auto",
    background=(1.0, 1.0, 1.0),
    progress: Progress | None = None,
) -> LiftResult:
    """Lift `extractor`'s 2D features onto `model` (see module docstring).

    Cameras: `views` orbit cameras framing the model (gsa.render.cameras_around), square
    `image_size` images. Each Adam iteration renders `batch_views` of them (cycling through a
    shuffled order). Returns the model with features (N,3) clipped to [0,1], and the report.
    """
    if len(model) == 0:
        raise ModelError("cannot lift features onto an empty model")
    if views < 1 or image_size < 8 or iterations < 0 or batch_views < 1:
        raise ValueError("need views >= 1, image_size >= 8, iterations >= 0, batch_views >= 1")
    report_progress = progress or (lambda stage, frac: None)
    t0 = time.perf_counter()
    cams = cameras_around(model.means, views, width=image_size, seed=seed)
    images, alphas = [], []
    for sl in _chunks(views, 8):
        out = render_model(model, cams[sl], features=False, depth=False, background=background, backend=backend)
        images.append(out.colors.numpy())
        alphas.append(out.alpha[..., 0].numpy())
    images = np.clip(np.concatenate(images), 0.0, 1.0)
    masks = np.concatenate(alphas) > 0.5
    t1 = time.perf_counter()
    report_progress("extract", 0.0)
    targets = np.asarray(extractor.extract_views(images, masks, model=model, cameras=cams), np.float32)
    if targets.shape != images.shape:
        raise ValueError(f"extractor {extractor.name} returned {targets.shape}, expected {images.shape}")
    t2 = time.perf_counter()
    target_t = torch.as_tensor(targets)

    # Back-projection init and visibility.
    n = len(model)
    acc = back_project(model, target_t, cams, batch_views, backend)
    visibility = acc[:, 3].numpy()
    seen = visibility >= MIN_VISIBLE_WEIGHT
    init = torch.where(
        acc[:, 3:] > 1e-12, acc[:, :3] / acc[:, 3:].clamp_min(1e-12), torch.zeros(n, 3, dtype=torch.float64)
    )
    feats = init.float().clone().requires_grad_(True)
    report_progress("lift", 0.0)

    def full_loss() -> float:
        with torch.no_grad():
            total = 0.0
            for sl in _chunks(views, batch_views):
                total += (_render_features(model, feats, cams[sl], backend) - target_t[sl]).abs().sum().item()
            return total / target_t.numel()

    initial = full_loss()
    opt = torch.optim.Adam([feats], lr=lr)
    rng = np.random.default_rng(seed)
    order: list[int] = []
    curve = []
    t3 = time.perf_counter()
    for it in range(iterations):
        if len(order) < batch_views:
            order += list(rng.permutation(views))
        idx, order = order[:batch_views], order[batch_views:]
        opt.zero_grad(set_to_none=True)
        loss = (_render_features(model, feats, cams[idx], backend) - target_t[idx]).abs().mean()
        loss.backward()
        opt.step()
        with torch.no_grad():
            feats.clamp_(0.0, 1.0)  # every extractor's encoding lives in [0,1]
        curve.append(float(loss.item()))
        report_progress("lift", (it + 1) / max(iterations, 1))
    t4 = time.perf_counter()
    final = full_loss() if iterations else initial

    lifted = feats.detach().numpy().astype(np.float32)
    filled = int((~seen).sum())
    if filled and seen.any():
        # Unseen (interior) Gaussians got no gradient: give them their nearest seen neighbour's
        # feature rather than an arbitrary one, so the coarse stage can still match them.
        _, nn_idx = cKDTree(model.means[seen]).query(model.means[~seen], k=1)
        lifted[~seen] = lifted[seen][nn_idx]
    report = LiftReport(
        extractor=extractor.name,
        gaussians=n,
        views=views,
        image_size=image_size,
        iterations=iterations,
        visible=int(seen.sum()),
        filled_from_neighbours=filled,
        initial_loss=initial,
        final_loss=final,
        loss_curve=curve,
        render_seconds=t1 - t0,
        extract_seconds=t2 - t1,
        optimise_seconds=t4 - t3,
        seconds_per_iteration=(t4 - t3) / max(iterations, 1),
        total_seconds=time.perf_counter() - t0,
    )
    out_model = model.with_features(lifted)
    out_model.metadata["features"] = f"lifted:{extractor.name}"
    return LiftResult(out_model, report, targets, masks, cams, visibility)


def lift_features(
    model: GaussianModel,
    extractor: FeatureExtractor,
    views: int = 24,
    image_size: int = 128,
    iterations: int = 150,
    lr: float = 0.02,
    progress: Progress | None = None,
    **kwargs,
) -> tuple[GaussianModel, LiftReport]:
    """(model with features (N,3) in [0,1], LiftReport). Keyword extras: batch_views, seed,
    backend, background (see lift_features_full)."""
    res = lift_features_full(
        model, extractor, views=views, image_size=image_size, iterations=iterations, lr=lr, progress=progress, **kwargs
    )
    return res.model, res.report


def prune_background(model: GaussianModel, threshold: float = 0.1) -> tuple[GaussianModel, int]:
    """Drop Gaussians whose feature magnitude ||f|| is below `threshold` (paper App. E:
    background-coloured Gaussians learn the background's zero feature). Returns
    (pruned model, number removed)."""
    if model.features is None:
        raise ModelError("prune_background needs a model with features (lift them first)")
    if not threshold >= 0:
        raise ValueError(f"threshold must be >= 0, got {threshold}")
    keep = np.linalg.norm(model.features.astype(np.float64), axis=1) >= threshold
    if not keep.any():
        raise ModelError(f"every Gaussian has feature magnitude below {threshold}; nothing would remain")
    removed = int((~keep).sum())
    return (model if removed == 0 else model.subset(keep)), removed
