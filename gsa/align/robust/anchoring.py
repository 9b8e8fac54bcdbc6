"""Anchors: a floater-free, voxel-downsampled summary of a model (mean position, CIELAB
colour, weight per voxel), the nearest-anchor grid that scores poses in O(1) per point, and
how far two models' palettes agree."""

from __future__ import annotations

from dataclasses import dataclass, field

import numba
import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from gsa.model import GaussianModel

# A colour of one model is "shared" when the other has one within this ΔE.
SHARED_DELTA_E = 8.0


@dataclass
class Anchors:
    """A voxel-downsampled, floater-free summary of a model."""

    points: np.ndarray  # (A, 3) float64, model units
    lab: np.ndarray  # (A, 3) CIELAB colour
    weights: np.ndarray  # (A,) Gaussians per anchor (normalised to mean 1)
    center: np.ndarray  # (3,) weighted centroid
    radius: float  # weighted RMS distance from the centroid
    kept: np.ndarray  # (N,) bool: Gaussians that are not floaters
    tree: cKDTree = field(repr=False)

    def __len__(self) -> int:
        return len(self.points)


def srgb_to_lab(rgb: np.ndarray) -> np.ndarray:
    """sRGB in [0, 1] -> CIELAB (D65): distances approximate perceived differences."""
    c = np.clip(np.asarray(rgb, np.float64), 0.0, 1.0)
    lin = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
    m = np.array(
        [[0.4124564, 0.3575761, 0.1804375], [0.2126729, 0.7151522, 0.0721750], [0.0193339, 0.1191920, 0.9503041]]
    )
    xyz = lin @ m.T / np.array([0.95047, 1.0, 1.08883])
    f = np.where(xyz > (6 / 29) ** 3, np.cbrt(xyz), xyz / (3 * (6 / 29) ** 2) + 4 / 29)
    return np.stack([116 * f[:, 1] - 16, 500 * (f[:, 0] - f[:, 1]), 200 * (f[:, 1] - f[:, 2])], axis=1)


def floater_mask(model: GaussianModel) -> np.ndarray:
    """Gaussians worth trusting for geometry: opacity at least half the model's
    median (faint floaters go), the rest judged by density in `anchors`."""
    o = model.opacities
    keep = o >= 0.5 * float(np.median(o))
    return keep if keep.sum() >= 3 else np.ones(len(model), bool)


def anchors(model: GaussianModel, count: int = 2000, seed: int = 0) -> Anchors:
    """Voxel-downsample the model to about `count` anchors, dropping floaters.

    The voxel size is found from the model's own extent (a surface's voxel count
    grows as size⁻²), so the same object at any scale gets comparable anchors.
    Voxels holding far fewer Gaussians than a typical surface voxel are floaters
    spread through space (an unpruned capture), not surface."""
    pts = model.means.astype(np.float64)
    kept = floater_mask(model)
    x = pts[kept]
    rgb = model.base_colors[kept]
    lo, hi = x.min(0), x.max(0)
    extent = float(np.max(hi - lo))
    if not extent > 0:
        raise ValueError("all Gaussians coincide; the model has no extent to align")
    voxel = extent / np.sqrt(count)
    for _ in range(4):
        keys, inverse, counts = _voxelise(x, lo, voxel)
        occupied = len(counts)
        if 0.7 * count <= occupied <= 1.4 * count or occupied >= len(x) * 0.9:
            break
        voxel *= np.sqrt(occupied / count)
    # Surface voxels hold many Gaussians; a floater's voxel one or two.
    typical = float(np.median(np.repeat(counts, counts)))
    solid = counts >= max(2.0, 0.1 * typical) if typical >= 8 else np.ones(len(counts), bool)
    if solid.sum() < 4:
        solid = np.ones(len(counts), bool)
    gaussian_solid = solid[inverse]
    full_kept = kept.copy()
    full_kept[np.flatnonzero(kept)[~gaussian_solid]] = False
    n_vox = len(counts)
    sums = np.zeros((n_vox, 3))
    np.add.at(sums, inverse, x)
    csum = np.zeros((n_vox, 3))
    np.add.at(csum, inverse, rgb)
    points = (sums / counts[:, None])[solid]
    colours = (csum / counts[:, None])[solid]
    weights = counts[solid].astype(np.float64)
    weights /= weights.mean()
    w = weights / weights.sum()
    center = w @ points
    radius = float(np.sqrt(w @ np.sum((points - center) ** 2, axis=1)))
    if not radius > 0:
        raise ValueError("all Gaussians coincide; the model has no extent to align")
    return Anchors(points, srgb_to_lab(colours), weights, center, radius, full_kept, cKDTree(points))


