"""Differentiable 3DGS rendering of colour, N-channel features, alpha and depth.

One entry point, `rasterize(...)`, with backends:
  "cpu"       torch projection + native numba compositing with a hand-written backward (default here);
  "cuda"      gsplat.rasterization on a CUDA device (used by "auto" when available; see gsa.render.cuda);
  "reference" torch projection + dense pure-torch compositing (slow; ground truth for tests).
`render_gaussians(...)` is the same on precomputed 3D covariances and explicit view matrices
(which may be similarities, so gradients reach a Sim(3) applied to the model through the cameras).
"""

from __future__ import annotations

import functools

import numpy as np
import torch

from gsa.render.cameras import Cameras, cameras_around, look_at, orbit_cameras
from gsa.render.cuda import render_gsplat
from gsa.render.output import RenderOutput, split_channels
from gsa.render.projection import colors_from_sh, covariance_3d, project
from gsa.render.reference import composite_reference
from gsa.render.steps import step

__all__ = [
    "Cameras",
    "RenderOutput",
    "cameras_around",
    "look_at",
    "orbit_cameras",
    "rasterize",
    "render_gaussians",
    "render_model",
    "available_backends",
]

BACKENDS = ("auto", "cpu", "cuda", "reference")


@functools.cache
def cuda_available() -> bool:
    """A CUDA device and a working gsplat extension. gsplat's PyPI wheel compiles its kernels on
    first use (minutes, needs nvcc): importing `gsplat` alone proves nothing, so this loads the
    compiled module, once per process."""
    if not torch.cuda.is_available():
        return False
    try:
        from gsplat.cuda._backend import _C
    # a native extension built against another torch/CUDA can fail in any way on import:
    # the CUDA backend is then unavailable and "auto" uses the CPU
    except Exception:  # noqa: BLE001
        return False
    return _C is not None


def available_backends() -> list[str]:
    return ["cpu", "reference"] + (["cuda"] if cuda_available() else [])


def resolve_backend(backend: str) -> str:
    """The backend that `backend` ("auto" included) renders with here: "cpu", "cuda" or "reference"."""
    if backend not in BACKENDS:
        raise ValueError(f"unknown backend {backend!r}; choose one of {BACKENDS}")
    if backend == "auto":
        return "cuda" if cuda_available() else "cpu"
    if backend == "cuda" and not cuda_available():
        raise ValueError("backend 'cuda' needs a CUDA device and the gsplat package")
    return backend


def _as_tensor(x, dtype=None) -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        return x if dtype is None else x.to(dtype)
    return torch.as_tensor(np.asarray(x), dtype=dtype or torch.float32)


def render_gaussians(
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
    backend: str = "auto",
    tile: int = 16,
) -> RenderOutput:
    """Render N Gaussians given as means (N,3), cov3d (N,3,3), opacities (N,) in (0,1).

    viewmats (C,4,4) world-to-camera (rigid or similarity), intrinsics (C,4) fx, fy, cx, cy.
    Colour from exactly one of colors (N,3) or (C,N,3) (used as is) or sh (N,K,3)
    (3DGS SH, view-dependent, +0.5 and clamped at 0), or neither (features only).
    features (N,D) composited like colour; background (3,) for colour and
    feature_background (D,) for features (default zeros).
    """
    backend = resolve_backend(backend)
    if colors is not None and sh is not None:
        raise ValueError("give colors or sh, not both")
    n = means.shape[0]
    if n == 0:
        raise ValueError("cannot render an empty set of Gaussians")
    if means.shape != (n, 3) or cov3d.shape != (n, 3, 3) or opacities.shape != (n,):
        raise ValueError(
            f"shape mismatch: means {tuple(means.shape)}, cov3d {tuple(cov3d.shape)}, "
            f"opacities {tuple(opacities.shape)}"
        )
    if features is not None and (features.ndim != 2 or features.shape[0] != n):
        raise ValueError(f"features must be (N, D) with N={n}, got {tuple(features.shape)}")
    c_count = viewmats.shape[0]
    if backend == "cuda":
        return render_gsplat(
            means,
            cov3d,
            opacities,
            viewmats,
            intrinsics,
            width,
            height,
            colors=colors,
            sh=sh,
            features=features,
            background=background,
            feature_background=feature_background,
            depth=depth,
        )
    dtype = means.dtype
    if backend == "cpu":
        # gsa.render.cpu is imported by the functions that use it: it loads numba and sets its
        # threading layer, which only the CPU backend needs.
        from gsa.render.cpu import project_cpu

        means2d, conics, z, cov_diag, valid = project_cpu(means, cov3d, viewmats, intrinsics, width, height)
    else:
        means2d, conics, z, cov_diag, valid = project(means, cov3d, viewmats, intrinsics, width, height)
    step()  # a caller's callback between the steps of a CPU render (gsa.render.steps)
    chans, bgs = [], []
    if sh is not None:
        if sh.ndim != 3 or sh.shape[0] != n or sh.shape[2] != 3 or sh.shape[1] not in (1, 4, 9, 16):
            raise ValueError(f"sh must be (N, K, 3) with K in 1, 4, 9, 16, got {tuple(sh.shape)}")
        colors = colors_from_sh(sh, means, viewmats)
    if colors is not None:
        if colors.shape[-1] != 3 or colors.shape[-2] != n:
            raise ValueError(f"colors must be (N, 3) or (C, N, 3), got {tuple(colors.shape)}")
        chans.append(colors.expand(c_count, n, 3))
        bgs.append(_as_tensor(background if background is not None else np.zeros(3), dtype).reshape(3))
    if features is not None:
        d = features.shape[1]
        chans.append(features[None].expand(c_count, n, d))
        bgs.append(_as_tensor(feature_background if feature_background is not None else np.zeros(d), dtype).reshape(d))
    if depth:
        chans.append(z[..., None])
        bgs.append(torch.zeros(1, dtype=dtype))
    if not chans:  # alpha only: composite a dummy channel
        chans.append(torch.zeros(c_count, n, 1, dtype=dtype))
        bgs.append(torch.zeros(1, dtype=dtype))
    chan = torch.cat(chans, -1)
    bg = torch.cat(bgs)
    op = opacities[None].expand(c_count, n)
    if backend == "cpu":
        from gsa.render.cpu import composite_cpu  # lazy: see above

        out, alpha = composite_cpu(means2d, conics, op, chan, cov_diag, z.detach(), valid, bg, width, height, tile)
    else:
        out, alpha = composite_reference(means2d, conics, op, chan, z, valid, bg, width, height)
    return split_channels(out, alpha, colors is not None, None if features is None else features.shape[1], depth)


