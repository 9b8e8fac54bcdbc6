"""Our SOG writer (PlayCanvas "spatially ordered Gaussians", meta.json version 2).

A zip of meta.json and lossless WebP images, one texel per Gaussian in Morton order:
means_l/means_u (16-bit positions after a symmetric log, per-axis range in meta.json),
quats (smallest-three, 8 bits per kept component, mode 252..255 in alpha), scales and sh0
(indices into 256-entry codebooks; sh0's alpha is the opacity), and for SH degree ≥ 1 a
palette: shN_centroids (64 entries per row, one texel per coefficient, codebook indices)
and shN_labels (16-bit palette index in red/green). Layout as in PlayCanvas's format
specification and gaussforge's own writer, whose reader and Spark's open our files.

gaussforge 0.6's writer grows superlinearly (200 s for 100k Gaussians); this one is
bounded: the SH palette is k-means on a subsample (at most PALETTE_SIZE entries, a fixed
number of iterations), then nearest-centroid assignment of every Gaussian in chunks of
matrix products; the 1-D codebooks are half evenly spaced, half quantiles. A model of at
most PALETTE_SIZE Gaussians gets one palette entry each (no clustering error).
"""

from __future__ import annotations

import io
import json
import math
import zipfile

import numpy as np

from gsa.model import GaussianModel

PALETTE_SIZE = 4096  # SH palette entries at most (the format allows 65536)
PALETTE_SAMPLE = 65536  # Gaussians the palette's k-means sees
PALETTE_ITERATIONS = 6
ASSIGN_CHUNK = 16384
SEED = 0


def _webp(img: np.ndarray) -> bytes:
    """Lossless WebP of an RGB or RGBA uint8 image (OpenCV wants BGR order)."""
    import cv2  # lazy, as elsewhere

    bgr = img[..., [2, 1, 0, 3]] if img.shape[2] == 4 else img[..., ::-1]
    ok, buf = cv2.imencode(".webp", np.ascontiguousarray(bgr), [cv2.IMWRITE_WEBP_QUALITY, 101])
    if not ok:
        raise ValueError("OpenCV could not encode a WebP image")
    return buf.tobytes()


