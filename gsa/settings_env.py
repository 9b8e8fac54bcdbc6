"""Settings read from the environment: only the edges (the `gsa` CLI and its command modules,
the service's settings) import this; the library takes its settings as arguments.

Standard library only, so reading the environment costs the CLI no start-up time.

    FeatureSettings(**feature_settings_env(backbone=args.backbone))   # GSA_FEATURES_* / GSA_LIFT_*
    encoder, decoder = sam_paths_env(args.sam_encoder, args.sam_decoder)   # GSA_SAM_*
"""

from __future__ import annotations

import os
from collections.abc import Mapping

# gsa.features.FeatureSettings field -> (environment variable, type of its value)
FEATURE_ENV: dict[str, tuple[str, type]] = {
    "extractor": ("GSA_FEATURES_EXTRACTOR", str),
    "backbone": ("GSA_FEATURES_BACKBONE", str),
    "head": ("GSA_FEATURES_HEAD", str),
    "lift_views": ("GSA_LIFT_VIEWS", int),
    "lift_image_size": ("GSA_LIFT_IMAGE_SIZE", int),
    "lift_iterations": ("GSA_LIFT_ITERATIONS", int),
    "prune_threshold": ("GSA_PRUNE_THRESHOLD", float),
}
# "off" turns the semantic tie-break (gsa.align.semantic) off where no option says otherwise.
SEMANTIC_ENV = "GSA_SEMANTIC"
SAM_ENCODER_ENV = "GSA_SAM_ENCODER"
SAM_DECODER_ENV = "GSA_SAM_DECODER"


def feature_settings_env(environ: Mapping[str, str] | None = None, **overrides) -> dict:
    """Keyword arguments for gsa.features.FeatureSettings from the GSA_FEATURES_* / GSA_LIFT_*
    variables (unset or empty ones are left to the defaults); keyword overrides win when not None."""
    environ = os.environ if environ is None else environ
    kw = {}
    for name, (var, kind) in FEATURE_ENV.items():
        if environ.get(var):
            kw[name] = kind(environ[var])
    kw.update({k: v for k, v in overrides.items() if v is not None})
    return kw


def sam_paths_env(
    encoder: str | None = None, decoder: str | None = None, environ: Mapping[str, str] | None = None
) -> tuple[str | None, str | None]:
    """The SAM ONNX encoder/decoder paths: the given ones, else GSA_SAM_ENCODER / GSA_SAM_DECODER."""
    environ = os.environ if environ is None else environ
    return encoder or environ.get(SAM_ENCODER_ENV), decoder or environ.get(SAM_DECODER_ENV)


def semantic_env(environ: Mapping[str, str] | None = None) -> str:
    """auto or off, from GSA_SEMANTIC (unset or empty: auto); ValueError naming it otherwise."""
    environ = os.environ if environ is None else environ
    value = (environ.get(SEMANTIC_ENV) or "auto").strip().lower()
    if value not in ("auto", "off"):
        raise ValueError(f"{SEMANTIC_ENV} must be auto or off, got {environ.get(SEMANTIC_ENV)!r}")
    return value
