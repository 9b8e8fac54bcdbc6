"""Small procedural Gaussian scenes for the render tests (test support; no dependency on gsa.synth)."""

from __future__ import annotations

import numpy as np

from gsa.geometry import normalize_quats
from gsa.model import GaussianModel


def blob_object(n: int, seed: int = 0, sh_degree: int = 0, feature_dim: int = 3) -> GaussianModel:
    """An asymmetric bumpy closed surface (extent ~1) covered by n flat-ish Gaussians.

    Colours and features are smooth functions of position (like canonical features), so
    renders of two copies disagree wherever the copies are misaligned.
    """
    if n <= 0:
        raise ValueError("n must be positive")
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    # asymmetric bumps so no rotation maps the shape onto itself
    r = 1.0 + 0.25 * np.sin(3 * d[:, 0] + 1.0) * np.cos(2 * d[:, 1]) + 0.15 * d[:, 2] ** 3 + 0.1 * d[:, 0]
    means = d * r[:, None] * np.array([1.0, 0.7, 0.5])
    area = 4 * np.pi * 0.75**2
    s = np.sqrt(area / n) * 0.9
    scales = np.stack([np.full(n, s), np.full(n, s), np.full(n, s * 0.2)], 1) * rng.uniform(0.7, 1.3, (n, 1))
    # orient the thin axis along the radial direction
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(z, d)
    sin = np.linalg.norm(axis, axis=1)
    cos = d @ z
    ang = np.arctan2(sin, cos)
    axis = axis / np.maximum(sin, 1e-9)[:, None]
    quats = normalize_quats(np.concatenate([np.cos(ang / 2)[:, None], axis * np.sin(ang / 2)[:, None]], 1))
    u = (means - means.min(0)) / np.ptp(means, axis=0)
    colors = np.clip(0.5 + 0.45 * np.sin(np.pi * np.stack([2 * u[:, 0], 3 * u[:, 1] + 1, 2 * u[:, 2] + 2], 1)), 0, 1)
    feats = None
    if feature_dim:
        w = np.random.default_rng(1234).normal(size=(3, feature_dim))
        feats = 0.5 + 0.5 * np.tanh(means @ w)
    model = GaussianModel.from_colors(
        means, colors, quats=quats, scales=scales, opacities=0.8, sh_degree=sh_degree, features=feats
    )
    if sh_degree > 0:
        model.sh[:, 1:, :] = rng.normal(scale=0.05, size=model.sh[:, 1:, :].shape)
    return model


def random_scene(n: int, sh_degree: int, seed: int, dim: int = 3) -> dict[str, np.ndarray]:
    """n random Gaussians as rasterize() takes them (means, quats, log_scales, opacity_logits,
    SH of `sh_degree`, `dim` features): the renderer tests' inputs."""
    rng = np.random.default_rng(seed)
    k = (sh_degree + 1) ** 2
    return dict(
        means=rng.normal(size=(n, 3)) * 0.5,
        quats=rng.normal(size=(n, 4)),
        log_scales=np.log(rng.uniform(0.05, 0.3, size=(n, 3))),
        opacity_logits=rng.normal(size=n) * 1.5,
        sh=rng.normal(size=(n, k, 3)) * 0.4,
        features=rng.normal(size=(n, dim)),
    )
