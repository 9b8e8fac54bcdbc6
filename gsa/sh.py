"""Real spherical harmonics in the 3DGS convention, and their exact rotation.

The basis (constants and signs) is the one the INRIA rasterizer evaluates, so a
model whose SH were rotated here renders, from a rotated camera, exactly as the
original did.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

# The basis' constants, defined here once (the model's DC colour, the renderer's SH colour).
SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def sh_dc_to_rgb(dc: np.ndarray) -> np.ndarray:
    """The RGB colour a DC coefficient encodes (the 3DGS convention, not clipped): 0.5 + C0·dc."""
    return 0.5 + SH_C0 * dc


def rgb_to_sh_dc(rgb: np.ndarray) -> np.ndarray:
    """The DC coefficient of an RGB colour (the inverse of sh_dc_to_rgb)."""
    return (rgb - 0.5) / SH_C0


def sh_basis(dirs: np.ndarray, degree: int) -> np.ndarray:
    """(M, 3) unit directions -> (M, (degree+1)**2) basis values, float64."""
    d = np.asarray(dirs, np.float64)
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    out = [np.full_like(x, SH_C0)]
    if degree >= 1:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [
            SH_C2[0] * xy,
            SH_C2[1] * yz,
            SH_C2[2] * (2 * zz - xx - yy),
            SH_C2[3] * xz,
            SH_C2[4] * (xx - yy),
        ]
    if degree >= 3:
        out += [
            SH_C3[0] * y * (3 * xx - yy),
            SH_C3[1] * xy * z,
            SH_C3[2] * y * (4 * zz - xx - yy),
            SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            SH_C3[4] * x * (4 * zz - xx - yy),
            SH_C3[5] * z * (xx - yy),
            SH_C3[6] * x * (xx - 3 * yy),
        ]
    return np.stack(out, axis=1)


def eval_sh(sh: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Colour contribution Σ_k c_k Y_k(d) for (N, K, 3) coefficients at (N, 3) directions."""
    degree = int(round(np.sqrt(sh.shape[1]))) - 1
    basis = sh_basis(dirs, degree)
    return np.einsum("nk,nkc->nc", basis, np.asarray(sh, np.float64))


@lru_cache(maxsize=1)
def _probe_directions() -> np.ndarray:
    # A fixed, well-spread set (Fibonacci sphere): 64 points make every band's
    # basis matrix full-rank and well conditioned, so the solve below is exact.
    n = 64
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    theta = np.pi * (1 + 5**0.5) * i
    return np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], 1)


def sh_rotation_matrices(rotation: np.ndarray, degree: int) -> list[np.ndarray]:
    """Per band l = 1..degree, the (2l+1)x(2l+1) matrix D_l with Y_l(Rᵀ d) = D_l Y_l(d).

    Each band spans a rotation-invariant space, so D_l is determined exactly by
    any set of directions on which Y_l has full rank; we solve on a fixed
    well-conditioned set in float64 (equivalent to the Wigner-D matrix in this basis).
    """
    r = np.asarray(rotation, np.float64)
    probe = _probe_directions()
    basis = sh_basis(probe, degree)
    basis_rot = sh_basis(probe @ r, degree)  # rows are Rᵀ d
    mats = []
    for band in range(1, degree + 1):
        sl = slice(band * band, (band + 1) ** 2)
        # basis_rot[:, sl] = basis[:, sl] @ D_lᵀ
        d_t, *_ = np.linalg.lstsq(basis[:, sl], basis_rot[:, sl], rcond=None)
        mats.append(d_t.T)
    return mats


def rotate_sh(sh: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """SH coefficients (N, K, 3) of a model rotated by R: the new coefficients c'
    satisfy Σ c'_k Y_k(R d) = Σ c_k Y_k(d) for every direction d."""
    sh = np.asarray(sh)
    degree = int(round(np.sqrt(sh.shape[1]))) - 1
    if degree == 0:
        return sh.astype(np.float32, copy=True)
    out = np.empty(sh.shape, np.float32)
    out[:, 0] = sh[:, 0]
    for band, d in enumerate(sh_rotation_matrices(rotation, degree), start=1):
        sl = slice(band * band, (band + 1) ** 2)
        # c'(d) = c(Rᵀ d) = cᵀ D Y(d)  ->  c' = Dᵀ c per colour channel; as (N, 3, m) @ D,
        # which is twice as fast as the equivalent einsum on millions of Gaussians.
        out[:, sl] = np.matmul(sh[:, sl].astype(np.float64).transpose(0, 2, 1), d).transpose(0, 2, 1)
    return out
