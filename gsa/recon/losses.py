"""Training losses of gsa.recon.train: SSIM (11x11 Gaussian window, as 3DGS), the RGB loss
0.8·L1 + 0.2·(1 − SSIM), and PSNR for the held-out report."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F


def gauss_window(size: int = 11, sigma: float = 1.5) -> torch.Tensor:
    x = torch.arange(size, dtype=torch.float32) - size // 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    g = g / g.sum()
    return g[:, None] * g[None, :]


_WINDOW = gauss_window()


def ssim(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Mean SSIM of (H, W, C) images in [0, 1] (11x11 Gaussian window, as 3DGS)."""
    c = a.shape[-1]
    x = a.permute(2, 0, 1)[None]
    y = b.permute(2, 0, 1)[None]
    w = _WINDOW.to(a.device, a.dtype)[None, None].expand(c, 1, -1, -1)
    pad = _WINDOW.shape[0] // 2
    conv = lambda t: F.conv2d(t, w, padding=pad, groups=c)  # noqa: E731
    mx, my = conv(x), conv(y)
    sxx = conv(x * x) - mx**2
    syy = conv(y * y) - my**2
    sxy = conv(x * y) - mx * my
    c1, c2 = 0.01**2, 0.03**2
    s = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx**2 + my**2 + c1) * (sxx + syy + c2))
    return s.mean()


def rgb_loss(pred: torch.Tensor, target: torch.Tensor, ssim_weight: float = 0.2) -> torch.Tensor:
    """0.8·L1 + 0.2·(1 − SSIM)."""
    return (1 - ssim_weight) * (pred - target).abs().mean() + ssim_weight * (1 - ssim(pred, target))


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    d = (np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2
    mse = d.mean() if mask is None else d[mask].mean()
    return float(10 * np.log10(1.0 / max(mse, 1e-12)))
