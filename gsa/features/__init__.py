"""Feature extractors (2D), lifting onto 3DGS models, background pruning (paper Sec. 3.2, App. D, E).

    extractor = make_extractor("spheremap", FeatureSettings(backbone=..., head=...))
    lifted, report = lift_features(model, extractor)
    lifted, removed = prune_background(lifted, 0.1)

`prepare_for_alignment(model, mode, settings)` is what `gsa align --features ...` calls.
"""

from __future__ import annotations

from gsa.features.extractors import (
    EXTRACTORS,
    CanonicalExtractor,
    Dinov2PCAExtractor,
    FeatureExtractor,
    FeatureSettings,
    SphereMapExtractor,
    WeightsError,
    make_extractor,
    weights_configured,
)
from gsa.features.lift import LiftReport, lift_features, lift_features_full, prune_background
from gsa.model import GaussianModel, ModelError

__all__ = ["ALIGN_FEATURE_MODES", "EXTRACTORS", "CanonicalExtractor", "Dinov2PCAExtractor", "FeatureExtractor",
           "FeatureSettings", "LiftReport", "SphereMapExtractor", "WeightsError", "lift_features",
           "lift_features_full", "make_extractor", "prepare_for_alignment", "prune_background"]

ALIGN_FEATURE_MODES = ("auto", "file", "canonical", "spheremap", "dinov2")


def prepare_for_alignment(model: GaussianModel, mode: str = "auto", settings: FeatureSettings | None = None, *,
                          extractor: FeatureExtractor | None = None, progress=None,
                          reports: list | None = None) -> GaussianModel:
    """A copy of `model` that carries the features `mode` asks for.

    file:      the model's own features (error if it has none);
    canonical: the weight-free canonical 3-D features, computed directly per Gaussian
               (exact; no rendering or lifting needed);
    spheremap | dinov2: 2D features from that extractor lifted onto the model, then
               background Gaussians (|f| < settings.prune_threshold) pruned;
    auto:      file features when present, else settings.extractor when its weights are
               configured (spheremap/dinov2), else canonical.
    `extractor` reuses an already-built extractor (weights loaded once; for dinov2 the same
    PCA basis for both models of a pair). A LiftReport is appended to `reports` when lifting ran.
    """
    if mode not in ALIGN_FEATURE_MODES:
        raise ValueError(f"features must be one of {', '.join(ALIGN_FEATURE_MODES)}, got {mode!r}")
    settings = settings or FeatureSettings.from_env()
    if mode == "auto":
        if model.features is not None and model.feature_dim > 0:
            mode = "file"
        elif settings.extractor in ("spheremap", "dinov2") and weights_configured(settings.extractor, settings):
            mode = settings.extractor
        else:
            mode = "canonical"
    if mode == "file":
        if model.features is None:
            raise ModelError("--features file: the model has no semantic_* features "
                             "(use auto, canonical, spheremap or dinov2, or `gsa lift` it first)")
        return model
    if mode == "canonical":
        from gsa.align.canonical import canonical_features

        out = model.with_features(canonical_features(model))
        out.metadata["features"] = "canonical"
        return out
    ext = extractor if extractor is not None else make_extractor(mode, settings)
    lifted, report = lift_features(model, ext, views=settings.lift_views, image_size=settings.lift_image_size,
                                   iterations=settings.lift_iterations, lr=settings.lift_lr,
                                   batch_views=settings.lift_batch_views, backend=settings.backend,
                                   progress=progress)
    if reports is not None:
        reports.append(report)
    if settings.prune_threshold > 0:
        lifted, _ = prune_background(lifted, settings.prune_threshold)
    return lifted
