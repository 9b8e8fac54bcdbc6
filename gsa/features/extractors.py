"""2D feature extractors: image (H,W,3) in [0,1] + mask (H,W) bool -> (H,W,3) float32 in [0,1],
background 0. Backends by name: `spheremap`, `dinov2`, `canonical` (see `make_extractor`).

All three produce GSA's 3-channel encoding, so lifting, pruning (|f| < 0.1 = background)
and the coarse stage's feature threshold treat them alike.
"""

from __future__ import annotations

from abc import ABC, abstractmethod

import numpy as np
import torch
import torch.nn.functional as F

from gsa.canonical import canonical_features
from gsa.features.settings import FeatureSettings
from gsa.features.vit import WeightsError, load_backbone, load_sphere_head, to_input
from gsa.render import render_model

__all__ = [
    "FeatureExtractor",
    "FeatureSettings",
    "SphereMapExtractor",
    "Dinov2PCAExtractor",
    "CanonicalExtractor",
    "EXTRACTORS",
    "make_extractor",
    "WeightsError",
]

# Setting names as they appear in errors, the CLI (--backbone/--head) and the environment.
BACKBONE_SETTING = "features.backbone (--backbone, GSA_FEATURES_BACKBONE)"
HEAD_SETTING = "features.head (--head, GSA_FEATURES_HEAD)"


