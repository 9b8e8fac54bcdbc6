"""Giving models features for alignment: the modes of `gsa align --features` (see gsa.features).

    extractor = make_extractor("spheremap", FeatureSettings(backbone=..., head=...))
    lifted, report = lift_features(model, extractor)
    lifted, removed = prune_background(lifted, 0.1)

`prepare_for_alignment(model, mode, settings)` is what `gsa align --features ...` calls.
"""

from __future__ import annotations

from gsa.canonical import canonical_features
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

__all__ = [
    "ALIGN_FEATURE_MODES",
    "EXTRACTORS",
    "CanonicalExtractor",
    "Dinov2PCAExtractor",
    "FeatureExtractor",
    "FeatureSettings",
    "LiftReport",
    "SphereMapExtractor",
    "WeightsError",
    "lift_features",
    "lift_features_full",
    "make_extractor",
    "prepare_for_alignment",
    "prepare_pair",
    "prune_background",
]

ALIGN_FEATURE_MODES = ("auto", "file", "canonical", "spheremap", "dinov2")


def prepare_for_alignment(
    model: GaussianModel,
    mode: str = "auto",
    settings: FeatureSettings | None = None,
    *,
    extractor: FeatureExtractor | None = None,
    progress=None,
    reports: list | None = None,
) -> GaussianModel:
    """A copy of `model` that carries the features `mode` asks for.

    file:      the model's own features (error if it has none);
    canonical: the weight-free canonical 3-D features, computed directly per Gaussian
               (exact; no rendering or lifting needed);
    spheremap | dinov2: 2D features from that extractor lifted onto the model, then
               background Gaussians (|f| < settings.prune_threshold) pruned;
    auto:      file features when present (and not frame-relative canonical ones, see
               GaussianModel.features_frame_relative), else settings.extractor when its weights are
               configured (spheremap/dinov2), else canonical.
    `extractor` reuses an already-built extractor (weights loaded once; for dinov2 the same
    PCA basis for both models of a pair). A LiftReport is appended to `reports` when lifting ran.
    """
    settings = settings or FeatureSettings()
    mode = resolve_mode(mode, settings, model)
    if mode == "file":
        if model.features is None:
            raise ModelError(
                "--features file: the model has no semantic_* features "
                "(use auto, canonical, spheremap or dinov2, or `gsa lift` it first)"
            )
        return model
    if mode == "canonical":
        out = model.with_features(canonical_features(model))
        out.metadata["features"] = "canonical"
        return out
    ext = extractor if extractor is not None else make_extractor(mode, settings)
    lifted, report = lift_with_settings(model, ext, settings, progress)
    if reports is not None:
        reports.append(report)
    if settings.prune_threshold > 0:
        lifted, _ = prune_background(lifted, settings.prune_threshold)
    return lifted


def lift_with_settings(model: GaussianModel, extractor, settings: FeatureSettings, progress=None):
    """lift_features with the lifting parameters of `settings` (views, size, iterations,
    learning rate, views per batch, backend): (lifted model, LiftReport)."""
    return lift_features(
        model,
        extractor,
        views=settings.lift_views,
        image_size=settings.lift_image_size,
        iterations=settings.lift_iterations,
        lr=settings.lift_lr,
        batch_views=settings.lift_batch_views,
        backend=settings.backend,
        progress=progress,
    )


def resolve_mode(mode: str, settings: FeatureSettings, *models: GaussianModel) -> str:
    """The concrete feature source `mode` means for these models: auto -> file when every
    model carries features of one dimension, else settings.extractor when its weights are
    configured, else canonical. Other modes are returned unchanged."""
    if mode not in ALIGN_FEATURE_MODES:
        raise ValueError(f"features must be one of {', '.join(ALIGN_FEATURE_MODES)}, got {mode!r}")
    if mode != "auto":
        return mode
    dims = {m.feature_dim for m in models}
    if len(dims) == 1 and 0 not in dims and not any(m.features_frame_relative for m in models):
        return "file"
    if settings.extractor in ("spheremap", "dinov2") and weights_configured(settings.extractor, settings):
        return settings.extractor
    return "canonical"


def prepare_pair(
    source: GaussianModel,
    target: GaussianModel,
    mode: str = "auto",
    settings: FeatureSettings | None = None,
    progress=None,
) -> tuple[GaussianModel, GaussianModel, str, list[LiftReport]]:
    """What `gsa align --features MODE` should run before `gsa.align.align`.

    Returns (source, target, pipeline_mode, lift_reports): pipeline_mode is the
    AlignOptions.features value to use ("file" or "canonical"). canonical is left to the
    pipeline, which computes it natively with its frame hypotheses and ICP refinement; for
    spheremap/dinov2 both models are lifted with ONE extractor (weights loaded once; for dinov2
    one PCA basis, fitted on the source) and background-pruned, then aligned as "file".
    """
    settings = settings or FeatureSettings()
    mode = resolve_mode(mode, settings, source, target)
    if mode in ("file", "canonical"):
        if mode == "file":
            for name, m in (("source", source), ("target", target)):
                if m.features is None:
                    raise ModelError(f"--features file: the {name} has no semantic_* features")
        return source, target, mode, []
    extractor = make_extractor(mode, settings)
    reports: list[LiftReport] = []
    src = prepare_for_alignment(
        source,
        mode,
        settings,
        extractor=extractor,
        reports=reports,
        progress=None if progress is None else (lambda st, f: progress(f"lift source {st}", f)),
    )
    dst = prepare_for_alignment(
        target,
        mode,
        settings,
        extractor=extractor,
        reports=reports,
        progress=None if progress is None else (lambda st, f: progress(f"lift target {st}", f)),
    )
    return src, dst, "file", reports
