"""Feature extractors (2D), lifting onto 3DGS models, background pruning (paper Sec. 3.2, App. D, E).

    extractor = make_extractor("spheremap", FeatureSettings(backbone=..., head=...))
    lifted, report = lift_features(model, extractor)
    lifted, removed = prune_background(lifted, 0.1)

`prepare_pair(source, target, mode, settings)` is what `gsa align --features ...` runs.
Names resolve lazily (the modules load torch), so the CLI starts fast.
"""

from __future__ import annotations

from gsa.lazy import lazy_exports

_HOME = {
    "ALIGN_FEATURE_MODES": "gsa.features.prepare",
    "CanonicalExtractor": "gsa.features.extractors",
    "Dinov2PCAExtractor": "gsa.features.extractors",
    "EXTRACTORS": "gsa.features.extractors",
    "FeatureExtractor": "gsa.features.extractors",
    "FeatureSettings": "gsa.features.settings",
    "LiftReport": "gsa.features.lift",
    "SphereMapExtractor": "gsa.features.extractors",
    "WeightsError": "gsa.features.extractors",
    "lift_features": "gsa.features.lift",
    "lift_features_full": "gsa.features.lift",
    "make_extractor": "gsa.features.extractors",
    "prepare_for_alignment": "gsa.features.prepare",
    "prepare_pair": "gsa.features.prepare",
    "prune_background": "gsa.features.lift",
    "resolve_mode": "gsa.features.prepare",
    "weights_configured": "gsa.features.extractors",
}

__all__ = sorted(_HOME)
__getattr__, __dir__ = lazy_exports(__name__, _HOME)