def _codebook(values: np.ndarray, size: int = 256) -> tuple[np.ndarray, np.ndarray]:
    """A sorted 1-D codebook of `size` entries and each value's uint8 index: half the entries
    spaced evenly over the range (the largest error is at most range / (size - 2)), half at
    the values' quantiles (finer where values are dense)."""
    flat = np.asarray(values, np.float64).ravel()
    lo, hi = float(flat.min()), float(flat.max())
    even = np.linspace(lo, hi, size // 2)
    dense = np.quantile(flat, (np.arange(size - size // 2) + 0.5) / (size - size // 2))
    book = np.sort(np.concatenate([even, dense])).astype(np.float32)
    index = np.searchsorted((book[1:].astype(np.float64) + book[:-1]) / 2, flat).astype(np.uint8)
    return book, index.reshape(np.shape(values))


def _nearest(x: np.ndarray, centroids: np.ndarray) -> np.ndarray:
    """Index of each row's nearest centroid (squared distance), in chunks of matrix products."""
    c_sq = (centroids.astype(np.float32) ** 2).sum(1)
    ct = np.ascontiguousarray(centroids.T, np.float32)
    out = np.empty(len(x), np.int64)
    for s in range(0, len(x), ASSIGN_CHUNK):
        d = x[s : s + ASSIGN_CHUNK] @ ct
        d *= -2
        d += c_sq
        out[s : s + ASSIGN_CHUNK] = d.argmin(1)
    return out


def _palette(vectors: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """k-means palette of at most `size` entries (a multiple of 64) and each vector's label."""
    n = len(vectors)
    if n <= size:
        return vectors.copy(), np.arange(n)
    rng = np.random.default_rng(SEED)
    sample = vectors[rng.choice(n, min(n, PALETTE_SAMPLE), replace=False)]
    centroids = sample[rng.choice(len(sample), size, replace=False)].copy()
    for _ in range(PALETTE_ITERATIONS):
        labels = _nearest(sample, centroids)
        counts = np.bincount(labels, minlength=size)
        sums = np.zeros_like(centroids, dtype=np.float64)
        np.add.at(sums, labels, sample)
        filled = counts > 0
        centroids[filled] = (sums[filled] / counts[filled, None]).astype(np.float32)
        empty = np.flatnonzero(~filled)  # reseed with the sample's worst-fitting vectors
        if len(empty):
            err = ((sample - centroids[labels]) ** 2).sum(1)
            centroids[empty] = sample[np.argsort(err)[-len(empty) :]]
    return centroids, _nearest(vectors, centroids)


def _morton_order(q: np.ndarray) -> np.ndarray:
    """Gaussians sorted along a 3-D Morton curve of their 10-bit quantised positions."""

    def spread(v: np.ndarray) -> np.ndarray:
        v = v.astype(np.uint64) & 0x3FF
        v = (v | (v << 16)) & 0x030000FF
        v = (v | (v << 8)) & 0x0300F00F
        v = (v | (v << 4)) & 0x030C30C3
        return (v | (v << 2)) & 0x09249249

    code = spread(q[:, 0] >> 6) | (spread(q[:, 1] >> 6) << 1) | (spread(q[:, 2] >> 6) << 2)
    return np.argsort(code, kind="stable")


def encode_sog(model: GaussianModel) -> bytes:
    """A .sog archive (bytes) of a model in the file's own axes (RDF: no change)."""
    n = len(model)
    width = max(4, math.ceil(math.sqrt(n) / 4) * 4)
    height = max(4, math.ceil(n / width / 4) * 4)

    def image(channels: list[np.ndarray], fill: int = 0) -> np.ndarray:
        img = np.full((width * height, len(channels)), fill, np.uint8)
        for i, ch in enumerate(channels):
            img[:n, i] = ch
        return img.reshape(height, width, len(channels))

    means = model.means.astype(np.float64)
    logged = np.sign(means) * np.log1p(np.abs(means))
    mins, maxs = logged.min(0), logged.max(0)
    span = np.where(maxs > mins, maxs - mins, 1.0)
    q = np.clip(np.rint((logged - mins) / span * 65535), 0, 65535).astype(np.uint32)
    order = _morton_order(q)
    q = q[order]
    files = {
        "means_l.webp": image([q[:, i] & 0xFF for i in range(3)]),
        "means_u.webp": image([q[:, i] >> 8 for i in range(3)]),
    }

    quats = model.quats[order].astype(np.float64)
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    largest = np.abs(quats).argmax(1)
    quats *= np.where(quats[np.arange(n), largest] < 0, -1.0, 1.0)[:, None]
    kept = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])[largest]
    three = np.take_along_axis(quats, kept, 1) * math.sqrt(2)
    three = np.clip(np.rint((three * 0.5 + 0.5) * 255), 0, 255).astype(np.uint8)
    files["quats.webp"] = image([three[:, 0], three[:, 1], three[:, 2], 252 + largest], fill=252)

    scale_book, scale_idx = _codebook(model.log_scales[order])
    files["scales.webp"] = image([scale_idx[:, i] for i in range(3)])

    dc_book, dc_idx = _codebook(model.sh[order, 0])
    # Lossless WebP drops the colour of fully transparent texels: opacity is at least 1/255.
    alpha = np.clip(np.rint(model.opacities[order].astype(np.float64) * 255), 1, 255)
    files["sh0.webp"] = image([dc_idx[:, 0], dc_idx[:, 1], dc_idx[:, 2], alpha])

    meta = {
        "version": 2,
        "asset": {"generator": "gsa"},
        "count": n,
        "antialias": False,
        "means": {"mins": mins.tolist(), "maxs": maxs.tolist(), "files": ["means_l.webp", "means_u.webp"]},
        "scales": {"codebook": scale_book.tolist(), "files": ["scales.webp"]},
        "quats": {"files": ["quats.webp"]},
        "sh0": {"codebook": dc_book.tolist(), "files": ["sh0.webp"]},
    }

    coeffs = model.sh.shape[1] - 1
    if coeffs > 0:
        rest = np.ascontiguousarray(model.sh[order, 1:], np.float32).reshape(n, coeffs * 3)
        centroids, labels = _palette(rest, PALETTE_SIZE)
        count = math.ceil(len(centroids) / 64) * 64
        sh_book, sh_idx = _codebook(centroids)
        rows = np.zeros((count, coeffs, 3), np.uint8)
        rows[: len(centroids)] = sh_idx.reshape(-1, coeffs, 3)
        files["shN_centroids.webp"] = rows.reshape(count // 64, 64 * coeffs, 3)
        files["shN_labels.webp"] = image([labels & 0xFF, labels >> 8, np.zeros(n, np.uint8)])
        meta["shN"] = {
            "count": count,
            "bands": model.sh_degree,
            "codebook": sh_book.tolist(),
            "files": ["shN_centroids.webp", "shN_labels.webp"],
        }

    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_STORED) as zf:  # WebP is compressed already
        for name, img in files.items():
            zf.writestr(name, _webp(img))
        zf.writestr("meta.json", json.dumps(meta))
    return out.getvalue()
