"""gsplat backend (CUDA), written against the documented `gsplat.rasterization(...)` API
(gsplat >= 1.0, `covars=` argument). Used by `backend="auto"` when torch.cuda.is_available()
and gsplat's compiled extension loads. tests/test_render_cuda.py checks it against the CPU
backend on a GPU machine (skipped without one); the results are in docs/benchmarks.md.

Colour (SH evaluated in torch, same convention as the CPU path), features and camera depth
are rendered together as one post-activation channel stack (sh_degree=None), so every
backend returns the same quantities. gsplat's compositing cut-offs (per-tile 3σ boxes)
differ slightly from the CPU backend's tile-independent rule; values agree to about 1e-2
near Gaussian footprint edges, not to machine precision.
"""

from __future__ import annotations

import torch

from gsa.render.constants import EPS2D, NEAR
from gsa.render.output import split_channels
from gsa.render.projection import colors_from_sh


def render_gsplat(
    means,
    cov3d,
    opacities,
    viewmats,
    intrinsics,
    width: int,
    height: int,
    *,
    colors=None,
    sh=None,
    features=None,
    background=None,
    feature_background=None,
    depth: bool = False,
):
    """Same contract as gsa.render.render_gaussians: inputs are moved to CUDA and the images
    back to the device `means` is on (differentiably both ways), so callers that keep their
    tensors on the CPU (training, the fine stage) need not know which backend rendered."""
    import gsplat  # optional dependency: only this backend needs it

    home = means.device
    dev = torch.device("cuda")
    dtype = torch.float32  # gsplat kernels are float32
    means, cov3d, opacities = (t.to(dev, dtype) for t in (means, cov3d, opacities))
    viewmats, intrinsics = viewmats.to(dev, dtype), intrinsics.to(dev, dtype)
    c_count, n = viewmats.shape[0], means.shape[0]
    ks = torch.zeros(c_count, 3, 3, device=dev, dtype=dtype)
    ks[:, 0, 0], ks[:, 1, 1] = intrinsics[:, 0], intrinsics[:, 1]
    ks[:, 0, 2], ks[:, 1, 2], ks[:, 2, 2] = intrinsics[:, 2], intrinsics[:, 3], 1.0
    chans, bgs = [], []
    if sh is not None:
        colors = colors_from_sh(sh.to(dev, dtype), means, viewmats)
    if colors is not None:
        chans.append(colors.to(dev, dtype).expand(c_count, n, 3))
        bgs.append(torch.as_tensor(background if background is not None else [0.0] * 3, dtype=dtype, device=dev))
    if features is not None:
        d = features.shape[1]
        chans.append(features.to(dev, dtype)[None].expand(c_count, n, d))
        bgs.append(
            torch.as_tensor(
                feature_background if feature_background is not None else [0.0] * d, dtype=dtype, device=dev
            ).reshape(d)
        )
    if depth:
        z = torch.einsum("cj,nj->cn", viewmats[:, 2, :3], means) + viewmats[:, 2, 3:4]
        chans.append(z[..., None])
        bgs.append(torch.zeros(1, dtype=dtype, device=dev))
    if not chans:
        chans.append(torch.zeros(c_count, n, 1, device=dev, dtype=dtype))
        bgs.append(torch.zeros(1, dtype=dtype, device=dev))
    chan = torch.cat(chans, -1).contiguous()
    bg = torch.cat(bgs)[None].expand(c_count, -1).contiguous()
    out, alpha, _meta = gsplat.rasterization(
        means,
        None,
        None,
        opacities,
        chan,
        viewmats,
        ks,
        width,
        height,
        near_plane=NEAR,
        eps2d=EPS2D,
        sh_degree=None,
        packed=False,
        backgrounds=bg,
        render_mode="RGB",
        covars=cov3d,
    )
    return split_channels(
        out.to(home), alpha.to(home), colors is not None, None if features is None else features.shape[1], depth
    )