def covariance(quats: torch.Tensor, log_scales: torch.Tensor, backend: str = "auto") -> torch.Tensor:
    """(N,3,3) 3D covariances R S S^T R^T as `backend` computes them (the CPU backend has a
    native kernel with a hand-written backward; the others use torch)."""
    if resolve_backend(backend) == "cpu":
        from gsa.render.cpu import covariance_cpu  # lazy: see render_gaussians

        return covariance_cpu(quats, log_scales)
    return covariance_3d(quats, log_scales)


def camera_tensors(cameras: Cameras, dtype=torch.float32) -> tuple[torch.Tensor, torch.Tensor]:
    """(C,4,4) view matrices and (C,4) intrinsics as tensors."""
    return (torch.as_tensor(cameras.viewmats, dtype=dtype), torch.as_tensor(cameras.intrinsics, dtype=dtype))


def rasterize(
    means,
    quats,
    log_scales,
    opacity_logits,
    colors_or_sh,
    features=None,
    cameras: Cameras = None,
    *,
    background=(0.0, 0.0, 0.0),
    feature_background=None,
    depth: bool = True,
    backend: str = "auto",
    viewmats=None,
) -> RenderOutput:
    """Render Gaussians from C cameras.

    means (N,3), quats (N,4) w,x,y,z, log_scales (N,3), opacity_logits (N,), colors_or_sh: (N,3)
    RGB used as is, or (N,K,3) SH coefficients (degree 0..3, view-dependent), or None;
    features (N,D) or None. Arrays may be numpy (-> float32) or torch tensors (gradients flow
    to every tensor that requires them). `viewmats` (C,4,4) overrides the cameras' poses,
    e.g. a tensor W·T that carries gradients to a Sim(3) T.
    Returns RenderOutput with colors (C,H,W,3), features (C,H,W,D), alpha (C,H,W,1), depth (C,H,W,1).
    """
    if cameras is None:
        raise ValueError("rasterize needs cameras")
    means = _as_tensor(means)
    dtype = means.dtype
    quats, log_scales, opacity_logits = (_as_tensor(a, dtype) for a in (quats, log_scales, opacity_logits))
    backend = resolve_backend(backend)
    cov3d = covariance(quats, log_scales, backend)
    if backend != "cuda":
        step()  # gsa.render.steps
    vm, intr = camera_tensors(cameras, dtype)
    if viewmats is not None:
        vm = _as_tensor(viewmats, dtype)
    colors = sh = None
    if colors_or_sh is not None:
        c = _as_tensor(colors_or_sh, dtype)
        if c.ndim == 3:
            sh = c
        else:
            colors = c
    feats = None if features is None else _as_tensor(features, dtype)
    return render_gaussians(
        means,
        cov3d,
        torch.sigmoid(opacity_logits.reshape(-1)),
        vm,
        intr,
        cameras.width,
        cameras.height,
        colors=colors,
        sh=sh,
        features=feats,
        background=background,
        feature_background=feature_background,
        depth=depth,
        backend=backend,
    )


def render_model(
    model,
    cameras: Cameras,
    *,
    features: bool = True,
    background=(1.0, 1.0, 1.0),
    feature_background=None,
    depth: bool = True,
    backend: str = "auto",
    sim3=None,
) -> RenderOutput:
    """Render a GaussianModel (optionally as sim3·model, by moving the cameras) without gradients."""
    if len(model) == 0:
        raise ValueError("cannot render an empty model")
    if sim3 is not None:
        cameras = cameras.for_transformed_model(sim3)
    with torch.no_grad():
        out = rasterize(
            model.means,
            model.quats,
            model.log_scales,
            model.opacity_logits,
            model.sh,
            model.features if features else None,
            cameras,
            background=background,
            feature_background=feature_background,
            depth=depth,
            backend=backend,
        )
    cpu = lambda t: None if t is None else t.cpu()  # noqa: E731  (gsplat renders live on the GPU)
    return RenderOutput(cpu(out.colors), cpu(out.features), cpu(out.alpha), cpu(out.depth))
