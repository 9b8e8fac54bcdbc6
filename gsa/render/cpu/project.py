"""Native projection (means, 2D covariances, conics) with a hand-written backward."""

from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange

from gsa.render.constants import EPS2D, NEAR
from gsa.render.cpu.common import _CHUNKS, _KERNEL_LOCK, _np

# ---------------------------------------------------------------- projection
# Native twin of gsa.render.projection.project (same formulas, same Jacobian clamp), with a
# hand-written backward to view matrices, means and 3D covariances. torch autograd on the
# vectorised version costs ~10x more than compositing at 50k Gaussians, hence this path.


@njit(parallel=True, cache=True, error_model="numpy")
def _project_fwd(means, cov, view, intr, width, height):
    n = means.shape[0]
    c_count = view.shape[0]
    dt = means.dtype
    m2d = np.zeros((c_count, n, 2), dt)
    con = np.zeros((c_count, n, 3), dt)
    depth = np.zeros((c_count, n), dt)
    cdiag = np.zeros((c_count, n, 2), dt)
    valid = np.zeros((c_count, n), np.bool_)
    chunk = (n + _CHUNKS - 1) // _CHUNKS
    # (camera, chunk) jobs: per-camera constants stay in registers and writes are contiguous
    for job in prange(c_count * _CHUNKS):
        c = job // _CHUNKS
        k = job % _CHUNKS
        fx, fy, cx, cy = intr[c, 0], intr[c, 1], intr[c, 2], intr[c, 3]
        v00, v01, v02, v03 = view[c, 0, 0], view[c, 0, 1], view[c, 0, 2], view[c, 0, 3]
        v10, v11, v12, v13 = view[c, 1, 0], view[c, 1, 1], view[c, 1, 2], view[c, 1, 3]
        v20, v21, v22, v23 = view[c, 2, 0], view[c, 2, 1], view[c, 2, 2], view[c, 2, 3]
        lxp = (width - cx) / fx + 0.15 * width / fx
        lxn = cx / fx + 0.15 * width / fx
        lyp = (height - cy) / fy + 0.15 * height / fy
        lyn = cy / fy + 0.15 * height / fy
        for i in range(k * chunk, min(n, (k + 1) * chunk)):
            mx, my, mz = means[i, 0], means[i, 1], means[i, 2]
            x = v00 * mx + v01 * my + v02 * mz + v03
            y = v10 * mx + v11 * my + v12 * mz + v13
            z = v20 * mx + v21 * my + v22 * mz + v23
            depth[c, i] = z
            if not z > NEAR:
                continue
            valid[c, i] = True
            u = x / z
            v = y / z
            tu = max(min(u, lxp), -lxn)
            tv = max(min(v, lyp), -lyn)
            # rows of J A (J: perspective Jacobian at the clamped point)
            m00 = fx / z * (v00 - tu * v20)
            m01 = fx / z * (v01 - tu * v21)
            m02 = fx / z * (v02 - tu * v22)
            m10 = fy / z * (v10 - tv * v20)
            m11 = fy / z * (v11 - tv * v21)
            m12 = fy / z * (v12 - tv * v22)
            s00 = m00 * cov[i, 0, 0] + m01 * cov[i, 1, 0] + m02 * cov[i, 2, 0]
            s01 = m00 * cov[i, 0, 1] + m01 * cov[i, 1, 1] + m02 * cov[i, 2, 1]
            s02 = m00 * cov[i, 0, 2] + m01 * cov[i, 1, 2] + m02 * cov[i, 2, 2]
            s11 = m10 * cov[i, 0, 1] + m11 * cov[i, 1, 1] + m12 * cov[i, 2, 1]
            s10 = m10 * cov[i, 0, 0] + m11 * cov[i, 1, 0] + m12 * cov[i, 2, 0]
            s12 = m10 * cov[i, 0, 2] + m11 * cov[i, 1, 2] + m12 * cov[i, 2, 2]
            caa = EPS2D + s00 * m00 + s01 * m01 + s02 * m02
            cab = s00 * m10 + s01 * m11 + s02 * m12
            cbb = EPS2D + s10 * m10 + s11 * m11 + s12 * m12
            det = max(caa * cbb - cab * cab, 1e-12)
            con[c, i, 0] = cbb / det
            con[c, i, 1] = -cab / det
            con[c, i, 2] = caa / det
            m2d[c, i, 0] = fx * u + cx
            m2d[c, i, 1] = fy * v + cy
            cdiag[c, i, 0] = caa
            cdiag[c, i, 1] = cbb
    return m2d, con, depth, cdiag, valid


