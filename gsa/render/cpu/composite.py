"""Front-to-back compositing and its hand-written back-to-front backward, as a torch.autograd.Function."""

from __future__ import annotations

import math

import numba
import numpy as np
import torch
from numba import njit, prange

from gsa.render.constants import ALPHA_MAX, ALPHA_MIN, MAHA_CUTOFF, T_MIN
from gsa.render.cpu.binning import _bin, _depth_order, _footprints, _pack, _pixel_box, _record
from gsa.render.cpu.common import _KERNEL_LOCK, TILE, _np
from gsa.render.steps import step


@njit(parallel=True, cache=True, error_model="numpy")
def _forward(recs, ids, chans, bg, offsets, width, height, tile):
    """-> out (C,H,W,F), t_final (C,H,W), n_contrib (C,H,W) int32 (list position past the last contributor)."""
    c_count, n, f = chans.shape
    tx_n = (width + tile - 1) // tile
    ty_n = (height + tile - 1) // tile
    nt = tx_n * ty_n
    dt = recs.dtype
    out = np.empty((c_count, height, width, f), dt)
    t_final = np.empty((c_count, height, width), dt)
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
        trans = np.ones(th * tw, dt)
        acc = np.zeros((th * tw, f), dt)
        done = np.zeros(th * tw, np.bool_)
        last = np.zeros(th * tw, np.int32)
        n_done = 0
        start = offsets[job]
        for k in range(start, offsets[job + 1]):
            if n_done == tw * th:
                break
            mx, my, ca, cb, cc, o, ex, ey = _record(recs, k)
            col = chans[c, ids[k]]
            px0, px1, py0, py1 = _pixel_box(mx, my, ex, ey, x0, y0, x1, y1)
            for py in range(py0, py1 + 1):
                dy = my - (py + 0.5)
                row = (py - y0) * tw - x0
                for px in range(px0, px1 + 1):
                    lp = row + px
                    if done[lp]:
                        continue
                    dx = mx - (px + 0.5)
                    m2 = ca * dx * dx + 2.0 * cb * dx * dy + cc * dy * dy
                    if m2 > MAHA_CUTOFF:
                        continue
                    alpha = min(ALPHA_MAX, o * math.exp(-0.5 * m2))
                    if alpha < ALPHA_MIN:
                        continue
                    tr = trans[lp]
                    t_next = tr * (1.0 - alpha)
                    if t_next < T_MIN:
                        done[lp] = True
                        n_done += 1
                        continue
                    w = alpha * tr
                    for ch in range(f):
                        acc[lp, ch] += w * col[ch]
                    trans[lp] = t_next
                    last[lp] = k - start + 1
        for ly in range(th):
            for lx in range(tw):
                lp = ly * tw + lx
                for ch in range(f):
                    out[c, y0 + ly, x0 + lx, ch] = acc[lp, ch] + trans[lp] * bg[ch]
                t_final[c, y0 + ly, x0 + lx] = trans[lp]
                n_contrib[c, y0 + ly, x0 + lx] = last[lp]
    return out, t_final, n_contrib


