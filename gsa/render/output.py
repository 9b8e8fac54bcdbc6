"""What every rendering backend returns, and how a composited channel stack is unpacked into it."""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass
class RenderOutput:
    """Per-camera images: colors (C,H,W,3) | None, features (C,H,W,D) | None, alpha (C,H,W,1),
    depth (C,H,W,1) | None (expected camera depth of the visible surface, 0 where alpha == 0)."""

    colors: torch.Tensor | None
    features: torch.Tensor | None
    alpha: torch.Tensor
    depth: torch.Tensor | None


def split_channels(
    out: torch.Tensor, alpha: torch.Tensor, has_colors: bool, feature_dim: int | None, depth: bool
) -> RenderOutput:
    """Unstack composited channels [colour(3) | features(D) | depth·alpha(1)] (C,H,W,·):
    every backend composites them as one stack."""
    i = 0
    col = feat = dep = None
    if has_colors:
        col, i = out[..., 0:3], 3
    if feature_dim is not None:
        feat, i = out[..., i : i + feature_dim], i + feature_dim
    if depth:
        acc = out[..., i : i + 1]
        dep = torch.where(alpha > 1e-6, acc / alpha.clamp_min(1e-6), torch.zeros_like(acc))
    return RenderOutput(col, feat, alpha, dep)