@njit(parallel=True, cache=True, error_model="numpy")
def _project_bwd(means, cov, view, intr, width, height, con, valid, g_m2d, g_con, g_depth, want_geom):
    """-> g_view (C,4,4), g_means (N,3), g_cov (N,3,3) (the last two zero-size unless want_geom)."""
    n = means.shape[0]
    c_count = view.shape[0]
    dt = means.dtype
    g_means = np.zeros((n if want_geom else 0, 3), dt)
    g_cov = np.zeros((n if want_geom else 0, 3, 3), dt)
    chunk = (n + _CHUNKS - 1) // _CHUNKS
    g_view_part = np.zeros((_CHUNKS, c_count, 3, 4), np.float64)
    for k in prange(_CHUNKS):
        m0 = np.empty(3, np.float64)
        m1 = np.empty(3, np.float64)
        gm0 = np.empty(3, np.float64)
        gm1 = np.empty(3, np.float64)
        mvec = np.empty(3, np.float64)
        # one camera at a time so its view-gradient sums stay in local variables
        gv = np.zeros((3, 4), np.float64)
        for c in range(c_count):
            fx, fy, cx, cy = intr[c, 0], intr[c, 1], intr[c, 2], intr[c, 3]
            lxp = (width - cx) / fx + 0.15 * width / fx
            lxn = cx / fx + 0.15 * width / fx
            lyp = (height - cy) / fy + 0.15 * height / fy
            lyn = cy / fy + 0.15 * height / fy
            a0 = view[c, 0, :3]
            a1 = view[c, 1, :3]
            a2 = view[c, 2, :3]
            gv[:] = 0.0
            for i in range(k * chunk, min(n, (k + 1) * chunk)):
                if not valid[c, i]:
                    continue
                mvec[0], mvec[1], mvec[2] = means[i, 0], means[i, 1], means[i, 2]
                x = a0[0] * mvec[0] + a0[1] * mvec[1] + a0[2] * mvec[2] + view[c, 0, 3]
                y = a1[0] * mvec[0] + a1[1] * mvec[1] + a1[2] * mvec[2] + view[c, 1, 3]
                z = a2[0] * mvec[0] + a2[1] * mvec[1] + a2[2] * mvec[2] + view[c, 2, 3]
                u = x / z
                v = y / z
                tu = max(min(u, lxp), -lxn)
                tv = max(min(v, lyp), -lyn)
                fxz = fx / z
                fyz = fy / z
                for j in range(3):
                    m0[j] = fxz * (a0[j] - tu * a2[j])
                    m1[j] = fyz * (a1[j] - tv * a2[j])
                # conic = S^-1: dL/dS from dQ = -Q dS Q
                a, b, cc = con[c, i, 0], con[c, i, 1], con[c, i, 2]
                ga, gb, gc = g_con[c, i, 0], g_con[c, i, 1], g_con[c, i, 2]
                g_caa = -(ga * a * a + gb * a * b + gc * b * b)
                g_cab = -(ga * 2 * a * b + gb * (a * cc + b * b) + gc * 2 * b * cc)
                g_cbb = -(ga * b * b + gb * b * cc + gc * cc * cc)
                for j in range(3):
                    s0 = cov[i, j, 0] * m0[0] + cov[i, j, 1] * m0[1] + cov[i, j, 2] * m0[2]
                    s1 = cov[i, j, 0] * m1[0] + cov[i, j, 1] * m1[1] + cov[i, j, 2] * m1[2]
                    gm0[j] = 2 * g_caa * s0 + g_cab * s1
                    gm1[j] = 2 * g_cbb * s1 + g_cab * s0
                    if want_geom:
                        for l in range(3):
                            g_cov[i, j, l] += g_caa * m0[j] * m0[l] + g_cab * m0[j] * m1[l] + g_cbb * m1[j] * m1[l]
                # M0 = fx/z (A0 - tu A2), M1 = fy/z (A1 - tv A2)
                g_tu = 0.0
                g_tv = 0.0
                g_z = g_depth[c, i]
                for j in range(3):
                    gv[0, j] += fxz * gm0[j]
                    gv[1, j] += fyz * gm1[j]
                    gv[2, j] -= fxz * tu * gm0[j] + fyz * tv * gm1[j]
                    g_tu -= fxz * gm0[j] * a2[j]
                    g_tv -= fyz * gm1[j] * a2[j]
                    g_z -= (gm0[j] * m0[j] + gm1[j] * m1[j]) / z
                g_u = fx * g_m2d[c, i, 0] + (g_tu if -lxn < u < lxp else 0.0)
                g_v = fy * g_m2d[c, i, 1] + (g_tv if -lyn < v < lyp else 0.0)
                g_x = g_u / z
                g_y = g_v / z
                g_z -= (g_u * u + g_v * v) / z
                for j in range(3):
                    gv[0, j] += g_x * mvec[j]
                    gv[1, j] += g_y * mvec[j]
                    gv[2, j] += g_z * mvec[j]
                    if want_geom:
                        g_means[i, j] += g_x * a0[j] + g_y * a1[j] + g_z * a2[j]
                gv[0, 3] += g_x
                gv[1, 3] += g_y
                gv[2, 3] += g_z
            g_view_part[k, c] = gv
    g_view = np.zeros((c_count, 4, 4), np.float64)
    for k in range(_CHUNKS):
        g_view[:, :3, :] += g_view_part[k]
    return g_view, g_means, g_cov


