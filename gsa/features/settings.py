"""Feature-extraction and lifting settings (no torch: the CLI builds them before it knows
whether an extractor will run). Taken as arguments; gsa.settings_env reads them from the
environment for the CLI and the service."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal


@dataclass
class FeatureSettings:
    """Where weights live and how lifting runs. Paths are local; nothing is downloaded.

    backbone: HF Dinov2 folder or torch.hub DINOv2 state dict (spheremap and dinov2);
    head: sphere_mapper checkpoint (spheremap only);
    extractor: what `--features auto` uses for a model without features
    ("canonical" unless weights are configured).
    """

    extractor: Literal["canonical", "spheremap", "dinov2"] = "canonical"
    backbone: str | None = None
    head: str | None = None
    input_size: int = 518  # 37x37 patches of 14 px, as GSA feeds the spherical mapper
    batch_size: int = 4  # images per backbone forward (memory vs. overhead)
    lift_views: int = 24
    lift_image_size: int = 128
    lift_iterations: int = 150
    lift_lr: float = 0.02
    lift_batch_views: int = 4
    prune_threshold: float = 0.1  # the authors' background-Gaussian threshold
    backend: Literal["auto", "cpu", "cuda", "reference"] = "auto"  # rasterizer backend (gsa.render.BACKENDS)