def _voxelise(x: np.ndarray, lo: np.ndarray, voxel: float):
    ijk = np.floor((x - lo) / voxel).astype(np.int64)
    span = ijk.max(0) + 1
    keys = (ijk[:, 0] * span[1] + ijk[:, 1]) * span[2] + ijk[:, 2]
    uniq, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
    return uniq, inverse.ravel(), counts


class NearestGrid:
    """Nearest-anchor index for every cell of a grid around a point set (exact
    Euclidean distance transform): a scoring lookup in O(1) per point, so
    thousands of candidate rotations are scored in one vectorised pass."""

    def __init__(self, points: np.ndarray, cell: float, pad: float):
        self.points = points
        self.lo = points.min(0) - pad
        self.cell = cell
        shape = np.ceil((points.max(0) + pad - self.lo) / cell).astype(int) + 1
        self.shape = shape
        ijk = np.floor((points - self.lo) / cell).astype(int)
        owner = np.full(tuple(shape), -1, np.int64)
        owner[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = np.arange(len(points))
        _, nearest = ndimage.distance_transform_edt(owner < 0, return_indices=True)
        self.nearest_flat = np.ascontiguousarray(owner[nearest[0], nearest[1], nearest[2]].ravel())
        self.shape = np.asarray(shape, np.int64)

    def lookup(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(..., 3) points -> (nearest anchor index, distance); outside the grid: index -1, distance inf."""
        ijk = ((x - self.lo) * (1.0 / self.cell)).astype(np.int32)  # truncation = floor inside the grid
        inside = np.all((ijk >= 0) & (ijk < self.shape) & (x >= self.lo), axis=-1)
        flat = (ijk[..., 0] * self.shape[1] + ijk[..., 1]) * self.shape[2] + ijk[..., 2]
        idx = self.nearest_flat[np.where(inside, flat, 0)]
        diff = self.points[idx] - x
        d = np.sqrt(np.einsum("...i,...i->...", diff, diff))
        return np.where(inside, idx, -1), np.where(inside, d, np.inf)


def colour_weight(src: Anchors, dst: Anchors) -> float:
    """How far colour can be trusted to compare poses, from the colours alone (no
    pose): two captures of one object share their palette, and then colour is what
    tells a symmetric object's sides apart; two different instances (another paint)
    do not, and then only geometry counts. Fraction of each model's anchors with a
    colour the other also has, both ways, mapped from [0.5, 0.9] to [0, 1]."""
    d1, _ = cKDTree(dst.lab).query(src.lab, k=1)
    d2, _ = cKDTree(src.lab).query(dst.lab, k=1)
    shared = 0.5 * (
        np.average(d1 <= SHARED_DELTA_E, weights=src.weights) + np.average(d2 <= SHARED_DELTA_E, weights=dst.weights)
    )
    return float(np.clip((shared - 0.5) / 0.4, 0.0, 1.0))


@numba.njit(cache=True, inline="always")
def grid_index(x0, x1, x2, lo, inv_cell, shape):  # pragma: no cover - compiled
    """Flat cell index of a point in a NearestGrid's lattice, −1 outside it (numba)."""
    f0, f1, f2 = (x0 - lo[0]) * inv_cell, (x1 - lo[1]) * inv_cell, (x2 - lo[2]) * inv_cell
    if f0 < 0 or f1 < 0 or f2 < 0 or f0 >= shape[0] or f1 >= shape[1] or f2 >= shape[2]:
        return -1
    return (int(f0) * shape[1] + int(f1)) * shape[2] + int(f2)


def _sample(rng: np.random.Generator, n: int, k: int) -> np.ndarray:
    return np.arange(n) if k >= n else np.sort(rng.choice(n, k, replace=False))