@njit(parallel=True, cache=True, error_model="numpy")
def _backward(recs, ids, chans, bg, offsets, t_final, n_contrib, g_out, g_alpha, width, height, tile, want_chans):
    """Per-pair gradients: g_pair (P,6) [x, y, conic a, b, c, opacity], g_chan (P,F) (zero-size unless want_chans)."""
    c_count, n, f = chans.shape
    tx_n = (width + tile - 1) // tile
    ty_n = (height + tile - 1) // tile
    nt = tx_n * ty_n
    p_count = recs.shape[0]
    dt = recs.dtype
    g_pair = np.zeros((p_count, 6), dt)
    g_ch = np.zeros((p_count if want_chans else 0, f), dt)
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
        npx = th * tw
        trans = np.empty(npx, dt)
        tfin = np.empty(npx, dt)
        ncon = np.empty(npx, np.int32)
        accum = np.zeros((npx, f), dt)
        last_ch = np.zeros((npx, f), dt)
        gout = np.empty((npx, f), dt)
        last_alpha = np.zeros(npx, dt)
        alpha_term = np.empty(npx, dt)
        max_n = 0
        for ly in range(th):
            for lx in range(tw):
                lp = ly * tw + lx
                tfin[lp] = t_final[c, y0 + ly, x0 + lx]
                trans[lp] = tfin[lp]
                ncon[lp] = n_contrib[c, y0 + ly, x0 + lx]
                s = 0.0
                for ch in range(f):
                    gout[lp, ch] = g_out[c, y0 + ly, x0 + lx, ch]
                    s += bg[ch] * gout[lp, ch]
                alpha_term[lp] = g_alpha[c, y0 + ly, x0 + lx] - s
                max_n = max(max_n, ncon[lp])
        for kk in range(max_n - 1, -1, -1):
            k = start + kk
            mx, my, ca, cb, cc, o, ex, ey = _record(recs, k)
            colv = chans[c, ids[k]]
            px0, px1, py0, py1 = _pixel_box(mx, my, ex, ey, x0, y0, x1, y1)
            gx = 0.0
            gy = 0.0
            ga = 0.0
            gb = 0.0
            gc = 0.0
            go_ = 0.0
            for py in range(py0, py1 + 1):
                dy = my - (py + 0.5)
                row = (py - y0) * tw - x0
                for px in range(px0, px1 + 1):
                    lp = row + px
                    if kk >= ncon[lp]:
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
                    inv = 1.0 / (1.0 - alpha)
                    tr = trans[lp] * inv
                    trans[lp] = tr
                    d_alpha = 0.0
                    la = last_alpha[lp]
                    for ch in range(f):
                        go = gout[lp, ch]
                        col = colv[ch]
                        if want_chans:
                            g_ch[k, ch] += alpha * tr * go
                        # colour of everything behind this Gaussian, as seen through it
                        acc = la * last_ch[lp, ch] + (1.0 - la) * accum[lp, ch]
                        accum[lp, ch] = acc
                        last_ch[lp, ch] = col
                        d_alpha += (col - acc) * go
                    d_alpha = d_alpha * tr + tfin[lp] * inv * alpha_term[lp]
                    last_alpha[lp] = alpha
                    if raw <= ALPHA_MAX:  # clamped alpha has no gradient
                        go_ += gauss * d_alpha
                        d_m2 = -0.5 * raw * d_alpha
                        gx += d_m2 * 2.0 * (ca * dx + cb * dy)
                        gy += d_m2 * 2.0 * (cb * dx + cc * dy)
                        ga += d_m2 * dx * dx
                        gb += d_m2 * 2.0 * dx * dy
                        gc += d_m2 * dy * dy
            g_pair[k, 0] = gx
            g_pair[k, 1] = gy
            g_pair[k, 2] = ga
            g_pair[k, 3] = gb
            g_pair[k, 4] = gc
            g_pair[k, 5] = go_
    return g_pair, g_ch


@njit(parallel=True, cache=True, error_model="numpy")
def _reduce(g_pair, g_ch, offsets, ids, c_count, n, nt, parts):
    """Sum per-pair gradients into per-(camera, Gaussian) arrays (r_ch is zero-size if g_ch is).

    Work item (camera, part) scans that camera's pairs and keeps the Gaussians of its own
    id range, so no two items write the same element and all threads have work even for C = 1.
    """
    f = g_ch.shape[1]
    want_chans = g_ch.shape[0] > 0
    dt = g_pair.dtype
    r_xy = np.zeros((c_count, n, 2), dt)
    r_con = np.zeros((c_count, n, 3), dt)
    r_op = np.zeros((c_count, n), dt)
    r_ch = np.zeros((c_count if want_chans else 0, n, f), dt)
    span = (n + parts - 1) // parts
    for job in prange(c_count * parts):
        c = job // parts
        lo = (job % parts) * span
        hi = lo + span
        for k in range(offsets[c * nt], offsets[(c + 1) * nt]):
            g = ids[k]
            if g < lo or g >= hi:
                continue
            r_xy[c, g, 0] += g_pair[k, 0]
            r_xy[c, g, 1] += g_pair[k, 1]
            r_con[c, g, 0] += g_pair[k, 2]
            r_con[c, g, 1] += g_pair[k, 3]
            r_con[c, g, 2] += g_pair[k, 4]
            r_op[c, g] += g_pair[k, 5]
            if want_chans:
                for ch in range(f):
                    r_ch[c, g, ch] += g_ch[k, ch]
    return r_xy, r_con, r_op, r_ch


