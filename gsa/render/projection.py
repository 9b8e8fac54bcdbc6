"""Differentiable per-camera preprocessing in torch, shared by every CPU-side backend.

EWA splatting as in 3DGS / gsplat: camera-space means, 2D covariance
J W Σ W^T J^T (+0.3 low-pass dilation), its inverse (the conic), and colour from
SH evaluated along the view direction. These are O(N) vectorised ops; the
O(pixels x Gaussians) compositing is what the native kernels do.
"""

from __future__ import annotations

import torch

from gsa.render.constants import EPS2D, NEAR
from gsa.sh import SH_C0, SH_C1, SH_C2, SH_C3


def quats_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """(N, 4) w,x,y,z (any norm) -> (N, 3, 3)."""
    q = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        -1,
    ).reshape(-1, 3, 3)


def covariance_3d(quats: torch.Tensor, log_scales: torch.Tensor) -> torch.Tensor:
    """(N, 4), (N, 3) -> (N, 3, 3) Σ = R diag(exp(2 log_s)) R^T."""
    m = quats_to_rotmat(quats) * torch.exp(log_scales)[:, None, :]
    return m @ m.transpose(1, 2)


def eval_sh(sh: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """3DGS SH colour: sh (N, K, 3), dirs (..., N, 3) unit -> (..., N, 3) = max(0, Σ c_k Y_k + 0.5)."""
    k = sh.shape[1]
    res = SH_C0 * sh[:, 0]
    if k > 1:
        x, y, z = dirs[..., 0:1], dirs[..., 1:2], dirs[..., 2:3]
        res = res - SH_C1 * y * sh[:, 1] + SH_C1 * z * sh[:, 2] - SH_C1 * x * sh[:, 3]
        if k > 4:
            xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
            res = (
                res
                + SH_C2[0] * xy * sh[:, 4]
                + SH_C2[1] * yz * sh[:, 5]
                + SH_C2[2] * (2 * zz - xx - yy) * sh[:, 6]
                + SH_C2[3] * xz * sh[:, 7]
                + SH_C2[4] * (xx - yy) * sh[:, 8]
            )
            if k > 9:
                res = (
                    res
                    + SH_C3[0] * y * (3 * xx - yy) * sh[:, 9]
                    + SH_C3[1] * xy * z * sh[:, 10]
                    + SH_C3[2] * y * (4 * zz - xx - yy) * sh[:, 11]
                    + SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy) * sh[:, 12]
                    + SH_C3[4] * x * (4 * zz - xx - yy) * sh[:, 13]
                    + SH_C3[5] * z * (xx - yy) * sh[:, 14]
                    + SH_C3[6] * x * (xx - 3 * yy) * sh[:, 15]
                )
    return torch.clamp_min(res + 0.5, 0.0)


def camera_centers(viewmats: torch.Tensor) -> torch.Tensor:
    """(C, 4, 4) world-to-camera (rigid or similarity) -> (C, 3) centres in world coordinates."""
    a = viewmats[:, :3, :3]
    return -torch.linalg.solve(a, viewmats[:, :3, 3:4])[..., 0]


def colors_from_sh(sh: torch.Tensor, means: torch.Tensor, viewmats: torch.Tensor) -> torch.Tensor:
    """(N, K, 3) SH -> (C, N, 3) view-dependent colours (or (1, N, 3) when K == 1)."""
    if sh.shape[1] == 1:
        return eval_sh(sh, means[None])  # no direction needed; broadcasts over cameras
    dirs = means[None] - camera_centers(viewmats)[:, None, :]
    dirs = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return eval_sh(sh, dirs)


def project(
    means: torch.Tensor,
    cov3d: torch.Tensor,
    viewmats: torch.Tensor,
    intrinsics: torch.Tensor,
    width: int,
    height: int,
    near: float = NEAR,
):
    """Project N Gaussians into C cameras.

    means (N, 3), cov3d (N, 3, 3), viewmats (C, 4, 4), intrinsics (C, 4) = fx, fy, cx, cy.
    Returns means2d (C, N, 2), conics (C, N, 3) = (a, b, c) of [[a, b], [b, c]] = Σ2D^-1,
    depths (C, N), cov2d_diag (C, N, 2) (for bounding boxes; no gradient needed),
    valid (C, N) bool (in front of the near plane).
    """
    a = viewmats[:, :3, :3]
    p = torch.einsum("cij,nj->cni", a, means) + viewmats[:, None, :3, 3]
    x, y, z = p.unbind(-1)
    valid = z > near
    zs = torch.where(valid, z, torch.ones_like(z))  # keeps culled entries finite
    fx, fy, cx, cy = (intrinsics[:, i : i + 1] for i in range(4))
    # Clamp the Jacobian's evaluation point like 3DGS/gsplat so far off-screen
    # Gaussians do not produce huge, unstable footprints.
    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    lim_xp, lim_xn = (width - cx) / fx + 0.3 * tan_x, cx / fx + 0.3 * tan_x
    lim_yp, lim_yn = (height - cy) / fy + 0.3 * tan_y, cy / fy + 0.3 * tan_y
    u, v = x / zs, y / zs
    tu = torch.maximum(torch.minimum(u, lim_xp), -lim_xn)
    tv = torch.maximum(torch.minimum(v, lim_yp), -lim_yn)
    # rows of M = J A (C, N, 3): J = [[fx/z, 0, -fx tu/z], [0, fy/z, -fy tv/z]]
    a0, a1, a2 = a[:, None, 0, :], a[:, None, 1, :], a[:, None, 2, :]
    m0 = (fx / zs)[..., None] * (a0 - tu[..., None] * a2)
    m1 = (fy / zs)[..., None] * (a1 - tv[..., None] * a2)
    s0 = torch.einsum("cnj,njk->cnk", m0, cov3d)
    s1 = torch.einsum("cnj,njk->cnk", m1, cov3d)
    caa = (s0 * m0).sum(-1) + EPS2D
    cab = (s0 * m1).sum(-1)
    cbb = (s1 * m1).sum(-1) + EPS2D
    det = (caa * cbb - cab * cab).clamp_min(1e-12)
    conics = torch.stack([cbb / det, -cab / det, caa / det], -1)
    means2d = torch.stack([fx * u + cx, fy * v + cy], -1)
    return means2d, conics, z, torch.stack([caa, cbb], -1).detach(), valid
