"""Slow, obviously-correct pure-torch compositing: every pixel against every Gaussian.

Used by the tests as ground truth (values, and gradients through torch autograd)
for the native CPU kernels. Memory is O(C x N x H x W): tiny scenes only.

Compositing rule shared with the native kernels (3DGS rules, made tile-independent):
a Gaussian touches a pixel iff its Mahalanobis distance² <= 9 (3σ ellipse) and
alpha = min(0.99, o·exp(-d²/2)) >= 1/255; front-to-back by camera depth (stable
order); a pixel stops before the Gaussian that would push its transmittance below 1e-4.
"""

from __future__ import annotations

import torch

from gsa.render.constants import ALPHA_MAX, ALPHA_MIN, MAHA_CUTOFF, T_MIN


def composite_reference(means2d, conics, opacities, chans, depths, valid, background, width: int, height: int):
    """means2d (C,N,2), conics (C,N,3), opacities (C,N), chans (C,N,F), depths (C,N),
    valid (C,N) bool, background (F,) -> out (C,H,W,F), alpha (C,H,W,1)."""
    c_count, n, f = chans.shape
    dtype = chans.dtype
    ys, xs = torch.meshgrid(
        torch.arange(height, dtype=dtype) + 0.5, torch.arange(width, dtype=dtype) + 0.5, indexing="ij"
    )
    px, py = xs.reshape(-1), ys.reshape(-1)
    outs, alphas = [], []
    for c in range(c_count):
        if n == 0:
            outs.append(background.expand(height * width, f).reshape(height, width, f))
            alphas.append(torch.zeros(height, width, 1, dtype=dtype))
            continue
        order = torch.sort(depths[c].detach(), stable=True).indices
        m = means2d[c, order]
        a, b, cc = conics[c, order].unbind(-1)
        dx = m[:, 0:1] - px[None]
        dy = m[:, 1:2] - py[None]
        m2 = a[:, None] * dx * dx + 2 * b[:, None] * dx * dy + cc[:, None] * dy * dy
        alpha = torch.clamp(opacities[c, order][:, None] * torch.exp(-0.5 * m2), max=ALPHA_MAX)
        keep = (m2 <= MAHA_CUTOFF) & (alpha >= ALPHA_MIN) & valid[c, order][:, None]
        alpha = torch.where(keep, alpha, torch.zeros_like(alpha))
        with torch.no_grad():  # early termination: a prefix of the depth order survives
            alive = torch.cumprod(1 - alpha, dim=0) >= T_MIN
        alpha = torch.where(alive, alpha, torch.zeros_like(alpha))
        trans = torch.cumprod(1 - alpha, dim=0)
        t_before = torch.cat([torch.ones_like(trans[:1]), trans[:-1]], 0)
        w = alpha * t_before  # (N, HW)
        img = w.transpose(0, 1) @ chans[c, order] + trans[-1][:, None] * background[None]
        outs.append(img.reshape(height, width, f))
        alphas.append((1 - trans[-1]).reshape(height, width, 1))
    return torch.stack(outs), torch.stack(alphas)