class FeatureExtractor(ABC):
    """Base class. `extract` handles one image; `extract_views` a rendered view set
    (images (C,H,W,3), masks (C,H,W)) and may use the model and cameras it came from."""

    name = "base"

    def extract(self, image: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """image (H,W,3) float in [0,1], mask (H,W) bool -> (H,W,3) float32, 0 outside mask."""
        return self.extract_views(np.asarray(image)[None], np.asarray(mask)[None])[0]

    @abstractmethod
    def extract_views(self, images: np.ndarray, masks: np.ndarray, *, model=None, cameras=None) -> np.ndarray:
        """Implemented by each subclass."""


def _check_views(images: np.ndarray, masks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    images = np.asarray(images, np.float32)
    masks = np.asarray(masks).astype(bool)
    if images.ndim != 4 or images.shape[-1] != 3:
        raise ValueError(f"images must be (C,H,W,3), got {images.shape}")
    if masks.shape != images.shape[:3]:
        raise ValueError(f"masks must be (C,H,W) = {images.shape[:3]}, got {masks.shape}")
    return images, masks


def _patch_masks(masks: np.ndarray, h: int, w: int) -> torch.Tensor:
    """(C,H,W) bool -> (C,h,w) bool: a patch is foreground when at least half its pixels are."""
    m = torch.as_tensor(masks, dtype=torch.float32)[:, None]
    return F.adaptive_avg_pool2d(m, (h, w))[:, 0] >= 0.5


def _upsample(maps: torch.Tensor, masks: np.ndarray) -> np.ndarray:
    """(C,3,h,w) -> (C,H,W,3) bilinear, zeroed outside the full-resolution masks."""
    _, hh, ww = masks.shape
    up = F.interpolate(maps, size=(hh, ww), mode="bilinear", align_corners=False)
    up = up.permute(0, 2, 3, 1) * torch.as_tensor(masks, dtype=up.dtype)[..., None]
    return up.numpy().astype(np.float32)


class SphereMapExtractor(FeatureExtractor):
    """Viewpoint-guided spherical maps (Mariotti et al., CVPR 2024) as GSA uses them:
    frozen DINOv2 pre-norm patch tokens -> sphere_mapper head -> L2-normalised 3-vector per
    patch; background patches -1; encoded (f+1)/2; bilinear to image size; background 0."""

    name = "spheremap"

    def __init__(self, backbone: torch.nn.Module, head: torch.nn.Module, input_size: int = 518, batch_size: int = 4):
        self.backbone, self.head = backbone.eval(), head.eval()
        self.input_size, self.batch_size = input_size, batch_size

    @classmethod
    def from_settings(cls, s: FeatureSettings) -> SphereMapExtractor:
        backbone = load_backbone(s.backbone, BACKBONE_SETTING)
        head = load_sphere_head(s.head, backbone.cfg.embed_dim, HEAD_SETTING)
        return cls(backbone, head, s.input_size, s.batch_size)

    @torch.no_grad()
    def patch_spheres(self, images: np.ndarray) -> torch.Tensor:
        """(C,H,W,3) -> (C,h,w,3) unit vectors per patch."""
        out = []
        for i in range(0, len(images), self.batch_size):
            pre, _ = self.backbone(to_input(images[i : i + self.batch_size], self.input_size))
            out.append(F.normalize(self.head(pre.flatten(1, 2)), dim=-1).reshape(*pre.shape[:3], 3))
        return torch.cat(out)

    def extract_views(self, images, masks, *, model=None, cameras=None) -> np.ndarray:
        images, masks = _check_views(images, masks)
        sph = self.patch_spheres(images)
        fg = _patch_masks(masks, sph.shape[1], sph.shape[2])
        sph = torch.where(fg[..., None], sph, torch.full_like(sph, -1.0))
        enc = (sph + 1.0) * 0.5  # background -1 -> 0
        return _upsample(enc.permute(0, 3, 1, 2), masks)


class Dinov2PCAExtractor(FeatureExtractor):
    """DINOv2 (normed) patch tokens projected on their top-3 principal components, fitted on
    the foreground patches of the view set, each component min-max scaled to [0,1] over those
    patches (1st-99th percentile, clipped). The basis is kept after the first fit, so a second
    model extracted with the same instance lands in the same feature space (paper App. D)."""

    name = "dinov2"

    def __init__(self, backbone: torch.nn.Module, input_size: int = 518, batch_size: int = 4):
        self.backbone, self.input_size, self.batch_size = backbone.eval(), input_size, batch_size
        self.pca: tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor] | None = None

    @classmethod
    def from_settings(cls, s: FeatureSettings) -> Dinov2PCAExtractor:
        return cls(load_backbone(s.backbone, BACKBONE_SETTING), s.input_size, s.batch_size)

    @torch.no_grad()
    def tokens(self, images: np.ndarray) -> torch.Tensor:
        out = [
            self.backbone(to_input(images[i : i + self.batch_size], self.input_size))[1]
            for i in range(0, len(images), self.batch_size)
        ]
        return torch.cat(out)

    def fit(self, tokens: torch.Tensor) -> None:
        """tokens (M, D) foreground patch tokens -> mean, basis (D,3), low/high (3,) for scaling."""
        x = tokens.double()
        mean = x.mean(0)
        _, _, vh = torch.linalg.svd(x - mean, full_matrices=False)
        basis = vh[:3].T
        # Sign of each component fixed by its largest loading: deterministic across runs.
        basis = basis * torch.sign(basis.gather(0, basis.abs().argmax(0, keepdim=True)))
        proj = (x - mean) @ basis
        lo = torch.quantile(proj, 0.01, dim=0)
        hi = torch.quantile(proj, 0.99, dim=0)
        self.pca = (mean, basis, lo, torch.maximum(hi, lo + 1e-9))

    def extract_views(self, images, masks, *, model=None, cameras=None) -> np.ndarray:
        images, masks = _check_views(images, masks)
        tok = self.tokens(images)  # (C,h,w,D)
        fg = _patch_masks(masks, tok.shape[1], tok.shape[2])
        if self.pca is None:
            sel = tok[fg]
            if len(sel) < 3:
                raise ValueError("dinov2 PCA needs at least 3 foreground patches; the masks are (nearly) empty")
            self.fit(sel)
        mean, basis, lo, hi = self.pca
        f = ((tok.double() - mean) @ basis - lo) / (hi - lo)
        f = f.clamp(0.0, 1.0).float() * fg[..., None]
        return _upsample(f.permute(0, 3, 1, 2), masks)


class CanonicalExtractor(FeatureExtractor):
    """The weight-free default: the model's canonical 3-D features (gsa.canonical)
    rendered to 2D with the rasterizer. Needs the model and cameras, not pixels. Maps are
    alpha-premultiplied (exactly what the renderer composites, background 0), not hard-masked:
    that keeps them consistent with the renderer at soft silhouettes."""

    name = "canonical"

    def __init__(self, backend: str = "auto"):
        self.backend = backend

    def extract(self, image, mask) -> np.ndarray:
        raise ValueError(
            "the canonical extractor renders the model's own 3-D features; "
            "call extract_views(images, masks, model=..., cameras=...)"
        )

    def extract_views(self, images, masks, *, model=None, cameras=None) -> np.ndarray:
        if model is None or cameras is None:
            raise ValueError("the canonical extractor needs model= and cameras=")
        feats = canonical_features(model)
        out = render_model(
            model.with_features(feats),
            cameras,
            features=True,
            depth=False,
            backend=self.backend,
            feature_background=np.zeros(3),
        )
        return out.features.numpy().astype(np.float32)


EXTRACTORS = {
    "spheremap": SphereMapExtractor.from_settings,
    "dinov2": Dinov2PCAExtractor.from_settings,
    "canonical": lambda s: CanonicalExtractor(s.backend),
}


def make_extractor(name: str, settings: FeatureSettings | None = None) -> FeatureExtractor:
    """Build the extractor `name` from settings (loading weights from their local paths)."""
    settings = settings or FeatureSettings()
    if name not in EXTRACTORS:
        raise ValueError(f"unknown feature extractor {name!r}; choose one of {', '.join(EXTRACTORS)}")
    return EXTRACTORS[name](settings)


def weights_configured(name: str, settings: FeatureSettings) -> bool:
    """Whether `name` has the weight paths it needs set (not whether they exist)."""
    if name == "canonical":
        return True
    if name == "dinov2":
        return bool(settings.backbone)
    if name == "spheremap":
        return bool(settings.backbone) and bool(settings.head)
    return False