class _ProjectCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, *args):
        with _KERNEL_LOCK:
            return _ProjectCPU._forward(ctx, *args)

    @staticmethod
    def backward(ctx, *grads):
        with _KERNEL_LOCK:
            return _ProjectCPU._backward(ctx, *grads)

    @staticmethod
    def _forward(ctx, means, cov3d, viewmats, intrinsics, width, height):
        dt = np.float64 if means.dtype == torch.float64 else np.float32
        args = (_np(means, dt), _np(cov3d, dt), _np(viewmats, dt), _np(intrinsics, dt))
        m2d, con, depth, cdiag, valid = _project_fwd(*args, width, height)
        ctx.saved = args + (width, height, con, valid)
        ctx.dtype = means.dtype
        as_t = torch.from_numpy
        out = (as_t(m2d), as_t(con), as_t(depth), as_t(cdiag), as_t(valid))
        ctx.mark_non_differentiable(out[3], out[4])
        return out

    @staticmethod
    def _backward(ctx, g_m2d, g_con, g_depth, _g_cdiag, _g_valid):
        means, cov, view, intr, width, height, con, valid = ctx.saved
        dt = means.dtype
        c_count, n = valid.shape
        z2 = lambda shape: np.zeros(shape, dt)  # noqa: E731
        g_m2d = z2((c_count, n, 2)) if g_m2d is None else _np(g_m2d, dt)
        g_con = z2((c_count, n, 3)) if g_con is None else _np(g_con, dt)
        g_depth = z2((c_count, n)) if g_depth is None else _np(g_depth, dt)
        want_geom = bool(ctx.needs_input_grad[0] or ctx.needs_input_grad[1])
        g_view, g_means, g_cov = _project_bwd(
            means, cov, view, intr, width, height, con, valid, g_m2d, g_con, g_depth, want_geom
        )
        t = lambda a: torch.from_numpy(a).to(ctx.dtype)  # noqa: E731
        if not want_geom:
            return None, None, t(g_view), None, None, None
        return t(g_means), t(g_cov), t(g_view), None, None, None


def project_cpu(means, cov3d, viewmats, intrinsics, width: int, height: int):
    """Native version of gsa.render.projection.project (same outputs, valid is a bool tensor);
    differentiable w.r.t. means, cov3d and viewmats (not intrinsics)."""
    if intrinsics.requires_grad:
        raise ValueError("the CPU projection does not differentiate intrinsics")
    return _ProjectCPU.apply(means, cov3d, viewmats, intrinsics, int(width), int(height))
