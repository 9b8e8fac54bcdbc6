"""Differentiable Gaussian rasterization: one entry point, several backends.

    out = rasterize(means, quats, log_scales, opacity_logits, colors_or_sh, features, cameras)
    out = render_model(model, cameras)

The implementation lives in `gsa.render.rasterizer`; names are resolved lazily
so that importing `gsa.render.cameras` or the CLI does not load torch.
"""

from __future__ import annotations

from gsa.lazy import lazy_exports
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
__getattr__, __dir__ = lazy_exports(__name__, _LAZY)