class _CompositeCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, *args):
        with _KERNEL_LOCK:
            return _CompositeCPU._forward(ctx, *args)

    @staticmethod
    def backward(ctx, *grads):
        with _KERNEL_LOCK:
            return _CompositeCPU._backward(ctx, *grads)

    @staticmethod
    def _forward(ctx, means2d, conics, opacities, chans, cov_diag, depths, valid, background, width, height, tile):
        dt = np.float64 if chans.dtype == torch.float64 else np.float32
        m2d, con, op, ch = _np(means2d, dt), _np(conics, dt), _np(opacities, dt), _np(chans, dt)
        bg = _np(background, dt)
        # step(): between the kernels, a caller's callback (gsa.render.steps; it may raise)
        step()
        grec, rects = _footprints(m2d, con, _np(cov_diag, dt), op, _np(valid, np.bool_), width, height, tile)
        step()
        depth_bits = _np(depths, dt).view(np.uint64 if dt == np.float64 else np.uint32)
        order, m_count = _depth_order(rects, depth_bits)
        step()
        offsets, ids = _bin(rects, order, m_count, width, height, tile)
        step()
        c_count, n, _ = ch.shape
        nt = ((width + tile - 1) // tile) * ((height + tile - 1) // tile)
        recs = _pack(grec, offsets, ids, nt)
        step()
        out, t_final, n_contrib = _forward(recs, ids, ch, bg, offsets, width, height, tile)
        step()
        ctx.saved = (recs, ch, bg, offsets, ids, t_final, n_contrib, n, width, height, tile)
        ctx.torch_dtype = chans.dtype
        alpha = 1.0 - t_final[..., None]
        return torch.from_numpy(out), torch.from_numpy(alpha)

    @staticmethod
    def _backward(ctx, g_out, g_alpha):
        recs, ch, bg, offsets, ids, t_final, n_contrib, n, width, height, tile = ctx.saved
        dt = recs.dtype
        c_count = t_final.shape[0]
        f = ch.shape[2]
        g_out = _np(g_out, dt) if g_out is not None else np.zeros((c_count, height, width, f), dt)
        g_alpha = _np(g_alpha[..., 0], dt) if g_alpha is not None else np.zeros((c_count, height, width), dt)
        want_chans = bool(ctx.needs_input_grad[3])
        step()  # gsa.render.steps, as in the forward
        g_pair, g_ch = _backward(
            recs, ids, ch, bg, offsets, t_final, n_contrib, g_out, g_alpha, width, height, tile, want_chans
        )
        step()
        nt = ((width + tile - 1) // tile) * ((height + tile - 1) // tile)
        r_xy, r_con, r_op, r_ch = _reduce(g_pair, g_ch, offsets, ids, c_count, n, nt, max(1, numba.get_num_threads()))
        step()
        # background gradient: d out / d bg = T_final
        g_bg = np.einsum("chw,chwf->f", t_final, g_out)
        as_t = lambda a: torch.from_numpy(a).to(ctx.torch_dtype)  # noqa: E731
        return (
            as_t(r_xy),
            as_t(r_con),
            as_t(r_op),
            as_t(r_ch) if want_chans else None,
            None,
            None,
            None,
            as_t(g_bg),
            None,
            None,
            None,
        )


def composite_cpu(
    means2d, conics, opacities, chans, cov_diag, depths, valid, background, width: int, height: int, tile: int = TILE
):
    """Same contract as reference.composite_reference (plus cov_diag (C,N,2) for footprints):
    -> out (C,H,W,F), alpha (C,H,W,1), differentiable w.r.t. means2d, conics, opacities, chans, background."""
    chans = chans.contiguous()
    return _CompositeCPU.apply(
        means2d.contiguous(),
        conics.contiguous(),
        opacities.contiguous(),
        chans,
        cov_diag,
        depths,
        valid,
        background.to(chans.dtype),
        int(width),
        int(height),
        int(tile),
    )
