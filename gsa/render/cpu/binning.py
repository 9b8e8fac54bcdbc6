"""Tile binning for the CPU compositor: per-Gaussian footprints and records, depth order
(exact radix sort), per-(camera, tile) lists, records packed in list order; and the Morton
order that keeps a model's Gaussians cache-friendly for these gathers."""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from gsa.render.constants import MAHA_CUTOFF
from gsa.render.cpu.common import _CHUNKS


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
