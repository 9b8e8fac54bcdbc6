"""Native CPU compositing with numba: tile binning, front-to-back forward and a
hand-written back-to-front backward (the scheme of the CUDA 3DGS rasterizer).

Work is parallel over (camera, 16x16 tile) with prange. Inside a tile, Gaussians
are visited in depth order and each one only touches the pixels of its own
bounding box (3σ ellipse shrunk by the 1/255 opacity cutoff), keeping per-pixel
transmittance, so the cost is the true overlap rather than pixels x list length.
The backward pass recovers each pixel's transmittance from the saved final value
(T / (1 - alpha)) and the saved contributor count. Gradients are written per
(tile, Gaussian) pair, never shared between threads, then reduced per camera,
so results are deterministic and race-free.

Projection (means, covariances, SH) happens in torch (gsa.render.projection);
`composite_cpu` is a torch.autograd.Function over its outputs, so autograd chains
the kernel gradients to means, quaternions, log-scales, opacities, SH and features.
Kernels are compiled for float32 (speed) and float64 (gradient checks).
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch
from numba import njit, prange

from gsa.render.reference import ALPHA_MAX, ALPHA_MIN, MAHA_CUTOFF, T_MIN

TILE = 16


@njit(cache=True)
def _pixel_box(mx, my, ex, ey, x0, y0, x1, y1):
    """Pixels (inclusive ranges) whose centres lie inside [m - e, m + e], clipped to a tile."""
    px0 = max(x0, int(math.ceil(mx - ex - 0.5)))
    px1 = min(x1 - 1, int(math.floor(mx + ex - 0.5)))
    py0 = max(y0, int(math.ceil(my - ey - 0.5)))
    py1 = min(y1 - 1, int(math.floor(my + ey - 0.5)))
    return px0, px1, py0, py1


@njit(cache=True)
def _extents(cov_diag, opac, valid):
    """(C,N,2) half-extents of each Gaussian's footprint; -1 for culled ones.

    A pixel can only contribute where d² <= min(9, 2 ln(255 o)); the ellipse
    d^T Σ^-1 d <= t has half-widths sqrt(t Σ_xx), sqrt(t Σ_yy). A small margin
    keeps boundary pixels that the exact per-pixel tests then decide.
    """
    c_count, n = opac.shape
    ext = np.empty((c_count, n, 2), cov_diag.dtype)
    for c in range(c_count):
        for i in range(n):
            o = opac[c, i]
            if not valid[c, i] or o * 255.0 < 1.0:
                ext[c, i, 0] = -1.0
                ext[c, i, 1] = -1.0
                continue
            t = min(MAHA_CUTOFF, 2.0 * math.log(255.0 * o)) * 1.0001 + 1e-6
            ext[c, i, 0] = math.sqrt(t * cov_diag[c, i, 0])
            ext[c, i, 1] = math.sqrt(t * cov_diag[c, i, 1])
    return ext


@njit(parallel=True, cache=True)
def _bin(means2d, ext, depths, width, height, tile):
    """Per (camera, tile) lists of Gaussian ids sorted front to back.

    Returns offsets (C*T + 1,) int64 and ids (P,) int32; the list of job j is
    ids[offsets[j]:offsets[j+1]].
    """
    c_count, n = depths.shape
    tx_n = (width + tile - 1) // tile
    ty_n = (height + tile - 1) // tile
    nt = tx_n * ty_n
    counts = np.zeros(c_count * nt, np.int64)
    rects = np.full((c_count, n, 4), -1, np.int32)
    for c in prange(c_count):
        for i in range(n):
            if ext[c, i, 0] < 0:
                continue
            px0, px1, py0, py1 = _pixel_box(means2d[c, i, 0], means2d[c, i, 1], ext[c, i, 0], ext[c, i, 1],
                                            0, 0, width, height)
            if px0 > px1 or py0 > py1:
                continue
            rects[c, i, 0] = px0 // tile
            rects[c, i, 1] = px1 // tile
            rects[c, i, 2] = py0 // tile
            rects[c, i, 3] = py1 // tile
            for ty in range(py0 // tile, py1 // tile + 1):
                for tx in range(px0 // tile, px1 // tile + 1):
                    counts[c * nt + ty * tx_n + tx] += 1
    offsets = np.zeros(c_count * nt + 1, np.int64)
    for j in range(c_count * nt):
        offsets[j + 1] = offsets[j] + counts[j]
    ids = np.empty(offsets[-1], np.int32)
    for c in prange(c_count):
        cursor = offsets[c * nt:(c + 1) * nt].copy()
        order = np.argsort(depths[c], kind="mergesort")  # stable, like the reference
        for i in order:
            if rects[c, i, 0] < 0:
                continue
            for ty in range(rects[c, i, 2], rects[c, i, 3] + 1):
                for tx in range(rects[c, i, 0], rects[c, i, 1] + 1):
                    t = ty * tx_n + tx
                    ids[cursor[t]] = i
                    cursor[t] += 1
    return offsets, ids


@njit(parallel=True, cache=True)
def _forward(means2d, conics, opac, chans, ext, bg, offsets, ids, width, height, tile):
    """-> out (C,H,W,F), t_final (C,H,W), n_contrib (C,H,W) int32 (list position past the last contributor)."""
    c_count, n, f = chans.shape
    tx_n = (width + tile - 1) // tile
    ty_n = (height + tile - 1) // tile
    nt = tx_n * ty_n
    out = np.empty((c_count, height, width, f), chans.dtype)
    t_final = np.empty((c_count, height, width), chans.dtype)
    n_contrib = np.zeros((c_count, height, width), np.int32)
    for job in prange(c_count * nt):
        c = job // nt
        t = job % nt
        x0 = (t % tx_n) * tile
        y0 = (t // tx_n) * tile
        x1 = min(x0 + tile, width)
        y1 = min(y0 + tile, height)
        tw = x1 - x0
        th = y1 - y0
        trans = np.ones((th, tw), chans.dtype)
        acc = np.zeros((th, tw, f), chans.dtype)
        done = np.zeros((th, tw), np.bool_)
        last = np.zeros((th, tw), np.int32)
        n_done = 0
        start = offsets[job]
        for k in range(start, offsets[job + 1]):
            if n_done == tw * th:
                break
            g = ids[k]
            mx = means2d[c, g, 0]
            my = means2d[c, g, 1]
            ca = conics[c, g, 0]
            cb = conics[c, g, 1]
            cc = conics[c, g, 2]
            o = opac[c, g]
            px0, px1, py0, py1 = _pixel_box(mx, my, ext[c, g, 0], ext[c, g, 1], x0, y0, x1, y1)
            for py in range(py0, py1 + 1):
                dy = my - (py + 0.5)
                ly = py - y0
                for px in range(px0, px1 + 1):
                    lx = px - x0
                    if done[ly, lx]:
                        continue
                    dx = mx - (px + 0.5)
                    m2 = ca * dx * dx + 2.0 * cb * dx * dy + cc * dy * dy
                    if m2 > MAHA_CUTOFF:
                        continue
                    alpha = min(ALPHA_MAX, o * math.exp(-0.5 * m2))
                    if alpha < ALPHA_MIN:
                        continue
                    t_next = trans[ly, lx] * (1.0 - alpha)
                    if t_next < T_MIN:
                        done[ly, lx] = True
                        n_done += 1
                        continue
                    w = alpha * trans[ly, lx]
                    for ch in range(f):
                        acc[ly, lx, ch] += w * chans[c, g, ch]
                    trans[ly, lx] = t_next
                    last[ly, lx] = k - start + 1
        for ly in range(th):
            for lx in range(tw):
                for ch in range(f):
                    out[c, y0 + ly, x0 + lx, ch] = acc[ly, lx, ch] + trans[ly, lx] * bg[ch]
                t_final[c, y0 + ly, x0 + lx] = trans[ly, lx]
                n_contrib[c, y0 + ly, x0 + lx] = last[ly, lx]
    return out, t_final, n_contrib


@njit(parallel=True, cache=True)
def _backward(means2d, conics, opac, chans, ext, bg, offsets, ids, t_final, n_contrib, g_out, g_alpha,
              width, height, tile):
    """Per-pair gradients: g_xy (P,2), g_conic (P,3), g_opac (P,), g_chan (P,F)."""
    c_count, n, f = chans.shape
    tx_n = (width + tile - 1) // tile
    ty_n = (height + tile - 1) // tile
    nt = tx_n * ty_n
    p_count = ids.shape[0]
    dt = chans.dtype
    g_xy = np.zeros((p_count, 2), dt)
    g_con = np.zeros((p_count, 3), dt)
    g_op = np.zeros(p_count, dt)
    g_ch = np.zeros((p_count, f), dt)
    for job in prange(c_count * nt):
        c = job // nt
        t = job % nt
        x0 = (t % tx_n) * tile
        y0 = (t // tx_n) * tile
        x1 = min(x0 + tile, width)
        y1 = min(y0 + tile, height)
        tw = x1 - x0
        th = y1 - y0
        start = offsets[job]
        trans = np.empty((th, tw), dt)
        accum = np.zeros((th, tw, f), dt)
        last_ch = np.zeros((th, tw, f), dt)
        last_alpha = np.zeros((th, tw), dt)
        bg_dot = np.zeros((th, tw), dt)
        max_n = 0
        for ly in range(th):
            for lx in range(tw):
                trans[ly, lx] = t_final[c, y0 + ly, x0 + lx]
                s = 0.0
                for ch in range(f):
                    s += bg[ch] * g_out[c, y0 + ly, x0 + lx, ch]
                bg_dot[ly, lx] = s
                max_n = max(max_n, n_contrib[c, y0 + ly, x0 + lx])
        for kk in range(max_n - 1, -1, -1):
            k = start + kk
            g = ids[k]
            mx = means2d[c, g, 0]
            my = means2d[c, g, 1]
            ca = conics[c, g, 0]
            cb = conics[c, g, 1]
            cc = conics[c, g, 2]
            o = opac[c, g]
            px0, px1, py0, py1 = _pixel_box(mx, my, ext[c, g, 0], ext[c, g, 1], x0, y0, x1, y1)
            for py in range(py0, py1 + 1):
                dy = my - (py + 0.5)
                ly = py - y0
                for px in range(px0, px1 + 1):
                    lx = px - x0
                    if kk >= n_contrib[c, py, px]:
                        continue
                    dx = mx - (px + 0.5)
                    m2 = ca * dx * dx + 2.0 * cb * dx * dy + cc * dy * dy
                    if m2 > MAHA_CUTOFF:
                        continue
                    gauss = math.exp(-0.5 * m2)
                    raw = o * gauss
                    alpha = min(ALPHA_MAX, raw)
                    if alpha < ALPHA_MIN:
                        continue
                    tr = trans[ly, lx] / (1.0 - alpha)
                    trans[ly, lx] = tr
                    d_alpha = 0.0
                    la = last_alpha[ly, lx]
                    for ch in range(f):
                        go = g_out[c, py, px, ch]
                        g_ch[k, ch] += alpha * tr * go
                        # colour of everything behind this Gaussian, as seen through it
                        accum[ly, lx, ch] = la * last_ch[ly, lx, ch] + (1.0 - la) * accum[ly, lx, ch]
                        last_ch[ly, lx, ch] = chans[c, g, ch]
                        d_alpha += (chans[c, g, ch] - accum[ly, lx, ch]) * go
                    d_alpha *= tr
                    last_alpha[ly, lx] = alpha
                    tf = t_final[c, py, px] / (1.0 - alpha)
                    d_alpha += tf * (g_alpha[c, py, px] - bg_dot[ly, lx])
                    if raw <= ALPHA_MAX:  # clamped alpha has no gradient
                        g_op[k] += gauss * d_alpha
                        d_m2 = -0.5 * raw * d_alpha
                        g_xy[k, 0] += d_m2 * 2.0 * (ca * dx + cb * dy)
                        g_xy[k, 1] += d_m2 * 2.0 * (cb * dx + cc * dy)
                        g_con[k, 0] += d_m2 * dx * dx
                        g_con[k, 1] += d_m2 * 2.0 * dx * dy
                        g_con[k, 2] += d_m2 * dy * dy
    return g_xy, g_con, g_op, g_ch


@njit(parallel=True, cache=True)
def _reduce(g_xy, g_con, g_op, g_ch, offsets, ids, c_count, n, nt):
    """Sum per-pair gradients into per-(camera, Gaussian) arrays."""
    f = g_ch.shape[1]
    dt = g_ch.dtype
    r_xy = np.zeros((c_count, n, 2), dt)
    r_con = np.zeros((c_count, n, 3), dt)
    r_op = np.zeros((c_count, n), dt)
    r_ch = np.zeros((c_count, n, f), dt)
    for c in prange(c_count):
        for k in range(offsets[c * nt], offsets[(c + 1) * nt]):
            g = ids[k]
            r_xy[c, g, 0] += g_xy[k, 0]
            r_xy[c, g, 1] += g_xy[k, 1]
            for j in range(3):
                r_con[c, g, j] += g_con[k, j]
            r_op[c, g] += g_op[k]
            for ch in range(f):
                r_ch[c, g, ch] += g_ch[k, ch]
    return r_xy, r_con, r_op, r_ch


def _np(t: torch.Tensor, dtype) -> np.ndarray:
    return np.ascontiguousarray(t.detach().cpu().numpy().astype(dtype, copy=False))


class _CompositeCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, chans, cov_diag, depths, valid, background, width, height, tile):
        dt = np.float64 if chans.dtype == torch.float64 else np.float32
        m2d, con, op, ch = _np(means2d, dt), _np(conics, dt), _np(opacities, dt), _np(chans, dt)
        bg = _np(background, dt)
        ext = _extents(_np(cov_diag, dt), op, _np(valid, np.bool_))
        offsets, ids = _bin(m2d, ext, _np(depths, dt), width, height, tile)
        out, t_final, n_contrib = _forward(m2d, con, op, ch, ext, bg, offsets, ids, width, height, tile)
        ctx.saved = (m2d, con, op, ch, ext, bg, offsets, ids, t_final, n_contrib, width, height, tile)
        ctx.torch_dtype = chans.dtype
        alpha = 1.0 - t_final[..., None]
        return torch.from_numpy(out), torch.from_numpy(alpha)

    @staticmethod
    def backward(ctx, g_out, g_alpha):
        m2d, con, op, ch, ext, bg, offsets, ids, t_final, n_contrib, width, height, tile = ctx.saved
        dt = ch.dtype
        c_count, n, _ = ch.shape
        g_out = _np(g_out, dt) if g_out is not None else np.zeros((c_count, height, width, ch.shape[2]), dt)
        g_alpha = _np(g_alpha[..., 0], dt) if g_alpha is not None else np.zeros((c_count, height, width), dt)
        pairs = _backward(m2d, con, op, ch, ext, bg, offsets, ids, t_final, n_contrib, g_out, g_alpha,
                          width, height, tile)
        nt = ((width + tile - 1) // tile) * ((height + tile - 1) // tile)
        r_xy, r_con, r_op, r_ch = _reduce(*pairs, offsets, ids, c_count, n, nt)
        # background gradient: d out / d bg = T_final
        g_bg = np.einsum("chw,chwf->f", t_final, g_out)
        as_t = lambda a: torch.from_numpy(a).to(ctx.torch_dtype)  # noqa: E731
        return (as_t(r_xy), as_t(r_con), as_t(r_op), as_t(r_ch), None, None, None, as_t(g_bg),
                None, None, None)


def composite_cpu(means2d, conics, opacities, chans, cov_diag, depths, valid, background, width: int, height: int,
                  tile: int = TILE):
    """Same contract as reference.composite_reference (plus cov_diag (C,N,2) for footprints):
    -> out (C,H,W,F), alpha (C,H,W,1), differentiable w.r.t. means2d, conics, opacities, chans, background."""
    chans = chans.contiguous()
    return _CompositeCPU.apply(means2d.contiguous(), conics.contiguous(), opacities.contiguous(), chans,
                               cov_diag, depths, valid, background.to(chans.dtype), int(width), int(height),
                               int(tile))


def set_threads(n: int) -> None:
    """Limit numba's worker threads (e.g. inside a service worker)."""
    numba.set_num_threads(max(1, min(int(n), numba.config.NUMBA_NUM_THREADS)))
