"""3D covariances from quaternions and log-scales, with a hand-written backward."""

from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit, prange

from gsa.render.cpu.common import _KERNEL_LOCK, _np


# ------------------------------------------------------- 3D covariance from quats and scales
@njit(parallel=True, cache=True, error_model="numpy")
def _cov_fwd(quats, log_scales):
    n = quats.shape[0]
    cov = np.empty((n, 3, 3), quats.dtype)
    for i in prange(n):
        r, s = _rot_scale(quats[i], log_scales[i])
        for a in range(3):
            for b in range(3):
                acc = 0.0
                for j in range(3):
                    acc += r[a, j] * s[j] * s[j] * r[b, j]
                cov[i, a, b] = acc
    return cov


@njit(cache=True, error_model="numpy")
def _rot_scale(q, ls):
    nrm = max(math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]), 1e-12)
    w, x, y, z = q[0] / nrm, q[1] / nrm, q[2] / nrm, q[3] / nrm
    r = np.empty((3, 3), np.float64)
    r[0, 0] = 1 - 2 * (y * y + z * z)
    r[0, 1] = 2 * (x * y - w * z)
    r[0, 2] = 2 * (x * z + w * y)
    r[1, 0] = 2 * (x * y + w * z)
    r[1, 1] = 1 - 2 * (x * x + z * z)
    r[1, 2] = 2 * (y * z - w * x)
    r[2, 0] = 2 * (x * z - w * y)
    r[2, 1] = 2 * (y * z + w * x)
    r[2, 2] = 1 - 2 * (x * x + y * y)
    s = np.empty(3, np.float64)
    for j in range(3):
        s[j] = math.exp(ls[j])
    return r, s


@njit(parallel=True, cache=True, error_model="numpy")
def _cov_bwd(quats, log_scales, g_cov):
    """Σ = R(q/|q|) diag(s²) R^T -> gradients w.r.t. the raw quaternion and log-scales."""
    n = quats.shape[0]
    g_q = np.zeros((n, 4), quats.dtype)
    g_ls = np.zeros((n, 3), quats.dtype)
    for i in prange(n):
        q = quats[i]
        r, s = _rot_scale(q, log_scales[i])
        # M = R diag(s), Σ = M M^T  =>  dL/dM = (G + G^T) M
        gr = np.empty((3, 3), np.float64)
        for a in range(3):
            for j in range(3):
                gm = 0.0
                for b in range(3):
                    gm += (g_cov[i, a, b] + g_cov[i, b, a]) * r[b, j] * s[j]
                gr[a, j] = gm * s[j]
                g_ls[i, j] += gm * r[a, j] * s[j]
        nrm = max(math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]), 1e-12)
        w, x, y, z = q[0] / nrm, q[1] / nrm, q[2] / nrm, q[3] / nrm
        gw = 2 * (-z * gr[0, 1] + y * gr[0, 2] + z * gr[1, 0] - x * gr[1, 2] - y * gr[2, 0] + x * gr[2, 1])
        gx = 2 * (
            y * gr[0, 1]
            + z * gr[0, 2]
            + y * gr[1, 0]
            - 2 * x * gr[1, 1]
            - w * gr[1, 2]
            + z * gr[2, 0]
            + w * gr[2, 1]
            - 2 * x * gr[2, 2]
        )
        gy = 2 * (
            -2 * y * gr[0, 0]
            + x * gr[0, 1]
            + w * gr[0, 2]
            + x * gr[1, 0]
            + z * gr[1, 2]
            - w * gr[2, 0]
            + z * gr[2, 1]
            - 2 * y * gr[2, 2]
        )
        gz = 2 * (
            -2 * z * gr[0, 0]
            - w * gr[0, 1]
            + x * gr[0, 2]
            + w * gr[1, 0]
            - 2 * z * gr[1, 1]
            + y * gr[1, 2]
            + x * gr[2, 0]
            + y * gr[2, 1]
        )
        dot = w * gw + x * gx + y * gy + z * gz
        g_q[i, 0] = (gw - w * dot) / nrm
        g_q[i, 1] = (gx - x * dot) / nrm
        g_q[i, 2] = (gy - y * dot) / nrm
        g_q[i, 3] = (gz - z * dot) / nrm
    return g_q, g_ls


class _CovarianceCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, *args):
        with _KERNEL_LOCK:
            return _CovarianceCPU._forward(ctx, *args)

    @staticmethod
    def backward(ctx, *grads):
        with _KERNEL_LOCK:
            return _CovarianceCPU._backward(ctx, *grads)

    @staticmethod
    def _forward(ctx, quats, log_scales):
        dt = np.float64 if quats.dtype == torch.float64 else np.float32
        q, ls = _np(quats, dt), _np(log_scales, dt)
        ctx.saved = (q, ls)
        ctx.dtype = quats.dtype
        return torch.from_numpy(_cov_fwd(q, ls))

    @staticmethod
    def _backward(ctx, g_cov):
        q, ls = ctx.saved
        g_q, g_ls = _cov_bwd(q, ls, _np(g_cov, q.dtype))
        return torch.from_numpy(g_q).to(ctx.dtype), torch.from_numpy(g_ls).to(ctx.dtype)


def covariance_cpu(quats, log_scales):
    """Native gsa.render.projection.covariance_3d: (N,4), (N,3) -> (N,3,3), hand-written backward."""
    return _CovarianceCPU.apply(quats.contiguous(), log_scales.contiguous())
