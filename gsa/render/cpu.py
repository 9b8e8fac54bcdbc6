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
import os
import threading

import numba
import numpy as np
import torch
from numba import njit, prange

from gsa.render.constants import ALPHA_MAX, ALPHA_MIN, EPS2D, MAHA_CUTOFF, NEAR, T_MIN

TILE = 16
_CHUNKS = 64  # work items per camera for loops over Gaussians (load balance across threads)

# numba's OpenMP layer shares libgomp with torch; on a busy machine spinning torch threads and
# descheduled numba threads make its barriers orders of magnitude slower. The built-in
# workqueue layer degrades gracefully. It must not be entered from two Python
# threads at once, hence _KERNEL_LOCK around every kernel call (the kernels use all cores anyway).
if "NUMBA_THREADING_LAYER" not in os.environ:
    numba.config.THREADING_LAYER = "workqueue"
_KERNEL_LOCK = threading.RLock()


@njit(cache=True, error_model="numpy")
def _pixel_box(mx, my, ex, ey, x0, y0, x1, y1):
    """Pixels (inclusive ranges) whose centres lie inside [m - e, m + e], clipped to a tile."""
    px0 = max(x0, int(math.ceil(mx - ex - 0.5)))
    px1 = min(x1 - 1, int(math.floor(mx + ex - 0.5)))
    py0 = max(y0, int(math.ceil(my - ey - 0.5)))
    py1 = min(y1 - 1, int(math.floor(my + ey - 0.5)))
    return px0, px1, py0, py1


@njit(cache=True, error_model="numpy")
def _radix_argsort(keys, sel, passes):
    """`sel` reordered by ascending unsigned `keys[sel]`, stable; 16 bits a pass (2 for uint32, 4 for uint64)."""
    m = sel.shape[0]
    cur = sel.copy()
    nxt = np.empty_like(cur)
    count = np.empty(65537, np.int64)
    for p in range(passes):
        shift = np.uint64(16 * p)  # unsigned throughout: numba turns uint64-int64 mixes into floats
        mask = np.uint64(0xFFFF)
        count[:] = 0
        for j in range(m):
            count[np.int64((np.uint64(keys[cur[j]]) >> shift) & mask) + 1] += 1
        if count[1:].max() == m:  # all keys share this digit: nothing to do
            continue
        for d in range(65536):
            count[d + 1] += count[d]
        for j in range(m):
            d = np.int64((np.uint64(keys[cur[j]]) >> shift) & mask)
            nxt[count[d]] = cur[j]
            count[d] += 1
        cur, nxt = nxt, cur
    return cur


# Packed per-pair record: the Gaussian's screen-space parameters, copied next to each other in
# tile order, so compositing reads memory sequentially instead of gathering from (C,N) arrays
# in depth order (those gathers were the compositing kernels' main cost). 8 values = 32 bytes
# in float32; channels stay in their (C,N,F) array (read only where a pixel is reached).
_R_X, _R_Y, _R_A, _R_B, _R_C, _R_O, _R_EX, _R_EY = range(8)
_R_LEN = 8


@njit(parallel=True, cache=True, error_model="numpy")
def _footprints(means2d, conics, cov_diag, opac, valid, width, height, tile):
    """Per (camera, Gaussian): its record (C,N,8) and tile rectangle (C,N,4) [tx0, tx1, ty0, ty1], -1 if culled.

    A pixel can only contribute where d² <= min(9, 2 ln(255 o)); the ellipse d^T Σ^-1 d <= t
    has half-widths sqrt(t Σ_xx), sqrt(t Σ_yy). A small margin keeps boundary pixels that the
    exact per-pixel tests then decide.
    """
    c_count, n = opac.shape
    grec = np.empty((c_count, n, _R_LEN), conics.dtype)
    rects = np.empty((c_count, n, 4), np.int32)
    chunk = (n + _CHUNKS - 1) // _CHUNKS
    for job in prange(c_count * _CHUNKS):
        c = job // _CHUNKS
        for i in range((job % _CHUNKS) * chunk, min(n, (job % _CHUNKS + 1) * chunk)):
            o = opac[c, i]
            rects[c, i, 0] = -1
            if not valid[c, i] or o * 255.0 < 1.0:
                continue
            # 2 ln(255 o) >= 9 from o >= e^4.5 / 255: skip the log for most Gaussians
            t = MAHA_CUTOFF if o >= 0.3531 else min(MAHA_CUTOFF, 2.0 * math.log(255.0 * o))
            t = t * 1.0001 + 1e-6
            ex = math.sqrt(t * cov_diag[c, i, 0])
            ey = math.sqrt(t * cov_diag[c, i, 1])
            r = grec[c, i]
            r[_R_X] = means2d[c, i, 0]
            r[_R_Y] = means2d[c, i, 1]
            r[_R_A] = conics[c, i, 0]
            r[_R_B] = conics[c, i, 1]
            r[_R_C] = conics[c, i, 2]
            r[_R_O] = o
            r[_R_EX] = ex
            r[_R_EY] = ey
            px0, px1, py0, py1 = _pixel_box(means2d[c, i, 0], means2d[c, i, 1], ex, ey, 0, 0, width, height)
            if px0 > px1 or py0 > py1:
                continue
            rects[c, i, 0] = px0 // tile
            rects[c, i, 1] = px1 // tile
            rects[c, i, 2] = py0 // tile
            rects[c, i, 3] = py1 // tile
    return grec, rects


