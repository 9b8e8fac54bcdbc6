"""Job options: which ones a client may set, which the server sets, which outputs exist."""

from __future__ import annotations

import dataclasses
from typing import Any, Literal, get_args

from gsa.features.settings import FeatureSettings  # torch-free: safe at API start-up
from gsa.settings_env import feature_settings_env
from service.problems import invalid_input

SERVICE_OPTIONS = {"outputs", "renders", "recon_iterations"}
# The artifacts a job can produce: the one definition (the HTTP schema's enum,
# validation and the worker's default all come from it).
OutputName = Literal["result", "aligned", "merged", "renders"]
OUTPUT_NAMES: tuple[str, ...] = get_args(OutputName)
DEFAULT_OUTPUTS = OUTPUT_NAMES  # a job that names no outputs gets all of them


def server_only_option(name: str) -> bool:
    return name in ("device", "feature_settings") or name.endswith(("_weights", "_path", "_dir", "_device"))


def server_options(settings, known: set[str]) -> dict:
    """Deployment settings for AlignOptions fields that exist in this library build:
    extractor weights (DINOv2 backbone, sphere-mapper head) live on the worker."""
    out = {}
    if "device" in known and settings.worker_device:
        out["device"] = settings.worker_device
    if "feature_settings" in known and (settings.dinov2_weights or settings.spheremap_weights):
        out["feature_settings"] = FeatureSettings(
            **feature_settings_env(
                backbone=str(settings.dinov2_weights) if settings.dinov2_weights else None,
                head=str(settings.spheremap_weights) if settings.spheremap_weights else None,
            )
        )
    return out


def align_option_names() -> set[str]:
    """The option names this library build's AlignOptions accepts."""
    from gsa.align.pipeline import AlignOptions  # lazy: ~1 s of imports, kept off API start-up

    return {f.name for f in dataclasses.fields(AlignOptions)}


def validate_options(options: dict[str, Any]) -> dict[str, Any]:
    fixed = sorted(k for k in options if server_only_option(k))
    if fixed:
        # Paths and devices are the server's business: a client path must never reach the filesystem.
        raise invalid_input(f"option(s) set by the server, not the client: {', '.join(fixed)}")
    known = align_option_names()
    unknown = sorted(set(options) - known - SERVICE_OPTIONS)
    if unknown:
        raise invalid_input(
            f"unknown option(s): {', '.join(unknown)}",
            allowed=sorted(known | SERVICE_OPTIONS),
        )
    outs = options.get("outputs")
    if outs is not None:
        bad = sorted(set(outs) - set(OUTPUT_NAMES))
        if bad:
            raise invalid_input(f"unknown output(s): {', '.join(bad)}")
    return options
