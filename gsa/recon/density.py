"""The optimiser and adaptive density control of gsa.recon.train: Adam over a dict of
tensors whose rows can be selected or appended, and 3DGS clone/split/prune (plus GSA's
feature-norm pruning, App. E)."""

from __future__ import annotations

import math
from typing import Protocol

import torch

from gsa.render.projection import quats_to_rotmat


class DensityConfig(Protocol):
    """The gsa.recon.train.TrainConfig fields density control reads."""

    grad_threshold: float
    percent_dense: float
    max_gaussians: int
    prune_opacity: float
    feature_prune: float


class Adam:
    """Adam over a dict of leaf tensors; moments are plain tensors so rows can be
    selected or appended when Gaussians are pruned or densified."""

    def __init__(self, params: dict[str, torch.Tensor], lrs: dict[str, float], betas=(0.9, 0.999), eps=1e-15):
        self.params, self.lrs, self.betas, self.eps = params, dict(lrs), betas, eps
        self.m = {k: torch.zeros_like(v) for k, v in params.items()}
        self.v = {k: torch.zeros_like(v) for k, v in params.items()}
        self.t = dict.fromkeys(params, 0)

    @torch.no_grad()
    def step(self, names) -> None:
        b1, b2 = self.betas
        for k in names:
            p = self.params[k]
            if p.grad is None:
                continue
            g = p.grad
            self.t[k] += 1
            self.m[k].mul_(b1).add_(g, alpha=1 - b1)
            self.v[k].mul_(b2).addcmul_(g, g, value=1 - b2)
            mh = self.m[k] / (1 - b1 ** self.t[k])
            vh = self.v[k] / (1 - b2 ** self.t[k])
            p.sub_(self.lrs[k] * mh / (vh.sqrt() + self.eps))
            p.grad = None

    def zero_grad(self) -> None:
        for p in self.params.values():
            p.grad = None

    def remap(self, new_params: dict[str, torch.Tensor], keep: torch.Tensor, n_new: int) -> None:
        """Rows `keep` of every tensor survive (in order), then n_new rows with zero moments."""
        for k in new_params:
            for st in (self.m, self.v):
                old = st[k][keep]
                st[k] = torch.cat([old, torch.zeros((n_new,) + old.shape[1:], dtype=old.dtype, device=old.device)])
        self.params = new_params


@torch.no_grad()
def densify_and_prune(
    opt: Adam,
    avg_grad,
    cfg: DensityConfig,
    extent: float,
    rng,
    densify: bool,
    region: tuple[torch.Tensor, float] | None = None,
) -> int:
    """One round of density control; region (centre, radius): Gaussians whose means left that
    ball (an object capture's region, gsa.recon.region) are pruned too. Returns how many were
    pruned for lying outside it (0 when the round keeps everything: never below 4 Gaussians)."""
    p = opt.params
    n = len(p["means"])
    scales = p["log_scales"].exp()
    smax = scales.max(1).values
    new_rows: dict[str, list[torch.Tensor]] = {k: [] for k in p}
    device = p["means"].device
    remove = torch.zeros(n, dtype=torch.bool, device=device)
    if densify and avg_grad is not None and n < cfg.max_gaussians:
        big = avg_grad >= cfg.grad_threshold
        # Keep the growth within the cap: the largest gradients first.
        budget = max(0, cfg.max_gaussians - n)
        idx = torch.nonzero(big).flatten()
        if len(idx) > budget:
            idx = idx[torch.argsort(avg_grad[idx], descending=True)[:budget]]
        sel = torch.zeros(n, dtype=torch.bool, device=device)
        sel[idx] = True
        clone = sel & (smax <= cfg.percent_dense * extent)
        split = sel & ~clone
        for k in p:  # clone: an identical copy (the gradient steps then separate them)
            new_rows[k].append(p[k][clone])
        if split.any():
            m = p["means"][split]
            s = scales[split]
            r = quats_to_rotmat(p["quats"][split])
            for _ in range(2):  # two children sampled from the parent, scales / 1.6
                off = (r @ (torch.randn_like(s) * s)[..., None])[..., 0]
                for k in p:
                    if k == "means":
                        new_rows[k].append(m + off)
                    elif k == "log_scales":
                        new_rows[k].append(p[k][split] - math.log(1.6))
                    else:
                        new_rows[k].append(p[k][split])
            remove |= split
    op = torch.sigmoid(p["opacity"])
    remove |= op < cfg.prune_opacity
    remove |= smax > 0.2 * extent
    if "features" in p:
        remove |= p["features"].norm(dim=1) < cfg.feature_prune
    outside = torch.zeros(n, dtype=torch.bool, device=device)
    if region is not None:
        outside = (p["means"] - region[0]).norm(dim=1) > region[1]
        outside &= ~remove
        remove |= outside
    keep = ~remove
    if keep.sum() < 4:  # never prune the model away
        return 0
    new_params = {}
    n_new = 0
    for k in p:
        add = torch.cat(new_rows[k]) if new_rows[k] else p[k][:0]
        n_new = len(add)
        new_params[k] = torch.cat([p[k].detach()[keep], add.detach()]).requires_grad_(True)
    opt.remap(new_params, keep, n_new)
    return int(outside.sum())