_BIN_PARTS = 16  # slices of each camera's depth order, binned in parallel


@njit(parallel=True, cache=True, error_model="numpy")
def _depth_order(rects, depth_bits):
    """(C,N) int32: per camera, the binned Gaussians front to back (first m_c entries), and m (C,)."""
    c_count, n = depth_bits.shape
    order = np.empty((c_count, n), np.int32)
    m_count = np.zeros(c_count, np.int64)
    for c in prange(c_count):
        m = 0
        for i in range(n):
            if rects[c, i, 0] >= 0:
                m += 1
        sel = np.empty(m, np.int32)
        m = 0
        for i in range(n):
            if rects[c, i, 0] >= 0:
                sel[m] = i
                m += 1
        # binned Gaussians all have depth > 0, so the IEEE bit patterns order like the
        # values and an exact, stable LSD radix sort applies
        order[c, :m] = _radix_argsort(depth_bits[c], sel, depth_bits.itemsize // 2)
        m_count[c] = m
    return order, m_count


@njit(cache=True, error_model="numpy")
def _walk_slice(rects, order, m_count, c, s, tx_n, table, ids):
    """Visit the tiles of slice s of camera c's depth order: with an empty `ids`, count pairs per
    tile into table[c, s]; otherwise write each Gaussian at table[c, s, tile] (a cursor) and advance it."""
    parts = table.shape[1]
    span = (m_count[c] + parts - 1) // parts
    scatter = ids.shape[0] > 0
    row = table[c, s]
    for j in range(s * span, min(m_count[c], (s + 1) * span)):
        i = order[c, j]
        for ty in range(rects[c, i, 2], rects[c, i, 3] + 1):
            for tx in range(rects[c, i, 0], rects[c, i, 1] + 1):
                t = ty * tx_n + tx
                if scatter:
                    ids[row[t]] = i
                row[t] += 1


@njit(parallel=True, cache=True, error_model="numpy")
def _bin(rects, order, m_count, width, height, tile):
    """Per (camera, tile) lists of Gaussian ids sorted front to back.

    Returns offsets (C*T + 1,) int64 and ids (P,) int32; the list of job j is
    ids[offsets[j]:offsets[j+1]]. Each camera's depth order is cut into _BIN_PARTS slices that
    are counted and scattered in parallel; slice s of a tile's list precedes slice s + 1, so
    every list stays in depth order.
    """
    c_count = rects.shape[0]
    tx_n = (width + tile - 1) // tile
    ty_n = (height + tile - 1) // tile
    nt = tx_n * ty_n
    parts = _BIN_PARTS
    counts = np.zeros((c_count, parts, nt), np.int64)
    no_ids = np.empty(0, np.int32)
    for job in prange(c_count * parts):
        _walk_slice(rects, order, m_count, job // parts, job % parts, tx_n, counts, no_ids)
    offsets = np.zeros(c_count * nt + 1, np.int64)
    cursor = np.empty((c_count, parts, nt), np.int64)
    pos = 0
    for c in range(c_count):
        for t in range(nt):
            offsets[c * nt + t] = pos
            for s in range(parts):
                cursor[c, s, t] = pos
                pos += counts[c, s, t]
    offsets[c_count * nt] = pos
    ids = np.empty(pos, np.int32)
    for job in prange(c_count * parts):
        _walk_slice(rects, order, m_count, job // parts, job % parts, tx_n, cursor, ids)
    return offsets, ids


@njit(parallel=True, cache=True, error_model="numpy")
def _pack(grec, offsets, ids, nt):
    """recs (P, 8): each pair's Gaussian record, in list order."""
    c_count = grec.shape[0]
    rec_len = grec.shape[2]
    recs = np.empty((ids.shape[0], rec_len), grec.dtype)
    for job in prange(c_count * nt):
        c = job // nt
        for k in range(offsets[job], offsets[job + 1]):
            i = ids[k]
            for j in range(rec_len):
                recs[k, j] = grec[c, i, j]
    return recs


@njit(cache=True, error_model="numpy")
def _record(recs, k):
    """Pair k's record: mean x, y, conic a, b, c, opacity, half-extents x, y."""
    r = recs[k]
    return r[_R_X], r[_R_Y], r[_R_A], r[_R_B], r[_R_C], r[_R_O], r[_R_EX], r[_R_EY]


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


def _np(t: torch.Tensor, dtype) -> np.ndarray:
    return np.ascontiguousarray(t.detach().cpu().numpy().astype(dtype, copy=False))


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
        grec, rects = _footprints(m2d, con, _np(cov_diag, dt), op, _np(valid, np.bool_), width, height, tile)
        depth_bits = _np(depths, dt).view(np.uint64 if dt == np.float64 else np.uint32)
        order, m_count = _depth_order(rects, depth_bits)
        offsets, ids = _bin(rects, order, m_count, width, height, tile)
        c_count, n, _ = ch.shape
        nt = ((width + tile - 1) // tile) * ((height + tile - 1) // tile)
        recs = _pack(grec, offsets, ids, nt)
        out, t_final, n_contrib = _forward(recs, ids, ch, bg, offsets, width, height, tile)
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
        g_pair, g_ch = _backward(recs, ids, ch, bg, offsets, t_final, n_contrib, g_out, g_alpha, width, height, tile,
                                 want_chans)
        nt = ((width + tile - 1) // tile) * ((height + tile - 1) // tile)
        r_xy, r_con, r_op, r_ch = _reduce(g_pair, g_ch, offsets, ids, c_count, n, nt, max(1, numba.get_num_threads()))
        # background gradient: d out / d bg = T_final
        g_bg = np.einsum("chw,chwf->f", t_final, g_out)
        as_t = lambda a: torch.from_numpy(a).to(ctx.torch_dtype)  # noqa: E731
        return (as_t(r_xy), as_t(r_con), as_t(r_op), as_t(r_ch) if want_chans else None, None, None, None,
                as_t(g_bg),
                None, None, None)


def composite_cpu(means2d, conics, opacities, chans, cov_diag, depths, valid, background, width: int, height: int,
                  tile: int = TILE):
    """Same contract as reference.composite_reference (plus cov_diag (C,N,2) for footprints):
    -> out (C,H,W,F), alpha (C,H,W,1), differentiable w.r.t. means2d, conics, opacities, chans, background."""
    chans = chans.contiguous()
    return _CompositeCPU.apply(means2d.contiguous(), conics.contiguous(), opacities.contiguous(), chans,
                               cov_diag, depths, valid, background.to(chans.dtype), int(width), int(height),
                               int(tile))


def locality_order(points: np.ndarray, bits: int = 10) -> np.ndarray:
    """Permutation sorting points along a 3D Morton (Z-order) curve.

    Rendering does not depend on the Gaussians' order, but the kernels gather them in depth
    order per tile; with neighbours stored nearby those gathers hit the cache (packing the
    per-pair records takes about half as long). Worth it for a model rendered many times.
    """
    p = np.asarray(points, np.float64)
    if len(p) == 0:
        return np.zeros(0, np.int64)
    lo, hi = p.min(0), p.max(0)
    q = ((p - lo) / np.maximum(hi - lo, 1e-12) * ((1 << bits) - 1)).astype(np.uint64)
    code = np.zeros(len(p), np.uint64)
    for b in range(bits):
        for axis in range(3):
            code |= ((q[:, axis] >> np.uint64(b)) & np.uint64(1)) << np.uint64(3 * b + axis)
    return np.argsort(code, kind="stable")


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
        g_view, g_means, g_cov = _project_bwd(means, cov, view, intr, width, height, con, valid, g_m2d, g_con,
                                              g_depth, want_geom)
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
        gx = 2 * (y * gr[0, 1] + z * gr[0, 2] + y * gr[1, 0] - 2 * x * gr[1, 1] - w * gr[1, 2] + z * gr[2, 0]
                  + w * gr[2, 1] - 2 * x * gr[2, 2])
        gy = 2 * (-2 * y * gr[0, 0] + x * gr[0, 1] + w * gr[0, 2] + x * gr[1, 0] + z * gr[1, 2] - w * gr[2, 0]
                  + z * gr[2, 1] - 2 * y * gr[2, 2])
        gz = 2 * (-2 * z * gr[0, 0] - w * gr[0, 1] + x * gr[0, 2] + w * gr[1, 0] - 2 * z * gr[1, 1] + y * gr[1, 2]
                  + x * gr[2, 0] + y * gr[2, 1])
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
