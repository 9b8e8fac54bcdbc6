"""Differentiable Gaussian rasterization: one entry point, several backends.

    out = rasterize(means, quats, log_scales, opacity_logits, colors_or_sh, features, cameras)
    out = render_model(model, cameras)

The implementation lives in `gsa.render.rasterizer`; names are resolved lazily
so that importing `gsa.render.cameras` or the CLI does not load torch.
"""

from __future__ import annotations

import importlib

from gsa.render.cameras import Cameras, cameras_around, look_at, orbit_cameras

_LAZY = dict.fromkeys(
    (
        "BACKENDS",
        "RenderOutput",
        "available_backends",
        "camera_tensors",
        "covariance",
        "cuda_available",
        "rasterize",
        "render_gaussians",
        "render_model",
        "resolve_backend",
        "colors_from_sh",
        "covariance_3d",
        "project",
    ),
    "gsa.render.rasterizer",
)
_LAZY["locality_order"] = "gsa.render.cpu"

__all__ = ["Cameras", "cameras_around", "look_at", "orbit_cameras", *sorted(_LAZY)]


def __getattr__(name: str):
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'gsa.render' has no attribute {name!r}")
