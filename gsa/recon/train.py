"""Feature-augmented 3DGS training (paper Sec. 3.2, App. E) on the project rasterizer.

L = L_rgb + λ_f·L_f with L_rgb = 0.8·L1 + 0.2·(1 − SSIM) and L_f = L1 on feature maps.
Each iteration first steps colour + geometry on L_rgb, then renders features with the
geometry detached and steps only the features on λ_f·L_f: low-resolution feature maps
must not pull the geometry (Sec. 3.2). Adaptive density control as in 3DGS (clone
small / split large Gaussians with large view-space gradients, prune transparent or
huge ones) plus the GSA fix: prune Gaussians whose feature norm is below 0.1 (App. E),
i.e. Gaussians that only ever explained masked-out background.

Features. `feature_maps` (C, h, w, D) from a 2D extractor are fitted from iteration 0.
With features="canonical" (the weight-free default) there is no 2D extractor: after a
colour-only phase (the first `feature_start` fraction of the iterations) the model's
canonical features (gsa.canonical) are rendered into every training view, masked
(background 0), and from then on lifted back exactly like extractor maps. The lift is
not circular in effect: the maps are masked, so Gaussians outside the object mask are
driven to zero features and pruned, and each Gaussian's feature becomes the multi-view
consensus of what it covers.

Optimiser: Adam with per-parameter state kept as plain tensors, so densification can
index/extend the moments (as 3DGS does) instead of resetting them (gsa.recon.density, with
the density control; the losses are in gsa.recon.losses).

Over 400 lines on purpose: train_gaussians is one training loop (~200 lines) whose steps share
its local state; splitting it would only pass that state around.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field

import numpy as np
import torch
from scipy.spatial import cKDTree

from gsa.canonical import canonical_features
from gsa.model import GaussianModel, sh_coeff_count
from gsa.recon.density import Adam, densify_and_prune
from gsa.recon.losses import psnr, rgb_loss, ssim  # noqa: F401  (ssim: public here before the split)
from gsa.recon.region import object_region
from gsa.render import rasterize, render_model, resolve_backend
from gsa.render.cameras import Cameras
from gsa.sh import rgb_to_sh_dc

Progress = Callable[[str, float], None]


@dataclass
class TrainConfig:
    iterations: int = 1000
    resolution: int = 128  # longest image side used for training (images are downsampled)
    sh_degree: int = 0
    lambda_f: float = 1.0
    ssim_weight: float = 0.2
    # learning rates (3DGS defaults; position lr is relative to the scene extent and decays)
    lr_means: float = 1.6e-4
    lr_means_final: float = 1.6e-6
    lr_sh_dc: float = 2.5e-3
    lr_opacity: float = 0.05
    lr_scales: float = 5e-3
    lr_quats: float = 1e-3
    lr_features: float = 1e-3
    # density control
    init_points: int = 4000  # SfM points are jittered up to this many initial Gaussians
    densify_from: int = 100
    densify_until: int = 700
    densify_every: int = 100
    # Mean view-space positional gradient to densify, in 3DGS's NDC units (dL/d(pixel) * W/2), so
    # the authors' 2e-4 means the same at any training resolution.
    grad_threshold: float = 2e-4
    percent_dense: float = 0.01
    max_gaussians: int = 40_000
    prune_opacity: float = 0.005
    feature_prune: float = 0.1  # App. E: near-zero-feature Gaussians are background
    opacity_reset_every: int = 0  # 0: never (short runs); 3DGS: 3000
    feature_start: float = 0.5  # canonical mode: fraction of iterations before features are lifted
    holdout_every: int = 8  # every k-th registered view is held out for PSNR (3DGS convention)
    background: tuple = (1.0, 1.0, 1.0)
    backend: str = "auto"
    seed: int = 0


PRESETS = {
    # Sized for CPU-only training (30 views in minutes): 128 px, 1000 iterations and faster
    # position/colour learning; fewer iterations cost held-out PSNR, more buy little for their
    # time (docs/benchmarks.md, reconstruction).
    "cpu": TrainConfig(
        iterations=1000,
        resolution=128,
        lr_means=1.6e-3,
        lr_means_final=1.6e-5,
        lr_sh_dc=1e-2,
        lr_features=1e-2,
        densify_from=100,
        densify_until=750,
        densify_every=100,
        max_gaussians=30_000,
    ),
    # The authors' build: 7000 iterations, full resolution, SH degree 3, feature lr 1e-3.
    "gpu": TrainConfig(
        iterations=7000,
        resolution=100_000,
        sh_degree=3,
        densify_from=500,
        densify_until=5000,
        densify_every=100,
        max_gaussians=1_000_000,
        opacity_reset_every=3000,
        init_points=0,
        feature_start=0.3,
    ),
}


@dataclass
class TrainResult:
    model: GaussianModel
    curve: list[dict]  # per logged iteration: iteration, loss, rgb, feat, n
    heldout: list[str]  # names of held-out views
    psnr_heldout: float | None  # mean PSNR (dB) over held-out views, whole image
    psnr_heldout_masked: float | None  # PSNR inside the object masks only
    seconds: float
    config: dict = field(default_factory=dict)
    # the object capture's region (gsa.recon.region) and what lay beyond it: {} when the cameras
    # do not converge or nothing is masked; else centre, camera_distance, radius,
    # sfm_points_dropped, gaussians_pruned
    region: dict = field(default_factory=dict)


# ----------------------------------------------------------------------------- init
def _rgb_to_sh0(rgb: np.ndarray) -> np.ndarray:
    return rgb_to_sh_dc(np.asarray(rgb, np.float64))


def init_from_points(points: np.ndarray, colors: np.ndarray, n_target: int, seed: int = 0) -> dict[str, np.ndarray]:
    """Gaussians at the SfM points (plus jittered copies up to n_target), isotropic with
    the 3-nearest-neighbour distance as scale, opacity 0.1 (3DGS init)."""
    rng = np.random.default_rng(seed)
    pts = np.asarray(points, np.float64)
    cols = np.asarray(colors, np.float64)
    if len(pts) < 4:
        raise ValueError(f"need at least 4 SfM points to initialise, got {len(pts)}")
    d, _ = cKDTree(pts).query(pts, k=4)
    nn = np.maximum(d[:, 1:].mean(1), 1e-7)
    if n_target > len(pts):
        k = n_target - len(pts)
        src = rng.integers(0, len(pts), k)
        pts = np.concatenate([pts, pts[src] + rng.normal(0, 1, (k, 3)) * nn[src, None]])
        cols = np.concatenate([cols, cols[src]])
        d, _ = cKDTree(pts).query(pts, k=4)
        nn = np.maximum(d[:, 1:].mean(1), 1e-7)
    n = len(pts)
    return {
        "means": pts,
        "quats": np.tile([1.0, 0, 0, 0], (n, 1)),
        "log_scales": np.log(nn)[:, None].repeat(3, 1),
        "opacity": np.full(n, math.log(0.1 / 0.9)),
        "colors": cols,
    }


def filter_points_by_masks(
    points: np.ndarray, cameras: Cameras, masks: np.ndarray, min_ratio: float = 0.6
) -> np.ndarray:
    """Bool (P,): points that project inside the object mask in at least min_ratio of the
    views that see them (drops background/table points before initialisation)."""
    h, w = masks.shape[1:]
    inside = np.zeros(len(points))
    seen = np.zeros(len(points))
    for i in range(len(cameras)):
        vm = cameras.viewmats[i]
        pc = points @ vm[:3, :3].T + vm[:3, 3]
        z = np.maximum(pc[:, 2], 1e-9)
        u = np.floor(cameras.fx[i] * pc[:, 0] / z + cameras.cx[i]).astype(np.int64)
        v = np.floor(cameras.fy[i] * pc[:, 1] / z + cameras.cy[i]).astype(np.int64)
        ok = (pc[:, 2] > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        seen += ok
        inside[ok] += masks[i][v[ok], u[ok]]
    return (seen > 0) & (inside >= min_ratio * np.maximum(seen, 1))


def init_selection(points: np.ndarray, cameras: Cameras, masks: np.ndarray):
    """(keep, region, info): the SfM points that initialise Gaussians. Points mostly outside the
    object masks are left out (filter_points_by_masks) and, in an object capture (masks cut
    something and the cameras converge, gsa.recon.region), so is what lies beyond its region:
    far background the masks let through. region: the Region Gaussians are kept within during
    training (None: no limit); info: its TrainResult.region row (sfm_points_dropped counted)."""
    keep = filter_points_by_masks(points, cameras, masks)
    if keep.sum() < 4:
        keep[:] = True  # masks disagree with the SfM points: do not throw the scene away
    region = object_region(cameras) if not masks.all() else None
    if region is None:
        return keep, None, {}
    inside = region.contains(points)
    if (keep & inside).sum() < 4:
        return keep, None, {}
    info = region.as_dict() | {"sfm_points_dropped": int((keep & ~inside).sum())}
    return keep & inside, region, info


def resize_images(images: np.ndarray, width: int, height: int, interp=None) -> np.ndarray:
    import cv2

    if images.shape[2] == width and images.shape[1] == height:
        return images
    interp = cv2.INTER_AREA if interp is None else interp
    return np.stack([cv2.resize(im, (width, height), interpolation=interp) for im in images])


# ----------------------------------------------------------------------------- training
def train_gaussians(
    images: np.ndarray,
    masks: np.ndarray,
    cameras: Cameras,
    points: np.ndarray,
    point_colors: np.ndarray,
    config: TrainConfig | str = "cpu",
    *,
    names: list[str] | None = None,
    features: str | np.ndarray = "canonical",
    progress: Progress | None = None,
    log_every: int = 10,
) -> TrainResult:
    """Train a feature-augmented 3DGS model.

    images: (C, H, W, 3) float in [0, 1] (unmasked; masks are applied here, Alg. 1);
    masks: (C, H, W) bool; cameras: C registered cameras at (W, H); points (P, 3) and
    point_colors (P, 3) in [0, 1]: the SfM cloud. features: "canonical", "none", or an
    array (C, h, w, D) of 2D feature maps from an extractor (masked here, upsampled to the
    training resolution).
    """
    cfg = PRESETS[config] if isinstance(config, str) else config
    t_start = time.perf_counter()
    report = progress or (lambda stage, frac: None)
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    c_all, h0, w0 = images.shape[:3]
    names = names or [f"view_{i}" for i in range(c_all)]
    s = min(1.0, cfg.resolution / max(h0, w0))
    w, h = max(8, int(round(w0 * s))), max(8, int(round(h0 * s)))
    cams = cameras.resized(w, h)
    import cv2

    imgs = resize_images(images.astype(np.float32), w, h)
    msk = resize_images(masks.astype(np.float32), w, h, cv2.INTER_LINEAR) > 0.5
    bg = np.asarray(cfg.background, np.float32)
    imgs = np.where(msk[..., None], imgs, bg)  # masked images (Alg. 1)
    held = [
        i for i in range(c_all) if cfg.holdout_every and c_all >= 2 * cfg.holdout_every and i % cfg.holdout_every == 0
    ]
    train_ids = [i for i in range(c_all) if i not in held]
    # On the CUDA backend every tensor of the loop lives on the GPU: moving ~60 floats per
    # Gaussian across the bus twice an iteration would cost more than the render.
    device = torch.device("cuda" if resolve_backend(cfg.backend) == "cuda" else "cpu")
    target = torch.from_numpy(imgs).to(device)

    keep, region, region_info = init_selection(points, cameras, masks)
    init = init_from_points(points[keep], point_colors[keep], cfg.init_points, cfg.seed)
    centres = cams.centers()
    extent = 1.1 * float(np.linalg.norm(centres - centres.mean(0), axis=1).max())
    k_sh = sh_coeff_count(cfg.sh_degree)
    sh0 = np.zeros((len(init["means"]), k_sh, 3))
    sh0[:, 0] = _rgb_to_sh0(init["colors"])
    tt = lambda a: torch.tensor(np.asarray(a), dtype=torch.float32, device=device, requires_grad=True)  # noqa: E731
    P = {
        "means": tt(init["means"]),
        "quats": tt(init["quats"]),
        "log_scales": tt(init["log_scales"]),
        "opacity": tt(init["opacity"]),
        "sh_dc": tt(sh0[:, :1]),
        "sh_rest": tt(sh0[:, 1:]),
        "features": None,
    }
    feat_dim = 0
    feat_maps = None
    if isinstance(features, np.ndarray):
        feat_maps = _prepare_feature_maps(features, msk, w, h).to(device)
        feat_dim = feat_maps.shape[-1]
    elif features not in ("canonical", "none"):
        raise ValueError(f"features must be 'canonical', 'none' or an array of maps, got {features!r}")
    feature_from = (
        0 if feat_maps is not None else (int(cfg.feature_start * cfg.iterations) if features == "canonical" else None)
    )
    if feat_dim:
        P["features"] = tt(np.full((len(init["means"]), feat_dim), 0.5))
    lrs = {
        "means": cfg.lr_means * extent,
        "quats": cfg.lr_quats,
        "log_scales": cfg.lr_scales,
        "opacity": cfg.lr_opacity,
        "sh_dc": cfg.lr_sh_dc,
        "sh_rest": cfg.lr_sh_dc / 20,
        "features": cfg.lr_features,
    }
    params = {k: v for k, v in P.items() if v is not None}
    opt = Adam(params, {k: lrs[k] for k in params})
    geo_names = ["means", "quats", "log_scales", "opacity", "sh_dc", "sh_rest"]
    grad_acc = torch.zeros(len(P["means"]), device=device)
    grad_cnt = torch.zeros(len(P["means"]), device=device)
    curve = []
    ball = None if region is None else (torch.tensor(region.centre, dtype=torch.float32, device=device), region.radius)
    pruned_outside = 0
    bg_t = tuple(float(x) for x in bg)

    def sh_tensor():
        return torch.cat([opt.params["sh_dc"], opt.params["sh_rest"]], 1)

    for it in range(cfg.iterations):
        frac = it / max(cfg.iterations - 1, 1)
        opt.lrs["means"] = lrs["means"] * (cfg.lr_means_final / cfg.lr_means) ** frac
        if feature_from is not None and it == feature_from and feat_maps is None:
            feat_maps = _canonical_feature_maps(opt.params, sh_tensor, cams, msk, cfg.backend).to(device)
            feat_dim = feat_maps.shape[-1]
            opt.params["features"] = tt(np.full((len(opt.params["means"]), feat_dim), 0.5))
            opt.m["features"] = torch.zeros_like(opt.params["features"])
            opt.v["features"] = torch.zeros_like(opt.params["features"])
            opt.t["features"] = 0
            opt.lrs["features"] = lrs["features"]
        i = int(train_ids[rng.integers(len(train_ids))])
        p = opt.params
        # 1) colour + geometry on L_rgb
        out = rasterize(
            p["means"],
            p["quats"],
            p["log_scales"],
            p["opacity"],
            sh_tensor(),
            None,
            cams[i],
            background=bg_t,
            depth=False,
            backend=cfg.backend,
        )
        l_rgb = rgb_loss(out.colors[0], target[i], cfg.ssim_weight)
        l_rgb.backward()
        with torch.no_grad():
            # View-space positional gradient, the 3DGS densify signal: |dL/dx_world| · z / f is
            # per pixel; × W/2 converts it to the NDC units the 3DGS threshold is stated in.
            g = p["means"].grad
            if g is not None:
                vm = torch.as_tensor(cams.viewmats[i], dtype=torch.float32, device=device)
                z = (p["means"] @ vm[:3, :3].T + vm[:3, 3])[:, 2].clamp_min(1e-6)
                gn = g.norm(dim=1) * z / float(cams.fx[i]) * (cams.width / 2)
                vis = gn > 0
                grad_acc += gn * vis
                grad_cnt += vis
        opt.step(geo_names)
        # 2) features with geometry fixed, on λ_f·L_f
        l_f = torch.zeros(())
        if feat_maps is not None and "features" in opt.params:
            out_f = rasterize(
                p["means"].detach(),
                p["quats"].detach(),
                p["log_scales"].detach(),
                p["opacity"].detach(),
                None,
                opt.params["features"],
                cams[i],
                depth=False,
                backend=cfg.backend,
            )
            l_f = (out_f.features[0] - feat_maps[i]).abs().mean()
            (cfg.lambda_f * l_f).backward()
            opt.step(["features"])
        if it % log_every == 0 or it == cfg.iterations - 1:
            curve.append(
                {
                    "iteration": it,
                    "loss": l_rgb.item() + cfg.lambda_f * l_f.item(),
                    "rgb": l_rgb.item(),
                    "feat": l_f.item(),
                    "n": int(len(opt.params["means"])),
                }
            )
            report("train", it / cfg.iterations)
        # density control
        if cfg.densify_from <= it < cfg.densify_until and it > 0 and it % cfg.densify_every == 0:
            avg = grad_acc / grad_cnt.clamp_min(1)
            pruned_outside += densify_and_prune(opt, avg, cfg, extent, rng, densify=True, region=ball)
            grad_acc = torch.zeros(len(opt.params["means"]), device=device)
            grad_cnt = torch.zeros(len(opt.params["means"]), device=device)
        if cfg.opacity_reset_every and it > 0 and it % cfg.opacity_reset_every == 0 and it < cfg.densify_until:
            with torch.no_grad():
                opt.params["opacity"].clamp_(max=math.log(0.01 / 0.99))
    # final clean-up: transparent and near-zero-feature Gaussians
    pruned_outside += densify_and_prune(opt, None, cfg, extent, rng, densify=False, region=ball)
    if region_info:
        region_info["gaussians_pruned"] = pruned_outside
    model = _to_model(opt.params, sh_tensor())
    if model.features is not None:
        # Provenance travels in the PLY: `gsa align --features auto` recomputes canonical ones.
        model.metadata["features"] = "lifted:canonical" if isinstance(features, str) else "lifted:maps"
    # held-out evaluation at the training resolution
    ps, psm = [], []
    for i in held:
        r = render_model(model, cams[i], features=False, background=bg_t, depth=False, backend=cfg.backend)
        pred = r.colors[0].numpy()
        ps.append(psnr(pred, imgs[i]))
        psm.append(psnr(pred, imgs[i], msk[i]))
    return TrainResult(
        model,
        curve,
        [names[i] for i in held],
        float(np.mean(ps)) if ps else None,
        float(np.mean(psm)) if psm else None,
        time.perf_counter() - t_start,
        asdict(cfg),
        region_info,
    )


def _prepare_feature_maps(maps: np.ndarray, masks: np.ndarray, w: int, h: int) -> torch.Tensor:
    """(C,h',w',D) extractor maps -> (C,H,W,D) tensor, bilinearly upsampled, background 0 (Alg. 1)."""
    import cv2

    maps = np.asarray(maps, np.float32)
    if maps.shape[0] != masks.shape[0]:
        raise ValueError(f"{maps.shape[0]} feature maps for {masks.shape[0]} images")
    up = np.stack([cv2.resize(m, (w, h), interpolation=cv2.INTER_LINEAR).reshape(h, w, -1) for m in maps])
    return torch.from_numpy(np.where(masks[..., None], up, 0.0).astype(np.float32))


@torch.no_grad()
def _canonical_feature_maps(params, sh_tensor, cams: Cameras, masks: np.ndarray, backend: str) -> torch.Tensor:
    """Render the current geometry's canonical features into every view, masked (background 0)."""
    model = _to_model(params, sh_tensor())
    f = canonical_features(model)
    maps = []
    for i in range(len(cams)):
        out = rasterize(
            model.means,
            model.quats,
            model.log_scales,
            model.opacity_logits,
            None,
            f,
            cams[i],
            depth=False,
            backend=backend,
        )
        maps.append(out.features[0].cpu().numpy())
    maps = np.stack(maps)
    return torch.from_numpy(np.where(masks[..., None], maps, 0.0).astype(np.float32))


def _to_model(p, sh) -> GaussianModel:
    q = p["quats"].detach().cpu().numpy()
    q = q / np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-12)
    feats = p.get("features")
    return GaussianModel(
        p["means"].detach().cpu().numpy(),
        q,
        p["log_scales"].detach().cpu().numpy(),
        p["opacity"].detach().cpu().numpy(),
        sh.detach().cpu().numpy(),
        None if feats is None else feats.detach().cpu().numpy(),
    )
